"""A second look at each localiser detection: a small classifier on the box's crop from the full-resolution frame.

The heatmap localiser reads a 384x288 copy of the frame and scores each object's peaks on its own; its misses
are mostly right boxes scoring under the threshold, and its false alarms mostly boxes on another object's
instance or on background (docs/BENCHMARKS.md). The verifier reads every candidate box (the heatmap's peaks down
to `candidates`) cut from the full frame with some context and warped to `size` x `size`, and says which object
fills it, or none (the last class). A detection's score becomes det_score^(1 - weight) * p(its object)^weight, so
the threshold then ranks boxes by what two networks see, at two resolutions.

With `refine` it also regresses, per object, a correction of the box it reads (centre shift in box widths and
heights, log scale; R-CNN's parameterisation), and the detection takes the corrected box. It was meant for the
heatmap's poorly placed boxes on partly hidden instances (IoU 0.4-0.5), reading the full frame with context around
the box; measured, it did not mend them (docs/BENCHMARKS.md, "A box refiner").
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import pairwise

import cv2
import numpy as np
import torch
from torch import nn

from axispose_core.detect.decode import Detection


@dataclass(frozen=True)
class VerifierConfig:
    size: int = 48
    """Side of the square crop the classifier reads (a multiple of 16)."""
    pad: float = 1.2
    """The box is grown by this factor about its centre before cutting: the context around the object."""
    channels: tuple[int, ...] = (16, 32, 64, 128)
    """Widths at strides 2, 4, 8, 16."""
    candidates: float = 0.05
    """Least heatmap score of a peak the verifier looks at."""
    weight: float = 1.0
    """Exponent of the verifier's probability in the final score (0: the heatmap's score alone; then only the
    peaks above the detection threshold are read)."""
    refine: bool = False
    """Also correct each detection's box (`apply_deltas`)."""


DELTA_SCALE = (0.1, 0.1, 0.2, 0.2)
"""The refiner's outputs times these are the box deltas: unit-scale targets for deltas of typical detector errors."""
MAX_LOG_SCALE = 1.4
"""A refined box grows or shrinks by at most e^1.4 (about 4x) per side."""


def box_deltas(box: tuple[float, float, float, float], target: tuple[float, float, float, float]) -> np.ndarray:
    """(dx, dy, dw, dh) taking the (x, y, w, h) `box` to `target`: centre shift in box widths and heights, log scale."""
    x, y, w, h = box
    tx, ty, tw, th = target
    return np.array([(tx + tw / 2 - x - w / 2) / w, (ty + th / 2 - y - h / 2) / h, np.log(tw / w), np.log(th / h)], np.float32)


def apply_deltas(box: tuple[float, float, float, float], deltas: np.ndarray) -> tuple[float, float, float, float]:
    """The box `box_deltas` leads to from `box` (log scales clipped to +-MAX_LOG_SCALE)."""
    x, y, w, h = box
    dx, dy, dw, dh = (float(v) for v in deltas)
    nw, nh = w * np.exp(np.clip(dw, -MAX_LOG_SCALE, MAX_LOG_SCALE)), h * np.exp(np.clip(dh, -MAX_LOG_SCALE, MAX_LOG_SCALE))
    cx, cy = x + w / 2 + dx * w, y + h / 2 + dy * h
    return (cx - nw / 2, cy - nh / 2, float(nw), float(nh))


def _block(c_in: int, c_out: int, stride: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(c_in, c_out, 3, stride, 1, bias=False), nn.BatchNorm2d(c_out), nn.SiLU(inplace=True))


class Verifier(nn.Module):
    """Crops (B,3,S,S) in [-1,1] -> logits (B, n_objects + 1), the last class "no object of ours, or a poor box",
    and with `refine` the box deltas per object (B, n_objects, 4) in units of DELTA_SCALE (else None)."""

    def __init__(self, config: VerifierConfig, n_objects: int) -> None:
        super().__init__()
        if config.size % 16 or len(config.channels) != 4 or not 0 <= config.weight <= 1:
            raise ValueError(f"a verifier needs a size in multiples of 16, 4 widths and a weight in [0, 1], got {config}")
        self.config, self.n_objects = config, n_objects
        c = config.channels
        layers = [_block(3, c[0], 2)]
        for a, b in pairwise(c):
            layers += [_block(a, b, 2), _block(b, b, 1)]
        self.features = nn.Sequential(*layers)
        cells = (config.size // 16) ** 2  # the flattened grid keeps where in the box the object sits
        outputs = n_objects + 1 + (4 * n_objects if config.refine else 0)
        self.head = nn.Sequential(nn.Flatten(), nn.Dropout(0.2), nn.Linear(c[-1] * cells, 128), nn.SiLU(), nn.Linear(128, outputs))

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        out = self.head(self.features(x))
        n = self.n_objects + 1
        return out[:, :n], out[:, n:].reshape(len(out), -1, 4) if self.config.refine else None


def box_crops(image_rgb: np.ndarray, boxes: list[tuple[float, float, float, float]], size: int, pad: float) -> np.ndarray:
    """(N, size, size, 3) uint8 crops of (x, y, w, h) boxes grown by `pad` about their centres, each stretched to
    the square (so the crop also shows how well the box fits); outside the frame is black."""
    out = np.zeros((len(boxes), size, size, 3), np.uint8)
    for k, (x, y, w, h) in enumerate(boxes):
        sx, sy = size / max(w * pad, 1e-3), size / max(h * pad, 1e-3)
        cx, cy = x + w / 2, y + h / 2
        # continuous coordinates (pixel k spans [k, k+1)) -> cv2's pixel-centre indices: u_dst = s (u - c) + size/2, less 1/2 on both sides
        A = np.array([[sx, 0, size / 2 - 0.5 + sx * (0.5 - cx)], [0, sy, size / 2 - 0.5 + sy * (0.5 - cy)]])
        out[k] = cv2.warpAffine(image_rgb, A, (size, size), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    return out


def crops_tensor(crops: np.ndarray) -> torch.Tensor:
    """uint8 (N,S,S,3) crops -> float (N,3,S,S) in [-1,1]."""
    return torch.from_numpy(crops).permute(0, 3, 1, 2).float() / 127.5 - 1


@torch.inference_mode()
def rescore(verifier: Verifier, image_rgb: np.ndarray, dets: list[Detection], obj_ids: tuple[int, ...]) -> list[Detection]:
    """`dets` with the verifier's score folded in (and with `refine`, its boxes), best first."""
    if not dets:
        return []
    cfg = verifier.config
    x = crops_tensor(box_crops(image_rgb, [d.box for d in dets], cfg.size, cfg.pad))
    dev = next(verifier.parameters()).device
    logits, deltas = verifier(x.to(dev, memory_format=torch.channels_last))
    probs = torch.softmax(logits, dim=1).cpu().numpy()
    moves = None if deltas is None else deltas.cpu().numpy() * np.array(DELTA_SCALE)
    cls = {o: k for k, o in enumerate(obj_ids)}
    scored = []
    for k, d in enumerate(dets):
        score = float(d.score ** (1 - cfg.weight) * probs[k, cls[d.obj_id]] ** cfg.weight)
        center, size = d.center, d.size
        if moves is not None:
            bx, by, bw, bh = apply_deltas(d.box, moves[k, cls[d.obj_id]])
            center, size = (bx + bw / 2, by + bh / 2), (bw, bh)
        scored.append(Detection(d.obj_id, score, center, size))
    return sorted(scored, key=lambda d: -d.score)
