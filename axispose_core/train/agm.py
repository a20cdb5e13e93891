"""`axispose train`: the AGM on synthetic BOP crops — AdamW, warm-up + cosine, clipping, EMA, resumable.

A run writes OUT (the estimator checkpoint, EMA weights, config inside) and OUT.state.pt (model, EMA,
optimiser, step, RNG: what `--resume` needs), both atomically every `save_every` steps and at the end, and
OUT.csv (loss, learning rate, wall time, periodic validation). `--max-minutes` stops cleanly, so long runs
are chains of short ones. Under `torchrun`, DistributedDataParallel (gloo on CPU, nccl on CUDA) splits the
batches; rank 0 writes.
"""

from __future__ import annotations

import copy
import csv
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
from torch.utils.data import DataLoader, DistributedSampler, RandomSampler
from tqdm import tqdm

from axispose_core.agm.model import AGMConfig, AxisGenerator
from axispose_core.data.objects import LMO_NAMES, ObjectSpec, objects_from_models
from axispose_core.data.synth.config import SynthConfig
from axispose_core.estimator import Estimator, EstimatorConfig
from axispose_core.metrics import re
from axispose_core.tbm.backproject import backproject
from axispose_core.tbm.reader import SHIPPED_READER, KeypointReader, load_reader
from axispose_core.train.dataset import AxisCropDataset
from axispose_core.train.loop import optimizer_step, training_device, training_record
from axispose_core.train.resume import load_run_state, save_run_state, state_path
from axispose_core.train.schedule import warmup_cosine


@dataclass(frozen=True)
class TrainConfig:
    agm: AGMConfig = field(default_factory=AGMConfig)
    steps: int = 20000
    batch: int = 32
    lr: float = 1e-3
    weight_decay: float = 1e-4
    warmup: int = 200
    grad_clip: float = 1.0
    ema_decay: float = 0.995
    seed: int = 0
    workers: int = 2
    min_visib: float = 0.1
    save_every: int = 200
    val_every: int = 500
    val_samples: int = 32
    val_steps: int = 4


def dataset_objects(root: str | Path) -> list[ObjectSpec]:
    """The objects a synthetic dataset shows (its synth_config.json), else all of its models_info.json."""
    synth = Path(root) / "synth_config.json"
    ids = list(SynthConfig.load(synth).objects) if synth.exists() else None
    return objects_from_models(root, ids or None, names=LMO_NAMES)


def validate(
    agm: AxisGenerator, reader: KeypointReader, batch: dict[str, torch.Tensor], lengths: np.ndarray, steps: int
) -> dict[str, float]:
    """Median rotation error and TBM success on a fixed batch of held-out crops."""
    axes = agm.sample(batch["crop"], steps, generator=torch.Generator().manual_seed(0))
    readings = reader.read(((axes + 1) * 0.5).clamp(0, 1).cpu())
    errs = []
    for i, kp in enumerate(readings):
        res = backproject(batch["K"][i].numpy(), kp.origin, kp.endpoints, lengths[i], refine=True) if kp.ok else None
        errs.append(re(res.R, batch["R"][i].numpy()) if res is not None and res.ok else 180.0)
    errs_a = np.array(errs)
    return {"val_rot_median_deg": float(np.median(errs_a)), "val_rot_within_15deg": float(np.mean(errs_a < 15.0))}


