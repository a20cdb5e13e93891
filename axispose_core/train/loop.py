"""The training loop every trainer (AGM, localiser, keypoint reader, direct baseline) runs, and its settings.

AdamW, linear warm-up then cosine decay, gradient clipping, EMA weights (what checkpoints hold), bf16 autocast,
a CSV log (OUT.csv: loss, learning rate, samples seen, training time summed over resumed calls, periodic held-out
metrics), atomic saves every `save_every` steps and at the end (OUT via the trainer's `save`, OUT.state.pt for
`--resume`), and `max_minutes` for chains of short runs. Under `torchrun` (a process group initialised) the model
is wrapped in DistributedDataParallel and rank 0 alone logs, validates and saves.
"""

from __future__ import annotations

import copy
import csv
import hashlib
import math
import platform
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
import torch.distributed as dist
from torch.utils.data import DataLoader, Dataset, DistributedSampler, RandomSampler
from tqdm import tqdm

from axispose_core.precision import bf16_native
from axispose_core.train.resume import RunParts, load_run_state, save_run_state, state_path
from axispose_core.trunks import Trunk

Batch = dict[str, torch.Tensor]


@dataclass(frozen=True)
class OptimConfig:
    """How a run optimises: the `optim` section of every trainer's config (each trainer has its own defaults)."""

    steps: int = 20000
    batch: int = 32
    lr: float = 1e-3
    weight_decay: float = 1e-4
    warmup: int = 200
    grad_clip: float = 1.0
    ema_decay: float = 0.995
    seed: int = 0
    """Seeds the initial weights, the data order and the loss's randomness (e.g. diffusion noise)."""
    workers: int = 1
    save_every: int = 200
    val_every: int = 500
    bf16: bool = False
    """bfloat16 autocast where the device computes it natively (1.6-1.8x faster steps on a CPU with AVX-512 BF16);
    elsewhere the run stays in float32, since emulated bfloat16 is about ten times slower (`precision.bf16_native`)."""
    trunk_lr: float = 1.0
    """Learning-rate factor of a pretrained trunk's stages (below 1: the ImageNet features move less than the
    layers trained from scratch)."""
    freeze_trunk: int = 0
    """A pretrained trunk's first stages kept as loaded: no gradient, BatchNorm statistics fixed."""
    freeze_trunk_batchnorm: bool = False
    """A pretrained trunk's BatchNorm statistics fixed in every stage, the trainable ones included."""


def warmup_cosine(step: int, warmup: int, total: int) -> float:
    """LR factor: linear warm-up over `warmup` steps, then cosine decay to 0 at `total`."""
    if step < warmup:
        return (step + 1) / warmup
    return 0.5 * (1 + math.cos(math.pi * min(1.0, (step - warmup) / max(1, total - warmup))))


@torch.no_grad()
def ema_update(ema: torch.nn.Module, model: torch.nn.Module, decay: float) -> None:
    """ema <- decay * ema + (1 - decay) * model for parameters; buffers (e.g. BatchNorm statistics) copied."""
    for pe, pm in zip(ema.parameters(), model.parameters(), strict=True):
        pe.lerp_(pm, 1 - decay)
    for be, bm in zip(ema.buffers(), model.buffers(), strict=True):
        be.copy_(bm)


@dataclass(frozen=True)
class RunOptions:
    """How one call of a trainer runs, as against what it trains (its config): the state to resume, the device
    ("auto": CUDA when there is one), a wall-time cap after which it saves and stops, a step at which it saves and
    stops (a recipe stage whose schedule changes its length part-way: `train/recipe.py`), and a progress bar."""

    resume: str | Path | None = None
    device: str = "auto"
    max_minutes: float | None = None
    stop_at: int | None = None
    progress: bool = True


DEFAULT_RUN = RunOptions()


def training_device(device: str) -> torch.device:
    """ "auto": CUDA when there is one, else the CPU; otherwise the named device."""
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(device)


