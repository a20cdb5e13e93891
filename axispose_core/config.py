"""Config dataclasses from plain dicts (YAML, JSON, a checkpoint's metadata): one parser for every config, so a
training YAML, a synthetic-data run's synth_config.json and a checkpoint's config read alike and fail alike."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from types import UnionType
from typing import Any, TypeVar, Union, get_args, get_origin, get_type_hints

C = TypeVar("C")


class ConfigError(ValueError):
    """A dict that does not make the config dataclass asked for: a key missing or unknown, or a kind not allowed."""


def yaml_mapping(text: str, empty_ok: bool = False) -> dict:
    """A YAML mapping given inline or as the path of a file holding one (with `empty_ok`, nothing at all is {})."""
    import yaml

    path = Path(text)
    try:
        data = yaml.safe_load(path.read_text() if path.is_file() else text)
    except yaml.YAMLError as err:
        raise ConfigError(f"not YAML: {err}".replace("\n", " ")) from err
    if data is None and empty_ok:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"expected a YAML mapping, got {text!r}")
    return data


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
            raise ConfigError(f"{source}: kind {data['kind']!r} is not one of {sorted(k for k in kinds if k)}")
        return kinds[data["kind"]]
    if len(options) > 1:
        raise ConfigError(f"{source}: 'kind' must say which of {sorted(k for k in kinds if k)} this is")
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


PRESET = {"preset": True}
"""Field metadata of a nested config whose default is a preset rather than its class's defaults (the crop stream's
appearance): a partial section in a config file changes only what it names and keeps the preset's other values."""


def _preset(f: dataclasses.Field) -> Any:
    """A `PRESET` field's default value, None for any other field."""
    if not f.metadata.get("preset"):
        return None
    return f.default if f.default is not dataclasses.MISSING else f.default_factory()  # type: ignore[misc]


def config_from_dict(cls: type[C], data: dict[str, Any], source: str = "config", base: Any = None) -> C:
    """Build a (possibly nested) config dataclass from a dict, naming any missing or unknown key. A key the dict
    leaves out takes `base`'s value where there is one (inside a `PRESET` field's section: the preset's), else the
    field's default. Where a field may hold one of several config classes (a union), their `kind` fields tell them
    apart. Keys a class lists in its `RETIRED` (fields earlier versions wrote that no longer configure anything) are
    ignored, keys that have moved into a nested section are read from where they were (`nest_moved_keys`), and a
    class with an `upgrade_config(data) -> data` rewrites what an earlier version wrote first."""
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: expected a mapping for {cls.__name__}")
    if callable(upgrade := getattr(cls, "upgrade_config", None)):
        data = upgrade(data)
    fields = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    hints = get_type_hints(cls)
    data = {k: v for k, v in nest_moved_keys(cls, data).items() if k not in getattr(cls, "RETIRED", ())}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise ConfigError(f"{source}: unknown key(s) {unknown} for {cls.__name__}")
    kwargs = {}
    for name, f in fields.items():
        if name not in data:
            if base is not None:
                kwargs[name] = getattr(base, name)
            elif f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                raise ConfigError(f"{source}: missing key '{name}' for {cls.__name__}")
            continue
        value = data[name]
        ftype = hints.get(name)
        item = get_args(ftype)[0] if get_origin(ftype) is tuple and get_args(ftype) else None
        union = get_args(ftype) if get_origin(ftype) in (Union, UnionType) else ()
        options = [a for a in union if isinstance(a, type) and dataclasses.is_dataclass(a)]
        within = getattr(base, name) if base is not None else _preset(f)
        if isinstance(ftype, type) and dataclasses.is_dataclass(ftype):
            kind = _pick_kind([ftype], value, f"{source}.{name}") if isinstance(value, dict) else ftype
            value = config_from_dict(kind, value, f"{source}.{name}", within if type(within) is kind else None)
        elif options and isinstance(value, dict):  # `AConfig | BConfig | None` holding one of them
            kind = _pick_kind(options, value, f"{source}.{name}")
            value = config_from_dict(kind, value, f"{source}.{name}", within if type(within) is kind else None)
        elif isinstance(item, type) and dataclasses.is_dataclass(item) and isinstance(value, list):
            value = tuple(config_from_dict(item, v, f"{source}.{name}[{k}]") for k, v in enumerate(value))
        elif isinstance(value, list):
            value = tuple(tuple(v) if isinstance(v, list) else v for v in value)
        kwargs[name] = value
    return cls(**kwargs)
