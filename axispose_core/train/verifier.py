"""`axispose train-verifier`: the localiser's second stage (`detect/verifier.py`) on crops mined from synthetic
BOP frames, with the other trainers' conventions (`fit`: AdamW, warm-up + cosine, EMA, seeded, resumable, CSV log
with periodic validation recall/precision of the two stages together, `--max-minutes`).

The crops are what the verifier will meet: the trained localiser's own peaks down to the verifier's candidate
score, labelled by the GT instance they overlap (IoU >= 0.5: that instance's object, whichever object the peak
claimed; < 0.4: nothing; in between, or on an instance less than `min_visib` visible: not used), plus jittered GT
boxes (right, and poorly placed) and random background boxes. Mining reads every `frame_stride`-th frame once and
keeps the crops in OUT.crops.npz, so a resumed run does not mine again.
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
from axispose_core.detect.verifier import Verifier, VerifierConfig, box_crops
from axispose_core.train.dataset import bop_frames
from axispose_core.train.detector import KIND, detection_scores, frame_instances, load_localiser
from axispose_core.train.loop import fit, training_device, training_record

Box = tuple[float, float, float, float]


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
    each labelled by `box_label` like the localiser's peaks."""
    background_per_frame: int = 2
    shift: int = 0
    """Random shift of each training crop, in pixels."""
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


def _jitter(box: Box, rng: np.random.Generator, shift: float, scale: float) -> Box:
    x, y, w, h = box
    nw, nh = w * rng.uniform(1 - scale, 1 + scale), h * rng.uniform(1 - scale, 1 + scale)
    cx, cy = x + w / 2 + rng.uniform(-shift, shift) * w, y + h / 2 + rng.uniform(-shift, shift) * h
    return (cx - nw / 2, cy - nh / 2, nw, nh)