def world() -> tuple[int, int]:
    """(rank, world size) of this process: (0, 1) unless a torch.distributed process group is initialised."""
    if dist.is_available() and dist.is_initialized():
        return dist.get_rank(), dist.get_world_size()
    return 0, 1


def training_record(
    data: list[str | Path], step: int, batch: int, seconds: float, device: torch.device | str, init: str | None = None
) -> dict[str, Any]:
    """What a checkpoint records of the run that made it: data, progress, hardware, and the checkpoint a
    warm-started run began from (None: from scratch)."""
    return {"data": [str(d) for d in data], "steps": step, "batch": batch, "seconds": seconds, "device": str(device),
            "host": platform.processor() or platform.machine(), "init": init}  # fmt: skip


def epochs(dataset: Dataset, optim: OptimConfig) -> Callable[[int], Iterator[Batch]]:
    """Batches of seeded epochs over `dataset` from a step on (the dataset's `epoch` attribute, where it has one,
    set for its own per-epoch randomness); each rank of a distributed run takes its share of every epoch."""
    _, size = world()

    def batches(step: int) -> Iterator[Batch]:
        epoch = step * optim.batch * size // len(dataset)
        while True:
            dataset.epoch = epoch
            sampler = (
                DistributedSampler(dataset, seed=optim.seed + epoch)
                if size > 1
                else RandomSampler(dataset, generator=torch.Generator().manual_seed(optim.seed + epoch))
            )
            yield from DataLoader(dataset, batch_size=optim.batch, sampler=sampler, num_workers=optim.workers, drop_last=True)
            epoch += 1

    return batches


def pretrained_trunks(model: torch.nn.Module) -> list[Trunk]:
    """The trunks in `model` that training starts from learned weights."""
    return [m for m in model.modules() if isinstance(m, Trunk) and m.pretrained]


def start_pretrained(model: torch.nn.Module) -> None:
    """Load the learned weights of `model`'s pretrained trunks: what a trainer does to a network it has just built,
    before copying a checkpoint's weights into it (which then win where they cover the trunk)."""
    for trunk in pretrained_trunks(model):
        trunk.load_pretrained()


def param_groups(model: torch.nn.Module, optim: OptimConfig) -> list[dict[str, Any]]:
    """The optimiser's parameter groups: everything trainable at optim.lr, then the pretrained trunks' trainable
    stages at optim.lr * optim.trunk_lr (where there are any); frozen stages are left out."""
    trunk = {id(p) for t in pretrained_trunks(model) for p in t.parameters()}
    rest = [p for p in model.parameters() if p.requires_grad and id(p) not in trunk]
    pretrained = [p for p in model.parameters() if p.requires_grad and id(p) in trunk]
    groups = [{"params": rest, "lr": optim.lr}]
    return groups + ([{"params": pretrained, "lr": optim.lr * optim.trunk_lr}] if pretrained else [])


LossFn = Callable[[torch.nn.Module, Batch, torch.Generator], torch.Tensor]
"""(net, batch on the device, the run's seeded generator) -> the loss."""
SaveFn = Callable[[torch.nn.Module, int, float, str | None], None]
"""(EMA weights, step, the run's training time in seconds, the checkpoint it was warm-started from) -> None."""


@dataclass(frozen=True)
class Validation:
    """The CSV's held-out metric columns and `metrics(ema)`, which gives them every optim.val_every steps (None: the
    columns stay empty, e.g. a run without held-out data, so that every run of a trainer writes the same header)."""

    columns: tuple[str, ...] = ()
    metrics: Callable[[torch.nn.Module], dict[str, float]] | None = None


