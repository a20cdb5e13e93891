"""CenterNet-style outputs -> detections, and the targets they are trained on (pure NumPy/torch, no network).

Per object class the localiser predicts a centre heatmap; at each peak the box size (log width and height in
image pixels) and a sub-cell offset of the centre. A detection is a local maximum of the heatmap (3x3 max-pool
NMS, as CenterNet) above a score threshold.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F


@dataclass(frozen=True)
class Detection:
    obj_id: int
    score: float
    center: tuple[float, float]
    """Box centre in image pixels (x, y)."""
    size: tuple[float, float]
    """Box width and height in image pixels."""

    @property
    def box(self) -> tuple[float, float, float, float]:
        """(x, y, w, h)."""
        return (self.center[0] - self.size[0] / 2, self.center[1] - self.size[1] / 2, self.size[0], self.size[1])


def decode(
    heatmap: torch.Tensor,
    log_size: torch.Tensor,
    offset: torch.Tensor,
    obj_ids: list[int],
    stride: float,
    threshold: float = 0.3,
    max_per_object: int = 5,
) -> list[list[Detection]]:
    """Detections per batch item from heatmaps (B,C,h,w) in [0,1], log box sizes (B,2,h,w) in image pixels and
    centre offsets (B,2,h,w) in cells; `stride` maps cells to image pixels (cell (i, j) covers pixels stride*j ... stride*(j+1))."""
    if heatmap.ndim != 4 or heatmap.shape[1] != len(obj_ids):
        raise ValueError(f"heatmap must be (B, {len(obj_ids)}, h, w), got {tuple(heatmap.shape)}")
    peaks = heatmap * (F.max_pool2d(heatmap, 3, stride=1, padding=1) == heatmap)
    b, c, h, w = heatmap.shape
    out: list[list[Detection]] = []
    for i in range(b):
        dets: list[Detection] = []
        for k in range(c):
            scores, idx = peaks[i, k].flatten().topk(min(max_per_object, h * w))
            for s, j in zip(scores.tolist(), idx.tolist(), strict=True):
                if s < threshold:
                    break
                y, x = divmod(j, w)
                cx = (x + 0.5 + float(offset[i, 0, y, x])) * stride
                cy = (y + 0.5 + float(offset[i, 1, y, x])) * stride
                size = (float(np.exp(float(log_size[i, 0, y, x]))), float(np.exp(float(log_size[i, 1, y, x]))))
                dets.append(Detection(obj_ids[k], s, (cx, cy), size))
        out.append(sorted(dets, key=lambda d: -d.score))
    return out


def draw_targets(
    boxes: list[tuple[int, tuple[float, float, float, float]]],
    n_classes: int,
    shape: tuple[int, int],
    stride: float,
    weights: list[float] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Training targets for (class index, (x, y, w, h) in input pixels) boxes on an (h, w) output grid:
    heatmap (C,h,w) with a Gaussian per centre (σ a sixth of the box's shorter side in cells, at least 0.8),
    log size (2,h,w) in image pixels, offset (2,h,w) and the mask (h,w) of the centre cells where size, offset
    and the heatmap's peak are supervised, holding each box's weight (default 1; the larger where boxes share a
    cell)."""
    if weights is not None and len(weights) != len(boxes):
        raise ValueError(f"{len(weights)} weights for {len(boxes)} boxes")
    h, w = shape
    heat = np.zeros((n_classes, h, w), np.float32)
    log_size = np.zeros((2, h, w), np.float32)
    offset = np.zeros((2, h, w), np.float32)
    mask = np.zeros((h, w), np.float32)
    ys, xs = np.mgrid[0:h, 0:w]
    for k, (cls, (x, y, bw, bh)) in enumerate(boxes):
        cx, cy = (x + bw / 2) / stride, (y + bh / 2) / stride
        j, i = int(np.floor(cx)), int(np.floor(cy))
        if not (0 <= i < h and 0 <= j < w) or bw <= 0 or bh <= 0:
            continue
        sigma = max(min(bw, bh) / stride / 6, 0.8)
        g = np.exp(-((xs + 0.5 - cx) ** 2 + (ys + 0.5 - cy) ** 2) / (2 * sigma**2))
        heat[cls] = np.maximum(heat[cls], g)
        heat[cls, i, j] = 1.0
        log_size[:, i, j] = (np.log(bw), np.log(bh))
        offset[:, i, j] = (cx - j - 0.5, cy - i - 0.5)
        mask[i, j] = max(mask[i, j], 1.0 if weights is None else weights[k])
    return heat, log_size, offset, mask


def focal_loss(
    pred: torch.Tensor, target: torch.Tensor, pos_weight: torch.Tensor | None = None, alpha: float = 2.0, beta: float = 4.0,
    known: torch.Tensor | None = None,
) -> torch.Tensor:  # fmt: skip
    """CenterNet's penalty-reduced focal loss on heatmaps in (0, 1), normalised by the number of centres;
    `pos_weight` (broadcast to the heatmap) scales the term of each centre, so that hard instances can count more;
    `known` (batch, classes) of 0 leaves a frame's class out of the negatives: a partly labelled frame says
    nothing of where its unlabelled objects are not."""
    pred = pred.clamp(1e-4, 1 - 1e-4)
    pos = target.eq(1).to(pred.dtype)
    weighted = pos if pos_weight is None else pos * pos_weight
    negative = 1 - pos if known is None else (1 - pos) * known[:, :, None, None].to(pred.dtype)
    pos_loss = -(torch.log(pred) * (1 - pred) ** alpha * weighted).sum()
    neg_loss = -(torch.log(1 - pred) * pred**alpha * (1 - target) ** beta * negative).sum()
    return (pos_loss + neg_loss) / pos.sum().clamp(min=1)


def iou(a: tuple[float, float, float, float], b: tuple[float, float, float, float]) -> float:
    """Intersection over union of two (x, y, w, h) boxes."""
    ix = max(0.0, min(a[0] + a[2], b[0] + b[2]) - max(a[0], b[0]))
    iy = max(0.0, min(a[1] + a[3], b[1] + b[3]) - max(a[1], b[1]))
    inter = ix * iy
    union = a[2] * a[3] + b[2] * b[3] - inter
    return inter / union if union > 0 else 0.0


def match(dets: list[Detection], gts: list[tuple[int, tuple[float, float, float, float]]], min_iou: float = 0.5) -> list[int | None]:
    """For each GT (obj_id, (x, y, w, h)) the index of the detection assigned to it, or None. As in COCO, the
    detections in order of score each take the free GT of their object they overlap most (IoU >= min_iou)."""
    out: list[int | None] = [None] * len(gts)
    for k in sorted(range(len(dets)), key=lambda k: -dets[k].score):
        d = dets[k]
        best, best_iou = None, min_iou
        for g, (obj_id, box) in enumerate(gts):
            if out[g] is None and obj_id == d.obj_id:
                v = iou(d.box, box)
                if v >= best_iou:
                    best, best_iou = g, v
        if best is not None:
            out[best] = k
    return out
