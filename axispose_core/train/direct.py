"""`axispose train-direct`: the direct-regression baseline (baseline/direct.py) on the AGM's training crops,
with the localiser's training loop (train/loop.py). Same crops, jitter and colour augmentation as the AGM."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from axispose_core.agm.denoiser import DenoiserConfig
from axispose_core.axis_image import axis_keypoints
from axispose_core.baseline.direct import DirectConfig, DirectEstimator, DirectRegressor, regression_loss
from axispose_core.metrics import re
from axispose_core.tbm.backproject import backproject
from axispose_core.train.agm import dataset_objects
from axispose_core.train.dataset import AxisCropDataset
from axispose_core.train.loop import fit, training_device, training_record


@dataclass(frozen=True)
class DirectTrainConfig:
    encoder: DenoiserConfig = field(default_factory=DenoiserConfig)
    steps: int = 3000
    batch: int = 16
    lr: float = 1e-3
    weight_decay: float = 1e-4
    warmup: int = 100
    grad_clip: float = 1.0
    ema_decay: float = 0.99
    seed: int = 0
    workers: int = 1
    min_visib: float = 0.1
    save_every: int = 200
    val_every: int = 500
    val_samples: int = 64


class KeypointCropDataset(AxisCropDataset):
    """The AGM's crops with the pixel keypoints (origin, end X, Y, Z) the GT pose projects to in each crop."""

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        item = super().__getitem__(i)
        lengths = self.specs[int(item["object"])].axes.lengths
        kp = axis_keypoints(item["K"].numpy(), item["R"].numpy(), item["t"].numpy(), lengths)
        return {"crop": item["crop"], "keypoints": torch.from_numpy(kp).float(), "object": item["object"],
                "K": item["K"], "R": item["R"]}  # fmt: skip


def train_direct(
    cfg: DirectTrainConfig,
    data: list[str | Path],
    out: str | Path,
    val_data: list[str | Path] | None = None,
    resume: str | Path | None = None,
    device: str = "auto",
    max_minutes: float | None = None,
    progress: bool = True,
) -> int:
    """Train (or continue) the regressor; OUT holds the EMA weights with their config. Returns the step reached."""
    dev = training_device(device)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    objects = dataset_objects(data[0])
    config = DirectConfig(encoder=cfg.encoder, objects=tuple(objects))
    torch.manual_seed(cfg.seed)
    train_set = KeypointCropDataset(data, objects, cfg.encoder.size, cfg.min_visib, seed=cfg.seed)
    if not len(train_set):
        raise ValueError(f"no training instances with visib_fract >= {cfg.min_visib} in {data}")
    val_batch = None
    if val_data:
        val_set = KeypointCropDataset(val_data, objects, cfg.encoder.size, 0.3, jitter=None, color_aug=False, seed=cfg.seed)
        items = [val_set[int(i)] for i in np.linspace(0, len(val_set) - 1, min(cfg.val_samples, len(val_set))).astype(int)]
        val_batch = {k: torch.stack([it[k] for it in items]) for k in items[0]}

    def save(ema: torch.nn.Module, step: int, seconds: float, init: str | None) -> None:
        DirectEstimator(ema).save(out, extra={"training": training_record(data, step, cfg.batch, seconds, dev, init)})

    def validate(ema: torch.nn.Module) -> dict[str, float]:
        with torch.inference_mode():
            kps = ema.keypoints(val_batch["crop"].to(dev)).double().cpu().numpy()
        errs = []
        for kp, K, R, obj in zip(kps, val_batch["K"].numpy(), val_batch["R"].numpy(), val_batch["object"], strict=True):
            res = backproject(K, kp[0], kp[1:], objects[int(obj)].axes.lengths, refine=True)
            errs.append(re(res.R, R) if res.ok else 180.0)
        return {"val_rot_median_deg": float(np.median(errs)), "val_rot_within_15deg": float(np.mean(np.array(errs) < 15.0))}

    return fit(
        cfg, DirectRegressor(config), train_set, regression_loss, out, save, validate if val_batch else None,
        ("val_rot_median_deg", "val_rot_within_15deg"), resume, dev, max_minutes, progress, "train direct",
    )  # fmt: skip
