"""Weights in safetensors with their configuration dataclass as metadata, so a file always knows what it holds."""

from __future__ import annotations

import dataclasses
import json
import subprocess
from pathlib import Path
from types import UnionType
from typing import Any, TypeVar, Union, get_args, get_origin, get_type_hints

import torch
from safetensors import SafetensorError, safe_open
from safetensors.torch import load_file, save_file

FORMAT = "axispose/1"
ESTIMATOR = "estimator"
"""The kind of an estimator checkpoint (`estimator.py`): AGM, reader and localiser in one file, as the node runs it."""
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


def kind_of(cls: type) -> str | None:
    """The `kind` a config class declares (a field of that name with a default), or None."""
    f = next((f for f in dataclasses.fields(cls) if f.name == "kind"), None)
    return None if f is None or f.default is dataclasses.MISSING else f.default


def _pick_kind(options: list[type], data: dict[str, Any], source: str) -> type:
    """The config class among `options` (the dataclasses a field's type allows) that `data` names by its `kind`;
    without one, the only option. Never the first that happens to fit."""
    kinds = {kind_of(c): c for c in options}
    if "kind" in data:
        if data["kind"] not in kinds:
            raise CheckpointError(f"{source}: kind {data['kind']!r} is not one of {sorted(k for k in kinds if k)}")
        return kinds[data["kind"]]
    if len(options) > 1:
        raise CheckpointError(f"{source}: 'kind' must say which of {sorted(k for k in kinds if k)} this is")
    return options[0]


def nest_moved_keys(cls: type, data: dict[str, Any]) -> dict[str, Any]:
    """`data`, a config dict an earlier version wrote, with the keys that have since moved into a nested section
    put there, at every depth: a key `cls` no longer has goes into the one section that has a field of that name
    and that `data` does not hold yet (e.g. the optimiser's fields before `optim` gathered them)."""
    fields = {f.name for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    hints = get_type_hints(cls)
    sections = {n: t for n, t in hints.items() if n in fields and isinstance(t, type) and dataclasses.is_dataclass(t)}
    out = dict(data)
    for key in [k for k in data if k not in fields and k not in getattr(cls, "RETIRED", ())]:
        homes = [n for n, t in sections.items() if n not in data and key in {f.name for f in dataclasses.fields(t)}]
        if len(homes) == 1:
            out.setdefault(homes[0], {})[key] = out.pop(key)
    return {k: nest_moved_keys(sections[k], v) if k in sections and isinstance(v, dict) else v for k, v in out.items()}


def config_from_dict(cls: type[C], data: dict[str, Any], source: str = "config") -> C:
    """Build a (possibly nested) config dataclass from a dict, naming any missing or unknown key. Where a field
    may hold one of several config classes (a union), their `kind` fields tell them apart. Keys a class lists in
    its `RETIRED` (fields earlier versions wrote that no longer configure anything) are ignored, keys that have
    moved into a nested section are read from where they were (`nest_moved_keys`), and a class with an
    `upgrade_config(data) -> data` rewrites what an earlier version wrote first."""
    if not isinstance(data, dict):
        raise CheckpointError(f"{source}: expected a mapping for {cls.__name__}")
    if callable(upgrade := getattr(cls, "upgrade_config", None)):
        data = upgrade(data)
    fields = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    hints = get_type_hints(cls)
    data = {k: v for k, v in nest_moved_keys(cls, data).items() if k not in getattr(cls, "RETIRED", ())}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise CheckpointError(f"{source}: unknown key(s) {unknown} for {cls.__name__}")
    kwargs = {}
    for name, f in fields.items():
        if name not in data:
            if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                raise CheckpointError(f"{source}: missing key '{name}' for {cls.__name__}")
            continue
        value = data[name]
        ftype = hints.get(name)
        item = get_args(ftype)[0] if get_origin(ftype) is tuple and get_args(ftype) else None
        union = get_args(ftype) if get_origin(ftype) in (Union, UnionType) else ()
        options = [a for a in union if isinstance(a, type) and dataclasses.is_dataclass(a)]
        if isinstance(ftype, type) and dataclasses.is_dataclass(ftype):
            value = config_from_dict(_pick_kind([ftype], value, f"{source}.{name}") if isinstance(value, dict) else ftype, value,
                                     f"{source}.{name}")  # fmt: skip
        elif options and isinstance(value, dict):  # `AConfig | BConfig | None` holding one of them
            value = config_from_dict(_pick_kind(options, value, f"{source}.{name}"), value, f"{source}.{name}")
        elif isinstance(item, type) and dataclasses.is_dataclass(item) and isinstance(value, list):
            value = tuple(config_from_dict(item, v, f"{source}.{name}[{k}]") for k, v in enumerate(value))
        elif isinstance(value, list):
            value = tuple(tuple(v) if isinstance(v, list) else v for v in value)
        kwargs[name] = value
    return cls(**kwargs)


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
