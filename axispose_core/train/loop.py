"""The single-process training loop the localiser and the direct-regression baseline share.

AdamW, warm-up + cosine, gradient clipping, EMA weights, seeded epoch order, a CSV log with periodic
validation, atomic saves every `save_every` steps and at the end (OUT via `save`, OUT.state.pt for `--resume`),
and `max_minutes` for chains of short runs. (The AGM trainer keeps its own loop for DDP and mixed precision,
but takes its optimisation step and checkpoint training record from here.)
"""

from __future__ import annotations

import copy
import csv
import platform
import time
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import torch
from torch.utils.data import DataLoader, Dataset, RandomSampler
from tqdm import tqdm

from axispose_core.train.resume import load_run_state, save_run_state, state_path
from axispose_core.train.schedule import ema_update, warmup_cosine


def training_device(device: str) -> torch.device:
    """ "auto": CUDA when there is one, else the CPU; otherwise the named device."""
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(device)


def training_record(
    data: list[str | Path], step: int, batch: int, seconds: float, device: torch.device | str, init: str | None = None
) -> dict[str, Any]:
    """What a checkpoint records of the run that made it: data, progress, hardware, and the checkpoint a
    warm-started run began from (None: from scratch)."""
    return {"data": [str(d) for d in data], "steps": step, "batch": batch, "seconds": seconds, "device": str(device),
            "host": platform.processor() or platform.machine(), "init": init}  # fmt: skip


def optimizer_step(
    loss: torch.Tensor,
    model: torch.nn.Module,
    ema: torch.nn.Module,
    opt: torch.optim.Optimizer,
    sched: torch.optim.lr_scheduler.LRScheduler,
    grad_clip: float,
    ema_decay: float,
) -> None:
    """One training step after the loss, the same in every trainer: backward, clip, AdamW, schedule, EMA."""
    opt.zero_grad(set_to_none=True)
    loss.backward()
    torch.nn.utils.clip_grad_norm_(model.parameters(), grad_clip)
    opt.step()
    sched.step()
    ema_update(ema, model, ema_decay)


def fit(
    cfg: Any,
    model: torch.nn.Module,
    train_set: Dataset,
    loss_fn: Callable[[torch.nn.Module, dict[str, torch.Tensor]], torch.Tensor],
    out: Path,
    save: Callable[[torch.nn.Module, int, float, str | None], None],
    validate: Callable[[torch.nn.Module], dict[str, float]] | None = None,
    val_columns: tuple[str, ...] = (),
    resume: str | Path | None = None,
    device: torch.device | str = "cpu",
    max_minutes: float | None = None,
    progress: bool = True,
    desc: str = "train",
    init: str | None = None,
    batches: Callable[[int], Iterable[dict[str, torch.Tensor]]] | None = None,
) -> int:
    """Train `model` for cfg.steps (fields: steps, batch, lr, weight_decay, warmup, grad_clip, ema_decay, seed,
    workers, save_every, val_every; bf16 if it has one); `save(ema, step, seconds, init)` writes the checkpoint.
    Returns the step reached. Seed torch before building `model`, so its initial weights follow cfg.seed too.
    `init` names the checkpoint `model` was warm-started from; a resumed run takes it from its state instead, so
    every call records it. `batches(step)`, where given, yields the training batches from `step` on (e.g. the
    crop stream's) instead of seeded epochs of `train_set`."""
    model = model.to(device)
    ema = copy.deepcopy(model).eval()
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: warmup_cosine(s, cfg.warmup, cfg.steps))
    step = 0
    if resume:
        step, init = load_run_state(resume, cfg, model, ema, opt, sched)
    log = open(out.with_suffix(".csv"), "a", newline="")
    writer = csv.writer(log)
    if step == 0:
        writer.writerow(["step", "loss", "lr", "seconds", *val_columns])
    start = time.time()

    def checkpoint() -> None:
        save(ema, step, time.time() - start, init)
        save_run_state(state_path(out), cfg, model, ema, opt, sched, step, init)

    def out_of_time() -> bool:
        return max_minutes is not None and time.time() - start > 60 * max_minutes

    bar = tqdm(total=cfg.steps, initial=step, desc=desc, disable=not progress)
    bf16 = bool(getattr(cfg, "bf16", False))

    def epochs() -> Iterable[Iterable[dict[str, torch.Tensor]]]:
        if batches is not None:
            yield batches(step)
            return
        epoch = step * cfg.batch // len(train_set)
        while True:
            train_set.epoch = epoch
            sampler = RandomSampler(train_set, generator=torch.Generator().manual_seed(cfg.seed + epoch))
            yield DataLoader(train_set, batch_size=cfg.batch, sampler=sampler, num_workers=cfg.workers, drop_last=True)
            epoch += 1

    try:
        for loader in epochs():
            if step >= cfg.steps or out_of_time():
                break
            for batch in loader:
                model.train()
                with torch.autocast(torch.device(device).type, dtype=torch.bfloat16, enabled=bf16):
                    loss = loss_fn(model, {k: v.to(device) for k, v in batch.items()})
                optimizer_step(loss, model, ema, opt, sched, cfg.grad_clip, cfg.ema_decay)
                step += 1
                bar.update(1)
                bar.set_postfix(loss=f"{loss.item():.4f}")
                val = validate(ema) if validate is not None and step % cfg.val_every == 0 else {}
                if step % 10 == 0 or val:
                    writer.writerow([step, f"{loss.item():.5f}", f"{sched.get_last_lr()[0]:.2e}", f"{time.time() - start:.1f}",
                                     *(val.get(c, "") for c in val_columns)])  # fmt: skip
                    log.flush()
                if step % cfg.save_every == 0:
                    checkpoint()
                if step >= cfg.steps or out_of_time():
                    break
        checkpoint()
    finally:
        bar.close()
        log.close()
    return step