@dataclass(frozen=True)
class TrainJob:
    """What a trainer hands `fit`: what it trains, on what, to which loss, where it saves and how it validates.

    `cfg` is the trainer's config (its `optim` the `OptimConfig`), saved in the resume state; it must match on
    resume but for the run's length, how often it saves and validates, and `data_fields` where `same_data` accepts
    them (`load_run_state`). Seed torch with cfg.optim.seed before building `model`, so its initial weights follow
    the seed too. `batches(step)` yields the training batches from `step` on (the crop stream's next samples, or
    `epochs`), so a resumed run continues where it stopped. `save` writes the checkpoint `out`; beside it go
    OUT.state.pt and OUT.csv. `device` is where `RunOptions.device` resolved to (the trainer's: under torchrun,
    the local rank's GPU). `init` names the checkpoint `model` was warm-started from; a resumed run takes it from
    its state, so that every call records it. `objective(model)`, where given, is the module whose forward
    computes the loss (`train/losses.py`): what `loss` is handed and DistributedDataParallel wraps, while the
    model's own state is what the EMA, the checkpoints and the resume state hold."""

    cfg: Any
    model: torch.nn.Module
    batches: Callable[[int], Iterable[Batch]]
    loss: LossFn
    out: Path
    save: SaveFn
    validation: Validation = Validation()
    device: torch.device | str = "cpu"
    desc: str = "train"
    init: str | None = None
    data_fields: tuple[str, ...] = ()
    same_data: Callable[[dict[str, Any], int], bool] | None = None
    objective: Callable[[torch.nn.Module], torch.nn.Module] | None = None


def _run_parts(job: TrainJob) -> RunParts:
    """The model on the device with its pretrained trunks' first optim.freeze_trunk stages frozen, its EMA copy,
    AdamW over `param_groups` and the warm-up-cosine schedule: what the resume state saves and restores."""
    optim: OptimConfig = job.cfg.optim
    for trunk in pretrained_trunks(job.model):
        trunk.freeze(optim.freeze_trunk, optim.freeze_trunk_batchnorm)
    model = job.model.to(job.device)
    ema = copy.deepcopy(model).eval()
    opt = torch.optim.AdamW(param_groups(model, optim), lr=optim.lr, weight_decay=optim.weight_decay)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: warmup_cosine(s, optim.warmup, optim.steps))
    return RunParts(model, ema, opt, sched)


def _bf16_autocast(optim: OptimConfig, device: torch.device | str, rank: int) -> bool:
    """Whether steps run under bfloat16 autocast: asked for and native on `device`; says so where it is not."""
    autocast = optim.bf16 and bf16_native(torch.device(device))
    if optim.bf16 and not autocast and rank == 0:
        device_type = torch.device(device).type
        print(f"bf16: {device_type} has no native bfloat16; training in float32 (emulated bfloat16 is ~10x slower)")
    return autocast