def frame_boxes(
    localiser: Localiser, rgb: np.ndarray, insts: list[tuple[int, Box, float]], cfg: VerifierTrainConfig, rng: np.random.Generator
) -> tuple[list[Box], list[int]]:
    """One frame's labelled training boxes: the localiser's candidates, jittered GT boxes and background."""
    classes = {o: k for k, o in enumerate(localiser.config.obj_ids)}
    boxes = [d.box for d in localiser.detect(rgb, threshold=cfg.verifier.candidates)]
    for obj, gt, visib in insts:
        if visib < cfg.min_visib or obj not in classes:
            continue
        boxes += [_jitter(gt, rng, 0.08, 0.15) for _ in range(cfg.jitter_per_instance)]
        boxes += [_jitter(gt, rng, 0.45, 0.5) for _ in range(cfg.jitter_per_instance // 2)]
    h, w = rgb.shape[:2]
    for _ in range(cfg.background_per_frame):
        side = rng.uniform(30, 200, 2)
        boxes.append((rng.uniform(-side[0] / 4, w - side[0] * 3 / 4), rng.uniform(-side[1] / 4, h - side[1] * 3 / 4), *side))
    labelled = [(b, box_label(b, insts, classes, cfg.min_visib)) for b in boxes]
    return [b for b, c in labelled if c is not None], [c for _, c in labelled if c is not None]


def mine_crops(
    localiser: Localiser, data: list[str | Path], cfg: VerifierTrainConfig, progress: bool = True
) -> tuple[np.ndarray, np.ndarray]:
    """uint8 crops (N,S,S,3) and class labels (N,) from every `cfg.frame_stride`-th frame of `data`."""
    detector = localiser.with_verifier(None).fused()
    frames = bop_frames(data)[:: cfg.frame_stride]
    crops, labels = [], []
    for k, (scene, im_id) in enumerate(tqdm(frames, desc="mine crops", disable=not progress)):
        rgb = scene.rgb(im_id)
        insts = frame_instances(scene, im_id, tuple({g.obj_id for g in scene.gt[im_id]}))
        boxes, labs = frame_boxes(detector, rgb, insts, cfg, np.random.default_rng([cfg.seed, k]))
        crops.append(box_crops(rgb, boxes, cfg.verifier.size, cfg.verifier.pad))
        labels += labs
    if not labels:
        raise ValueError(f"no training crops in {data}")
    return np.concatenate(crops), np.array(labels, np.int64)


class CropDataset(Dataset):
    """Mined crops in [-1,1], shifted by up to `shift` pixels (edges reflected) and colour-jittered, seeded by
    (seed, epoch, index)."""

    def __init__(self, crops: np.ndarray, labels: np.ndarray, seed: int = 0, shift: int = 0) -> None:
        self.crops, self.labels, self.seed, self.shift, self.epoch = crops, labels, seed, shift, 0

    def __len__(self) -> int:
        return len(self.labels)

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        rng = np.random.default_rng([self.seed, self.epoch, i])
        crop, s = self.crops[i], self.shift
        if s:
            dx, dy = rng.integers(0, 2 * s + 1, 2)
            crop = np.pad(crop, ((s, s), (s, s), (0, 0)), mode="reflect")[dy : dy + len(self.crops[i]), dx : dx + len(self.crops[i])]
        image = np.clip(crop / 255 * rng.uniform(0.7, 1.3, 3) + rng.uniform(-0.1, 0.1), 0, 1)
        return {"image": torch.from_numpy(image * 2 - 1).permute(2, 0, 1).float(), "label": torch.tensor(self.labels[i])}


def _cached_crops(
    localiser: Localiser, data: list[str | Path], cfg: VerifierTrainConfig, cache: Path, progress: bool
) -> tuple[np.ndarray, np.ndarray]:
    """The mined crops, from `cache` when it was mined from the same data, localiser (config and weights) and settings."""
    weights = hashlib.sha256(b"".join(v.cpu().numpy().tobytes() for v in localiser.state_dict().values())).hexdigest()
    recipe = json.dumps({"data": [str(d) for d in data], "localiser": asdict(localiser.config), "weights": weights,
                         "verifier": asdict(cfg.verifier), "seed": cfg.seed, "frame_stride": cfg.frame_stride,
                         "min_visib": cfg.min_visib, "jitter": cfg.jitter_per_instance,
                         "background": cfg.background_per_frame}, sort_keys=True)  # fmt: skip
    if cache.exists():
        with np.load(cache) as saved:
            if str(saved["recipe"]) == recipe:
                return saved["crops"], saved["labels"]
    crops, labels = mine_crops(localiser, data, cfg, progress)
    with open(cache.with_suffix(".tmp"), "wb") as f:
        np.savez(f, crops=crops, labels=labels, recipe=np.array(recipe))
    cache.with_suffix(".tmp").replace(cache)
    return crops, labels


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
    crops, labels = _cached_crops(localiser, data, cfg, Path(f"{out}.crops.npz"), progress)
    if progress:
        counts = np.bincount(labels, minlength=len(localiser.config.obj_ids) + 1)
        print(f"{len(labels)} crops: " + ", ".join(f"{o}: {n}" for o, n in zip([*localiser.config.obj_ids, "none"], counts, strict=True)))
    torch.manual_seed(cfg.seed)

    def save(ema: torch.nn.Module, step: int, seconds: float, started_from: str | None) -> None:
        both = localiser.with_verifier(ema)
        provenance = training_record(data, step, cfg.batch, seconds, dev, started_from)
        save_checkpoint(out, KIND, both.config, {"localiser": both}, extra={"training": provenance})

    def validate(ema: torch.nn.Module) -> dict[str, float]:
        scores = detection_scores(localiser.with_verifier(ema), val_data, limit=cfg.val_frames)
        return {"val_recall": scores["recall"], "val_precision": scores["precision"]}

    def loss(model: torch.nn.Module, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        return F.cross_entropy(model(batch["image"]), batch["label"])

    return fit(
        cfg, Verifier(cfg.verifier, len(localiser.config.obj_ids)), CropDataset(crops, labels, cfg.seed, cfg.shift), loss, out, save,
        validate if val_data else None, ("val_recall", "val_precision"), resume, dev, max_minutes, progress, "train verifier",
        str(localiser_path),
    )  # fmt: skip
