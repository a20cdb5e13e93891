"""`axispose train-verifier`: the localiser's second stage (`detect/verifier.py`) on crops mined from synthetic
BOP frames, with the other trainers' conventions (`fit`: AdamW, warm-up + cosine, EMA, seeded, resumable, CSV log
with periodic validation recall/precision of the two stages together, `--max-minutes`).

The crops are what the verifier will meet: the trained localiser's own peaks down to the verifier's candidate
score, labelled by the GT instance they overlap (IoU >= 0.5: that instance's object, whichever object the peak
claimed; < 0.4: nothing; in between, or on an instance less than `min_visib` visible: not used), plus jittered GT
boxes (right, and poorly placed) and random background boxes. A verifier that `refine`s boxes also learns, from
every box that overlaps an instance of the object it claims at IoU >= `refine_min_iou`, the deltas to that
instance's box (boxes between the class labels' IoU bands then train the box head alone). Mining reads every
`frame_stride`-th frame once and keeps the crops in OUT.crops.npz, so a resumed run does not mine again.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch.utils.data import Dataset
from tqdm import tqdm

from axispose_core.checkpoint import save_checkpoint
from axispose_core.detect.decode import iou
from axispose_core.detect.model import Localiser
from axispose_core.detect.verifier import DELTA_SCALE, Verifier, VerifierConfig, box_crops, box_deltas
from axispose_core.train.dataset import bop_frames
from axispose_core.train.detector import KIND, detection_scores, frame_instances, load_localiser
from axispose_core.train.loop import fit, training_device, training_record

Box = tuple[float, float, float, float]
IGNORE = -100
"""Class label of a crop that trains only the box head."""


@dataclass(frozen=True)
class VerifierTrainConfig:
    verifier: VerifierConfig = field(default_factory=VerifierConfig)
    steps: int = 3000
    batch: int = 256
    lr: float = 2e-3
    weight_decay: float = 1e-4
    warmup: int = 100
    grad_clip: float = 5.0
    ema_decay: float = 0.99
    seed: int = 0
    workers: int = 0
    frame_stride: int = 3
    """Mine every n-th training frame."""
    min_visib: float = 0.1
    jitter_per_instance: int = 2
    """GT boxes jittered a little (shift 8 %, scale 15 %) per instance, and half as many moved far (45 %, 50 %);
    each labelled by `box_label` like the localiser's peaks; with `verifier.refine` as many again moved part way
    (25 %, 40 %), errors like the localiser's poor boxes."""
    background_per_frame: int = 2
    shift: int = 0
    """Random shift of each training crop, in pixels."""
    refine_min_iou: float = 0.25
    """With `verifier.refine`: least IoU of a box with an instance of its claimed object for it to learn that box."""
    refine_weight: float = 1.0
    """Weight of the box loss (smooth L1 in DELTA_SCALE units) beside the classification loss."""
    save_every: int = 500
    val_every: int = 1000
    val_frames: int = 40


def box_label(box: Box, insts: list[tuple[int, Box, float]], classes: dict[int, int], min_visib: float) -> int | None:
    """Class of what `box` frames: the object of the instance it overlaps at IoU >= 0.5, `len(classes)` (nothing)
    below 0.4, None (not used) in between or on an instance of another object set or less than `min_visib` visible."""
    best, best_iou = None, 0.0
    for obj, gt, visib in insts:
        v = iou(box, gt)
        if v > best_iou:
            best, best_iou = (obj, visib), v
    if best is None or best_iou < 0.4:
        return len(classes)
    if best_iou < 0.5 or best[1] < min_visib or best[0] not in classes:
        return None
    return classes[best[0]]


def refine_target(box: Box, claimed: int | None, insts: list[tuple[int, Box, float]], min_iou: float, min_visib: float) -> Box | None:
    """The box the refiner should turn `box` into: the instance of the object `box` claims (None: a background
    box, no target) that it overlaps most, if at IoU >= `min_iou` and at least `min_visib` visible."""
    best, best_iou = None, min_iou
    for obj, gt, visib in insts:
        if obj == claimed and visib >= min_visib and (v := iou(box, gt)) >= best_iou:
            best, best_iou = gt, v
    return best


def _jitter(box: Box, rng: np.random.Generator, shift: float, scale: float) -> Box:
    x, y, w, h = box
    nw, nh = w * rng.uniform(1 - scale, 1 + scale), h * rng.uniform(1 - scale, 1 + scale)
    cx, cy = x + w / 2 + rng.uniform(-shift, shift) * w, y + h / 2 + rng.uniform(-shift, shift) * h
    return (cx - nw / 2, cy - nh / 2, nw, nh)