def train_agm(
    cfg: TrainConfig,
    data: list[str | Path],
    out: str | Path,
    val_data: list[str | Path] | None = None,
    reader_path: str | Path | None = None,
    resume: str | Path | None = None,
    device: str = "auto",
    max_minutes: float | None = None,
    progress: bool = True,
    init: str | Path | None = None,
) -> int:
    """Train (or continue) the AGM; returns the step reached.

    `init`: an estimator checkpoint with the same AGM network whose (EMA) weights a new run starts from, with a
    fresh optimiser and schedule, e.g. to train the shipped model on; a resumed run restores its own weights and
    keeps recording the checkpoint its first call started from.
    """
    distributed = "RANK" in os.environ and "WORLD_SIZE" in os.environ
    if distributed and not dist.is_initialized():
        dist.init_process_group("nccl" if torch.cuda.is_available() and device != "cpu" else "gloo")
    rank = dist.get_rank() if distributed else 0
    dev = training_device(device)
    if dev.type == "cuda" and distributed:
        dev = torch.device("cuda", int(os.environ.get("LOCAL_RANK", 0)))
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(cfg.seed + rank)
    objects = dataset_objects(data[0])
    reader = load_reader(reader_path or SHIPPED_READER)
    if reader.config.size != cfg.agm.denoiser.size:
        raise ValueError(f"the keypoint reader reads {reader.config.size}px images; the AGM is configured for {cfg.agm.denoiser.size}px")
    train_set = AxisCropDataset(data, objects, cfg.agm.denoiser.size, cfg.min_visib, seed=cfg.seed)
    if not len(train_set):
        raise ValueError(f"no training instances with visib_fract >= {cfg.min_visib} in {data}")
    model = AxisGenerator(cfg.agm)
    if init and not resume:
        start_from = Estimator.load(init)
        if start_from.config.agm != cfg.agm:
            raise ValueError(f"{init}: its AGM is {start_from.config.agm}, the config asks for {cfg.agm}")
        model.denoiser.load_state_dict(start_from.agm.denoiser.state_dict())
    model = model.to(dev)
    ema = copy.deepcopy(model).eval()
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: warmup_cosine(s, cfg.warmup, cfg.steps))
    step, started_from = 0, str(init) if init else None
    if resume:  # its weights are the run's own; the record keeps naming what its first call started from
        step, started_from = load_run_state(resume, cfg, model, ema, opt, sched)
    net = torch.nn.parallel.DistributedDataParallel(model) if distributed else model
    val_batch, val_lengths = None, None
    if val_data and rank == 0:
        val_set = AxisCropDataset(val_data, objects, cfg.agm.denoiser.size, 0.3, jitter=None, color_aug=False, seed=cfg.seed)
        idx = np.linspace(0, len(val_set) - 1, min(cfg.val_samples, len(val_set))).astype(int)
        items = [val_set[int(i)] for i in idx]
        val_batch = {k: torch.stack([it[k] for it in items]) for k in items[0]}
        val_lengths = np.stack([objects[int(it["object"])].axes.lengths for it in items])
    log = open(out.with_suffix(".csv"), "a", newline="") if rank == 0 else None
    writer = csv.writer(log) if log else None
    if writer and step == 0:
        writer.writerow(["step", "loss", "lr", "seconds", "val_rot_median_deg", "val_rot_within_15deg"])
    use_amp = dev.type == "cuda"
    start = time.time()
    bar = tqdm(total=cfg.steps, initial=step, desc="train agm", disable=not progress or rank != 0)
    epoch = step * cfg.batch // max(1, len(train_set))
    gen = torch.Generator().manual_seed(cfg.seed * 1000 + step + rank)

    def out_of_time() -> bool:
        return max_minutes is not None and time.time() - start > 60 * max_minutes

    def save() -> None:
        if rank != 0:
            return
        est_cfg = EstimatorConfig(
            agm=cfg.agm,
            reader=reader.config,
            objects=tuple(objects),
            training=training_record(data, step, cfg.batch, time.time() - start, dev, started_from),
        )
        Estimator(est_cfg, ema, reader, "cpu" if dev.type == "cpu" else str(dev)).save(out)
        save_run_state(state_path(out), cfg, model, ema, opt, sched, step, started_from)

    try:
        while step < cfg.steps:
            train_set.epoch = epoch
            sampler = (
                DistributedSampler(train_set, seed=cfg.seed + epoch)
                if distributed
                else RandomSampler(train_set, generator=torch.Generator().manual_seed(cfg.seed + epoch))
            )
            loader = DataLoader(
                train_set, batch_size=cfg.batch, sampler=sampler, num_workers=cfg.workers, drop_last=True, persistent_workers=False
            )
            for batch in loader:
                crops, axes = batch["crop"].to(dev), batch["axes"].to(dev)
                with torch.autocast(dev.type, dtype=torch.bfloat16, enabled=use_amp):
                    loss = net(crops, axes, gen)
                optimizer_step(loss, model, ema, opt, sched, cfg.grad_clip, cfg.ema_decay)
                step += 1
                bar.update(1)
                bar.set_postfix(loss=f"{loss.item():.4f}")
                val = {}
                if val_batch is not None and step % cfg.val_every == 0:
                    val = validate(
                        ema, reader, {k: v.to(dev) if k == "crop" else v for k, v in val_batch.items()}, val_lengths, cfg.val_steps
                    )
                if writer and (step % 10 == 0 or val):
                    writer.writerow([step, f"{loss.item():.5f}", f"{sched.get_last_lr()[0]:.2e}", f"{time.time() - start:.1f}",
                                     val.get("val_rot_median_deg", ""), val.get("val_rot_within_15deg", "")])  # fmt: skip
                    log.flush()
                if step % cfg.save_every == 0:
                    save()
                if step >= cfg.steps or out_of_time():
                    break
            epoch += 1
            if out_of_time():
                break
        save()
    finally:
        bar.close()
        if log:
            log.close()
        if distributed:
            dist.barrier()
    return step