class _Session:
    """One call of `fit` under way: the parts it trains, the step reached, its clock and rank 0's CSV log. Kept
    apart from `fit` so that each step of a training step (optimise, validate, log, save) has a name."""

    def __init__(self, job: TrainJob, run: RunOptions, parts: RunParts, resumed: tuple[int, str | None, float]) -> None:
        """Open the log and start the clock; `resumed`: the step, init and seconds `load_run_state` gave."""
        self.job, self.run, self.parts, self.optim = job, run, parts, job.cfg.optim
        self.rank, self.size = world()
        self.step, self.init, self.before = resumed
        self.columns = job.validation.columns
        self.log = open(job.out.with_suffix(".csv"), "a", newline="") if self.rank == 0 else None
        self.writer = csv.writer(self.log) if self.log else None
        if self.writer and self.step == 0:
            self.writer.writerow(["step", "samples", "loss", "lr", "seconds", *self.columns])
        self.start = time.time()

    def seconds(self) -> float:
        """The run's training time over all its calls: the checkpoint's record and the CSV's clock."""
        return self.before + time.time() - self.start

    def done(self) -> bool:
        """The end of the schedule or of this call: the last step, the stop step, or the wall-time cap."""
        if self.step >= self.optim.steps or (self.run.stop_at is not None and self.step >= self.run.stop_at):
            return True
        return self.run.max_minutes is not None and time.time() - self.start > 60 * self.run.max_minutes

    def checkpoint(self) -> None:
        """Rank 0 saves the EMA weights (the trainer's `save`) and the resume state beside them."""
        if self.rank == 0:
            now = self.seconds()
            self.job.save(self.parts.ema, self.step, now, self.init)
            save_run_state(state_path(self.job.out), self.job.cfg, self.parts, self.step, self.init, now)

    def train_step(self, net: torch.nn.Module, batch: Batch, gen: torch.Generator, autocast: bool) -> torch.Tensor:
        """One optimiser step on `batch` (clipped, scheduled, EMA updated); the loss."""
        parts, device = self.parts, self.job.device
        parts.model.train()
        with torch.autocast(torch.device(device).type, dtype=torch.bfloat16, enabled=autocast):
            loss = self.job.loss(net, {k: v.to(device) for k, v in batch.items()}, gen)
        parts.opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(parts.model.parameters(), self.optim.grad_clip)
        parts.opt.step()
        parts.sched.step()
        ema_update(parts.ema, parts.model, self.optim.ema_decay)
        self.step += 1
        return loss

    def record(self, loss: torch.Tensor) -> None:
        """After a step: rank 0 validates every val_every steps and logs every 10th step (and each validated
        one); everyone saves every save_every steps."""
        step, metrics = self.step, self.job.validation.metrics
        val = metrics(self.parts.ema) if metrics is not None and self.rank == 0 and step % self.optim.val_every == 0 else {}
        if self.writer and (step % 10 == 0 or val):
            self.writer.writerow([step, step * self.optim.batch * self.size, f"{loss.item():.5f}",
                                  f"{self.parts.sched.get_last_lr()[0]:.2e}", f"{self.seconds():.1f}",
                                  *(val.get(c, "") for c in self.columns)])  # fmt: skip
            self.log.flush()
        if step % self.optim.save_every == 0:
            self.checkpoint()


def step_seed(seed: int, step: int, rank: int) -> int:
    """The seed of the loss's randomness (e.g. diffusion noise) at one step of one rank: a function of the step, so a
    resumed run draws what the uninterrupted run would have."""
    return int.from_bytes(hashlib.sha256(f"{seed}/{step}/{rank}".encode()).digest()[:8], "little")


def fit(job: TrainJob, run: RunOptions = DEFAULT_RUN) -> int:
    """Train `job.model` for cfg.optim.steps, as `run` says (resume, stop, progress); returns the step reached.

    AdamW over `param_groups` with warm-up then cosine decay, gradient clipping, EMA weights (what the checkpoints
    hold) and bf16 autocast where native; pretrained trunks (`start_pretrained`) have their first
    optim.freeze_trunk stages frozen and train the rest at optim.trunk_lr times the rate. Under torchrun the
    model (or its objective) is wrapped in DistributedDataParallel and rank 0 alone logs, validates and saves."""
    parts = _run_parts(job)
    resumed = load_run_state(run.resume, job.cfg, parts, job.data_fields, job.same_data) if run.resume else (0, job.init, 0.0)
    trained = job.objective(parts.model) if job.objective is not None else parts.model
    net = torch.nn.parallel.DistributedDataParallel(trained) if world()[1] > 1 else trained
    session = _Session(job, run, parts, resumed)
    gen = torch.Generator()
    autocast = _bf16_autocast(session.optim, job.device, session.rank)
    bar = tqdm(total=session.optim.steps, initial=session.step, desc=job.desc, disable=not run.progress or session.rank != 0)
    try:
        for batch in job.batches(session.step) if not session.done() else ():
            gen.manual_seed(step_seed(session.optim.seed, session.step, session.rank))
            loss = session.train_step(net, batch, gen, autocast)
            bar.update(1)
            bar.set_postfix(loss=f"{loss.item():.4f}")
            session.record(loss)
            if session.done():
                break
        session.checkpoint()
    finally:
        bar.close()
        if session.log:
            session.log.close()
        if session.size > 1:
            dist.barrier()
    return session.step
