"""Weights in safetensors with their configuration dataclass as metadata, so a file always knows what it holds."""

from __future__ import annotations

import dataclasses
import json
import subprocess
from pathlib import Path
from typing import Any, TypeVar

import torch
from safetensors import SafetensorError, safe_open
from safetensors.torch import load_file, save_file

from axispose_core.config import config_from_dict

FORMAT = "axispose/1"
ESTIMATOR = "estimator"
"""The kind of an estimator checkpoint (`estimator_checkpoint.py`): AGM, reader and localiser in one file, as the node runs it."""
C = TypeVar("C")


class CheckpointError(ValueError):
    """The file is not an AxisPose checkpoint of the expected kind, or its config or tensors do not match."""


def git_commit() -> str:
    """The source commit, recorded in checkpoints for provenance ('unknown' outside a git checkout)."""
    try:
        out = subprocess.run(["git", "rev-parse", "HEAD"], cwd=Path(__file__).parent, capture_output=True, text=True, timeout=5, check=True)
        return out.stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def save_checkpoint(
    path: str | Path,
    kind: str,
    config: Any,
    modules: dict[str, torch.nn.Module],
    extra: dict[str, Any] | None = None,
    half: bool = False,
) -> None:
    """Write the modules' state dicts (prefixed by their names) and the config dataclass into one safetensors file;
    `half` stores floating-point tensors as float16 (half the size; loading casts them back to the module's dtype)."""
    tensors = {}
    for prefix, module in modules.items():
        for key, value in module.state_dict().items():
            value = value.detach().cpu()
            tensors[f"{prefix}.{key}"] = (value.half() if half and value.is_floating_point() else value).contiguous()
    meta = {
        "format": FORMAT,
        "kind": kind,
        "config": json.dumps(dataclasses.asdict(config)),
        "extra": json.dumps(extra or {}),
        "git_commit": git_commit(),
    }
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    save_file(tensors, str(tmp), metadata=meta)
    tmp.chmod(0o644)  # safetensors writes 0600; a shipped or shared checkpoint must be readable by all
    tmp.replace(path)


def stored_half(path: str | Path) -> bool:
    """Whether the checkpoint stores its floating-point tensors as float16 (`save_checkpoint(half=True)`), so a tool
    that rewrites it in place keeps its size: the shipped file in float32 would be twice its 20 MB budget."""
    try:
        with safe_open(str(path), framework="pt") as f:
            return any(f.get_slice(key).get_dtype() == "F16" for key in f.keys())
    except (SafetensorError, OSError, ValueError) as err:
        raise CheckpointError(f"{path}: not a readable safetensors file ({err})") from err


def read_metadata(path: str | Path, kind: str | None) -> dict[str, str]:
    """The metadata of an AxisPose checkpoint of `kind` (None: any), or CheckpointError saying why the file is not one."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: checkpoint file not found")
    try:
        with safe_open(str(path), framework="pt") as f:
            meta = f.metadata() or {}
    except (SafetensorError, OSError, ValueError) as err:
        raise CheckpointError(f"{path}: not a readable safetensors file ({err})") from err
    if meta.get("format") != FORMAT:
        raise CheckpointError(f"{path}: not an AxisPose checkpoint (format {meta.get('format')!r}, expected {FORMAT!r})")
    if kind is not None and meta.get("kind") != kind:
        raise CheckpointError(f"{path}: holds a {meta.get('kind')!r} model, expected {kind!r}")
    return meta


def read_checkpoint(
    path: str | Path, kind: str, config_cls: type[C], section: str | None = None
) -> tuple[C | None, dict[str, dict[str, torch.Tensor]], dict[str, Any]]:
    """Read a checkpoint of `kind`: (config, state dicts by module name, extra metadata).

    `section` reads only that field of the config as `config_cls` (None when the checkpoint has none), so one
    part of a composite checkpoint, e.g. an estimator's localiser, loads whatever version its other parts are."""
    meta = read_metadata(path, kind)
    try:
        tensors = load_file(str(path))
    except (SafetensorError, OSError, ValueError) as err:
        raise CheckpointError(f"{path}: tensors unreadable ({err})") from err
    try:
        raw = json.loads(meta["config"])
        if section is not None:
            raw = raw.get(section)
        config = None if raw is None else config_from_dict(config_cls, raw, f"{path}: config" + (f".{section}" if section else ""))
        extra = json.loads(meta.get("extra", "{}"))
    except (KeyError, ValueError, TypeError) as err:  # ValueError: JSON, or a config that refuses its values
        raise CheckpointError(f"{path}: config metadata unreadable ({err})") from err
    states: dict[str, dict[str, torch.Tensor]] = {}
    for key, value in tensors.items():
        prefix, _, rest = key.partition(".")
        states.setdefault(prefix, {})[rest] = value
    return config, states, extra


def upgrade_state(module: torch.nn.Module, state: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """`state` with the names an earlier version saved under renamed as `module` names them now: every submodule
    that moved weights has an `upgrade_state(state, prefix)` that renames its own in place."""
    state = dict(state)
    for name, sub in module.named_modules():
        if callable(upgrade := getattr(sub, "upgrade_state", None)):
            upgrade(state, f"{name}." if name else "")
    return state


def load_state(module: torch.nn.Module, state: dict[str, torch.Tensor], source: str) -> None:
    """load_state_dict (after `upgrade_state`) with an error that lists what is missing, unexpected or mis-shaped."""
    state = upgrade_state(module, state)
    own = module.state_dict()
    missing = sorted(set(own) - set(state))
    unexpected = sorted(set(state) - set(own))
    shapes = sorted(k for k in set(own) & set(state) if own[k].shape != state[k].shape)
    if missing or unexpected or shapes:
        raise CheckpointError(
            f"{source}: weights do not match the network built from its config "
            f"(missing {missing[:5]}, unexpected {unexpected[:5]}, shape mismatch {shapes[:5]})"
        )
    module.load_state_dict(state)
