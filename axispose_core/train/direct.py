"""`axispose train-direct`: the direct-regression baseline (baseline/direct.py) with the shared training loop
(train/loop.py), on the AGM's data: the crop stream by default (the same samples, held-out crops and metrics as
`axispose train`), or the annotated crops of BOP folders with the AGM's jitter and colour augmentation."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from axispose_core.agm.denoiser import EncoderConfig
from axispose_core.agm.model import depth_from_log
from axispose_core.axis_image import axis_keypoints
from axispose_core.baseline.direct import DirectConfig, DirectEstimator, DirectRegressor
from axispose_core.data.synth.config import StreamConfig
from axispose_core.data.synth.stream import stream_loader
from axispose_core.metrics import re
from axispose_core.tbm.backproject import backproject
from axispose_core.train.agm import with_depth_target
from axispose_core.train.dataset import AxisCropDataset
from axispose_core.train.loop import (
    DEFAULT_RUN,
    OptimConfig,
    RunOptions,
    TrainJob,
    Validation,
    epochs,
    fit,
    start_pretrained,
    training_device,
    training_record,
)
from axispose_core.train.losses import DirectObjective
from axispose_core.train.sources import CropSources


@dataclass(frozen=True)
class DirectTrainConfig:
    encoder: EncoderConfig = field(default_factory=EncoderConfig)
    size: int = 64
    optim: OptimConfig = field(default_factory=lambda: OptimConfig(steps=3000, batch=16, warmup=100, ema_decay=0.99, bf16=True))
    min_visib: float = 0.1
    val_samples: int = 64
    stream: StreamConfig = field(default_factory=StreamConfig)
    val_seed: int = 1_000_000


class KeypointCropDataset(AxisCropDataset):
    """The AGM's crops with the pixel keypoints (origin, end X, Y, Z) the GT pose projects to in each crop."""

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        item = super().__getitem__(i)
        lengths = self.specs[int(item["object"])].axes.lengths
        kp = axis_keypoints(item["K"].numpy(), item["R"].numpy(), item["t"].numpy(), lengths)
        return {k: item[k] for k in ("crop", "object", "K", "R", "t")} | {"keypoints": torch.from_numpy(kp).float()}


def train_direct(cfg: DirectTrainConfig, sources: CropSources, out: str | Path, run: RunOptions = DEFAULT_RUN) -> int:
    """Train (or continue) the regressor; OUT holds the EMA weights with their config. Returns the step reached."""
    dev = training_device(run.device)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    objects, train_set, stream = sources.training(KeypointCropDataset, cfg.stream, cfg.size, cfg.min_visib, cfg.optim.seed)
    config = DirectConfig(encoder=cfg.encoder, size=cfg.size, objects=tuple(objects))
    torch.manual_seed(cfg.optim.seed)
    scales = torch.tensor([o.scale for o in objects], dtype=torch.float64)
    items = sources.held_out(KeypointCropDataset, objects, cfg.stream, cfg.val_seed, cfg.size, cfg.val_samples, cfg.optim.seed)
    val_batch = {k: torch.stack([it[k] for it in items]) for k in items[0]} if items else None

    def save(ema: torch.nn.Module, step: int, seconds: float, init: str | None) -> None:
        record = training_record(sources.describe(), step, cfg.optim.batch, seconds, dev, init)
        DirectEstimator(ema).save(out, extra={"training": record})

    def validate(ema: torch.nn.Module) -> dict[str, float]:
        with torch.inference_mode(), torch.autocast(dev.type, dtype=torch.bfloat16, enabled=cfg.optim.bf16):
            enc = ema.encoder(val_batch["crop"].to(dev), val_batch["object"].to(dev))
            kps = ((ema.head(enc.context).view(-1, 4, 2).float() + 1) * 0.5 * cfg.size - 0.5).double().cpu().numpy()
        errs, kp_errs, depth = [], [], []
        for i, (kp, K, R, t, obj) in enumerate(zip(kps, *(val_batch[k].numpy() for k in ("K", "R", "t", "object")), strict=True)):
            lengths = objects[int(obj)].axes.lengths
            res = backproject(K, kp[0], kp[1:], lengths, refine=True)
            errs.append(re(res.R, R) if res.ok else 180.0)
            kp_errs.append(float(np.linalg.norm(kp - axis_keypoints(K, R, t, lengths), axis=1).mean()))
            depth.append(abs(depth_from_log(float(enc.log_depth[i]), K, lengths[0], cfg.size) / t[2] - 1))
        return {"val_rot_median_deg": float(np.median(errs)), "val_rot_within_15deg": float(np.mean(np.array(errs) < 15.0)),
                "val_kp_err_px": float(np.median(kp_errs)), "val_depth_head": float(np.median(depth))}  # fmt: skip

    def loss(model: torch.nn.Module, batch: dict[str, torch.Tensor], _: torch.Generator) -> torch.Tensor:
        return model(with_depth_target(batch, scales.to(batch["t"].device), cfg.size))

    def batches(step: int):
        return stream_loader(stream, cfg.optim.batch, start=step * cfg.optim.batch, workers=cfg.optim.workers)

    model = DirectRegressor(config)
    if not run.resume:
        start_pretrained(model)
    columns = ("val_rot_median_deg", "val_rot_within_15deg", "val_kp_err_px", "val_depth_head")
    job = TrainJob(
        cfg, model, batches if stream is not None else epochs(train_set, cfg.optim), loss, out, save,
        validation=Validation(columns, validate if val_batch else None), device=dev, desc="train direct", objective=DirectObjective,
    )  # fmt: skip
    return fit(job, run)