@dataclass
class MinedCrops:
    """Training crops and their targets."""

    crops: np.ndarray
    """uint8 (N,S,S,3)."""
    labels: np.ndarray
    """(N,) class index, `len(obj_ids)` for nothing, IGNORE for a crop that trains only the box head."""
    box_obj: np.ndarray
    """(N,) index of the object whose box deltas the crop learns, -1 for none."""
    deltas: np.ndarray
    """(N,4) `box_deltas` from the crop's box to its target box (zero where box_obj is -1)."""


def frame_boxes(
    localiser: Localiser, rgb: np.ndarray, insts: list[tuple[int, Box, float]], cfg: VerifierTrainConfig, rng: np.random.Generator
) -> list[tuple[Box, int, int, np.ndarray]]:
    """One frame's training boxes, (box, class label, box_obj, deltas) as in MinedCrops: the localiser's
    candidates, jittered GT boxes and background; boxes with neither a class label nor a box target are left out."""
    classes = {o: k for k, o in enumerate(localiser.config.obj_ids)}
    refine = cfg.verifier.refine
    claimed: list[tuple[Box, int | None]] = [(d.box, d.obj_id) for d in localiser.detect(rgb, threshold=cfg.verifier.candidates)]
    for obj, gt, visib in insts:
        if visib < cfg.min_visib or obj not in classes:
            continue
        claimed += [(_jitter(gt, rng, 0.08, 0.15), obj) for _ in range(cfg.jitter_per_instance)]
        claimed += [(_jitter(gt, rng, 0.45, 0.5), obj) for _ in range(cfg.jitter_per_instance // 2)]
        claimed += [(_jitter(gt, rng, 0.25, 0.4), obj) for _ in range(cfg.jitter_per_instance * refine)]
    h, w = rgb.shape[:2]
    for _ in range(cfg.background_per_frame):
        side = rng.uniform(30, 200, 2)
        claimed.append(((rng.uniform(-side[0] / 4, w - side[0] * 3 / 4), rng.uniform(-side[1] / 4, h - side[1] * 3 / 4), *side), None))
    out = []
    for box, obj in claimed:
        label = box_label(box, insts, classes, cfg.min_visib)
        target = refine_target(box, obj, insts, cfg.refine_min_iou, cfg.min_visib) if refine else None
        if target is not None:
            out.append((box, IGNORE if label is None else label, classes[obj], box_deltas(box, target)))
        elif label is not None:
            out.append((box, label, -1, np.zeros(4, np.float32)))
    return out


def mine_crops(localiser: Localiser, data: list[str | Path], cfg: VerifierTrainConfig, progress: bool = True) -> MinedCrops:
    """The training crops of every `cfg.frame_stride`-th frame of `data`."""
    detector = localiser.with_verifier(None).fused()
    frames = bop_frames(data)[:: cfg.frame_stride]
    crops, rows = [], []
    for k, (scene, im_id) in enumerate(tqdm(frames, desc="mine crops", disable=not progress)):
        rgb = scene.rgb(im_id)
        insts = frame_instances(scene, im_id, tuple({g.obj_id for g in scene.gt[im_id]}))
        boxes = frame_boxes(detector, rgb, insts, cfg, np.random.default_rng([cfg.seed, k]))
        crops.append(box_crops(rgb, [b for b, *_ in boxes], cfg.verifier.size, cfg.verifier.pad))
        rows += boxes
    if not rows:
        raise ValueError(f"no training crops in {data}")
    return MinedCrops(np.concatenate(crops), np.array([r[1] for r in rows], np.int64), np.array([r[2] for r in rows], np.int64),
                      np.stack([r[3] for r in rows]).astype(np.float32))  # fmt: skip


class CropDataset(Dataset):
    """Mined crops in [-1,1], shifted by up to `shift` pixels (edges reflected; the box deltas follow, for crops cut
    from boxes grown by `pad`) and colour-jittered, seeded by (seed, epoch, index)."""

    def __init__(self, mined: MinedCrops, seed: int = 0, shift: int = 0, pad: float = 1.2) -> None:
        self.mined, self.seed, self.shift, self.pad, self.epoch = mined, seed, shift, pad, 0

    def __len__(self) -> int:
        return len(self.mined.labels)

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        rng = np.random.default_rng([self.seed, self.epoch, i])
        crop, s, side = self.mined.crops[i], self.shift, len(self.mined.crops[i])
        deltas = self.mined.deltas[i].copy()
        if s:
            dx, dy = rng.integers(0, 2 * s + 1, 2)
            crop = np.pad(crop, ((s, s), (s, s), (0, 0)), mode="reflect")[dy : dy + side, dx : dx + side]
            # the crop now shows the box moved by (dx - s, dy - s) crop pixels, pad / side box widths each
            deltas[:2] -= (np.array([dx, dy]) - s) * self.pad / side
        image = np.clip(crop / 255 * rng.uniform(0.7, 1.3, 3) + rng.uniform(-0.1, 0.1), 0, 1)
        return {"image": torch.from_numpy(image * 2 - 1).permute(2, 0, 1).float(), "label": torch.tensor(self.mined.labels[i]),
                "box_obj": torch.tensor(self.mined.box_obj[i]), "deltas": torch.from_numpy(deltas)}  # fmt: skip


def _cached_crops(localiser: Localiser, data: list[str | Path], cfg: VerifierTrainConfig, cache: Path, progress: bool) -> MinedCrops:
    """The mined crops, from `cache` when it was mined from the same data, localiser (config and weights) and settings."""
    weights = hashlib.sha256(b"".join(v.cpu().numpy().tobytes() for v in localiser.state_dict().values())).hexdigest()
    recipe = json.dumps({"data": [str(d) for d in data], "localiser": asdict(localiser.config), "weights": weights,
                         "verifier": asdict(cfg.verifier), "seed": cfg.seed, "frame_stride": cfg.frame_stride,
                         "min_visib": cfg.min_visib, "jitter": cfg.jitter_per_instance,
                         "background": cfg.background_per_frame, "refine_min_iou": cfg.refine_min_iou}, sort_keys=True)  # fmt: skip
    if cache.exists():
        with np.load(cache) as saved:
            if str(saved["recipe"]) == recipe:
                return MinedCrops(saved["crops"], saved["labels"], saved["box_obj"], saved["deltas"])
    mined = mine_crops(localiser, data, cfg, progress)
    with open(cache.with_suffix(".tmp"), "wb") as f:
        np.savez(f, crops=mined.crops, labels=mined.labels, box_obj=mined.box_obj, deltas=mined.deltas, recipe=np.array(recipe))
    cache.with_suffix(".tmp").replace(cache)
    return mined


def train_verifier(
    cfg: VerifierTrainConfig,
    localiser_path: str | Path,
    data: list[str | Path],
    out: str | Path,
    val_data: list[str | Path] | None = None,
    resume: str | Path | None = None,
    device: str = "auto",
    max_minutes: float | None = None,
    progress: bool = True,
) -> int:
    """Train (or continue) a verifier for the localiser in `localiser_path` (its own checkpoint or an estimator's);
    OUT is that localiser with the verifier's EMA weights attached. Returns the step reached."""
    dev = training_device(device)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    localiser = load_localiser(localiser_path).with_verifier(None)
    mined = _cached_crops(localiser, data, cfg, Path(f"{out}.crops.npz"), progress)
    if progress:
        names = [*localiser.config.obj_ids, "none"]
        counts = np.bincount(mined.labels[mined.labels != IGNORE], minlength=len(names))
        boxes = f"; {int((mined.box_obj >= 0).sum())} with a box target" if cfg.verifier.refine else ""
        print(f"{len(mined.labels)} crops: " + ", ".join(f"{o}: {n}" for o, n in zip(names, counts, strict=True)) + boxes)
    torch.manual_seed(cfg.seed)

    def save(ema: torch.nn.Module, step: int, seconds: float, started_from: str | None) -> None:
        both = localiser.with_verifier(ema)
        provenance = training_record(data, step, cfg.batch, seconds, dev, started_from)
        save_checkpoint(out, KIND, both.config, {"localiser": both}, extra={"training": provenance})

    def validate(ema: torch.nn.Module) -> dict[str, float]:
        scores = detection_scores(localiser.with_verifier(ema), val_data, limit=cfg.val_frames)
        return {"val_recall": scores["recall"], "val_precision": scores["precision"]}

    scale = torch.tensor(DELTA_SCALE, device=dev)

    def loss(model: torch.nn.Module, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        logits, deltas = model(batch["image"])
        labels, box_obj = batch["label"], batch["box_obj"]
        value = F.cross_entropy(logits, labels, ignore_index=IGNORE, reduction="sum") / (labels != IGNORE).sum().clamp(min=1)
        if deltas is not None:
            rows = (box_obj >= 0).nonzero()[:, 0]
            pred = deltas[rows, box_obj[rows]]
            box = F.smooth_l1_loss(pred, batch["deltas"][rows] / scale, reduction="sum") / (4 * len(rows)) if len(rows) else pred.sum()
            value = value + cfg.refine_weight * box
        return value

    crops = CropDataset(mined, cfg.seed, cfg.shift, cfg.verifier.pad)
    return fit(
        cfg, Verifier(cfg.verifier, len(localiser.config.obj_ids)), crops, loss, out, save,
        validate if val_data else None, ("val_recall", "val_precision"), resume, dev, max_minutes, progress, "train verifier",
        str(localiser_path),
    )  # fmt: skip
