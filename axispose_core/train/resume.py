"""The resume state every trainer keeps beside its checkpoint: OUT.state.pt, read by --resume."""

from __future__ import annotations

import copy
import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from axispose_core.config import nest_moved_keys


def state_path(out: Path) -> Path:
    """Where the resume state of checkpoint `out` lives."""
    return out.with_suffix(out.suffix + ".state.pt")


@dataclass(frozen=True)
class RunParts:
    """What a resume state holds besides the config and the step: the weights being trained, their EMA, the
    optimiser and its LR schedule. Saved and restored together, since a run resumed with one of them missing or
    from another step would silently train another recipe."""

    model: torch.nn.Module
    ema: torch.nn.Module
    opt: torch.optim.Optimizer
    sched: torch.optim.lr_scheduler.LRScheduler


def save_run_state(path: Path, cfg: Any, parts: RunParts, step: int, init: str | None = None, seconds: float = 0.0) -> None:
    """The run's `parts`, step and RNG with its config, written atomically; `init` names the checkpoint a
    warm-started run began from and `seconds` the run's training time so far, so that every later call of the run
    still records both."""
    tmp = path.with_suffix(".tmp")
    torch.save(
        {
            "config": dataclasses.asdict(cfg),
            "model": parts.model.state_dict(),
            "ema": parts.ema.state_dict(),
            "opt": parts.opt.state_dict(),
            "sched": parts.sched.state_dict(),
            "step": step,
            "torch_rng": torch.get_rng_state(),
            "init": init,
            "seconds": seconds,
        },
        tmp,
    )
    tmp.replace(path)


# Fields of `optim` a resumed run may change: its length (the cosine schedule stretches to the new total, so a
# finished run can be extended) and how often it saves and validates. Anything else makes the weights another recipe.
EXTENDABLE = ("steps", "save_every", "val_every")


def _fill_new_fields(saved: dict[str, Any], cfg: Any) -> None:
    """A field added since the state was written (at any depth), left at its default, is the same recipe."""
    now = dataclasses.asdict(cfg)
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        if f.name in saved:
            if dataclasses.is_dataclass(value) and isinstance(saved[f.name], dict):
                _fill_new_fields(saved[f.name], value)
            continue
        if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            continue
        default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
        if now[f.name] == (dataclasses.asdict(default) if dataclasses.is_dataclass(default) else default):
            saved[f.name] = now[f.name]


def load_run_state(
    path: str | Path,
    cfg: Any,
    parts: RunParts,
    data_fields: tuple[str, ...] = (),
    same_data: Callable[[dict[str, Any], int], bool] | None = None,
) -> tuple[int, str | None, float]:
    """Restore a saved run into `parts` and return its step, the checkpoint it was warm-started from
    (None: from scratch) and its training time so far in seconds (0 for a state written before it was kept); a run
    with another recipe is refused. `data_fields` say what the run trains on at each step: they may change where
    `same_data(saved config, saved step)` finds that the new ones give the same data before the saved step (e.g. a
    curriculum stage appended after it), since the weights are then the new recipe's too."""
    state = torch.load(path, map_location="cpu", weights_only=False)
    saved, now = copy.deepcopy(dict(state["config"])), dataclasses.asdict(cfg)
    saved = nest_moved_keys(type(cfg), saved)
    _fill_new_fields(saved, cfg)
    for key in EXTENDABLE:
        saved.get("optim", {}).pop(key, None), now.get("optim", {}).pop(key, None)
    if data_fields and same_data is not None and same_data(saved, state["step"]):
        for key in data_fields:
            saved.pop(key, None), now.pop(key, None)
    if saved != now:
        changed = sorted(k for k in saved.keys() | now.keys() if saved.get(k) != now.get(k))
        raise ValueError(f"{path}: saved by a run with another configuration ({', '.join(changed)}); only "
                         f"optim.{', optim.'.join(EXTENDABLE)} may change on resume, and the data from the saved step on")  # fmt: skip
    parts.model.load_state_dict(state["model"])
    parts.ema.load_state_dict(state["ema"])
    parts.opt.load_state_dict(state["opt"])
    parts.sched.load_state_dict(state["sched"])
    torch.set_rng_state(state["torch_rng"])
    return state["step"], state.get("init"), float(state.get("seconds", 0.0))
