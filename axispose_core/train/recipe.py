"""`axispose train --recipe`: a model's whole training as data, run stage by stage, resumable, and assembled into
one estimator checkpoint (AGM, keypoint reader, localiser). This module reads and checks a recipe; the runner
(`recipe_runner.py`) builds it.

A recipe (YAML; the shipped model's: config/recipes/axispose_lmo.yaml) holds
- `models`: the BOP models folder that the crop stream and the synthetic frames render;
- `data`: synthetic BOP folders by name (`axispose synth` settings), rendered under OUT/data/NAME when a stage
  needs them;
- `stages`: each a trainer (reader, agm, localiser); its config, a YAML file or a mapping, or without one the
  config of the same trainer's stage before, with `changes` merged into it; the stage whose weights it starts
  from (`init`; an AGM stage's with its trunk anew, drawn with the seed `fresh_trunk`); the data a localiser
  stage trains and validates on; and its `schedule` where the cosine's length changes part-way (segments of
  `steps`, each but the last stopping at `until`);
- `estimator`: the stages that make the checkpoint, the estimator settings it ships with (`config.refine`: the
  contour refiner's, which attaches the meshes of `models`), and the detection verifier fitted on the assembled
  checkpoint (`verifier`: the data it is fitted on and its `VerifierFitConfig`);
- `adapt` (optional): the assembled checkpoint adapted to a recording of the scene, `axispose adapt`'s rounds on
  its frames (`recording`: a BOP scene folder, whose labels are never read; `config`: `AdaptConfig`'s fields, a
  YAML file or a mapping); the checkpoint is then the adapted one.
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from axispose_core.adapt.run import AdaptConfig
from axispose_core.config import ConfigError, config_from_dict
from axispose_core.data.synth.config import RandomizationConfig, SceneConfig, SynthConfig
from axispose_core.data.synth.config import recipe as synth_recipe
from axispose_core.estimator_checkpoint import EstimatorConfig
from axispose_core.refine.config import RefineConfig
from axispose_core.train.agm import TrainConfig
from axispose_core.train.localiser import LocaliserTrainConfig
from axispose_core.train.reader import ReaderTrainConfig
from axispose_core.train.verifier import VerifierFitConfig

CONFIGS: dict[str, type] = {"reader": ReaderTrainConfig, "agm": TrainConfig, "localiser": LocaliserTrainConfig}
"""Each trainer's config class, by the name a stage gives as its `trainer`."""

SYNTH_KEYS = {"scenes", "images_per_scene", "seed", "recipe", "depth", "objects", "scene", "randomization"}
STAGE_KEYS = {"name", "trainer", "config", "changes", "init", "fresh_trunk", "data", "val", "schedule"}
ESTIMATOR_KEYS = {"agm", "reader", "localiser", "config", "half", "verifier"}
ADAPT_KEYS = {"recording", "config"}
ESTIMATOR_SETTINGS = {f.name for f in dataclasses.fields(EstimatorConfig)} - {"agm", "reader", "objects", "training", "localiser",
                                                                               "verifier"}  # fmt: skip


class RecipeError(ValueError):
    """A recipe that cannot be run, or an output folder built by another recipe: one line saying which and why."""


@dataclass(frozen=True)
class Segment:
    """A stretch of a stage's run with one schedule length."""

    steps: int
    """optim.steps while this segment trains: the step the cosine schedule decays to 0 at."""
    until: int | None = None
    """The step the segment stops at (None: the schedule's end, `steps`)."""
    data: tuple[str, ...] = ()
    """A localiser segment's frames where they differ from the stage's (a run given new frames on resume)."""


@dataclass(frozen=True)
class Stage:
    name: str
    trainer: str
    config: dict[str, Any]
    """The trainer's whole config, resolved (its optim.steps: the last segment's)."""
    init: str | None = None
    data: tuple[str, ...] = ()
    val: tuple[str, ...] = ()
    schedule: tuple[Segment, ...] = ()
    fresh_trunk: int | None = None
    """An AGM stage's seed for a new trunk under its init's denoiser (`agm/model.py: fresh_trunk`); None: init's
    weights as they are."""

    def segment_config(self, segment: Segment) -> Any:
        """The trainer's config dataclass as this segment runs it."""
        cfg = config_from_dict(CONFIGS[self.trainer], self.config, f"stage {self.name}")
        return dataclasses.replace(cfg, optim=dataclasses.replace(cfg.optim, steps=segment.steps))

    @property
    def sha256(self) -> str:
        return _sha256(_stage_dict(self))


@dataclass(frozen=True)
class Recipe:
    models: str
    data: dict[str, dict[str, Any]]
    stages: tuple[Stage, ...]
    estimator: dict[str, Any]
    adapt: dict[str, Any] | None = None
    """`recording` and the resolved `config` mapping, or None: the assembled checkpoint is the recipe's."""

    def stage(self, name: str) -> Stage:
        return next(s for s in self.stages if s.name == name)

    def as_dict(self) -> dict[str, Any]:
        """The resolved recipe: what the checkpoint records and the hash covers."""
        out = {"models": self.models, "data": self.data, "stages": [_stage_dict(s) for s in self.stages], "estimator": self.estimator}
        return out | ({"adapt": self.adapt} if self.adapt is not None else {})  # a recipe without one hashes as before

    def adapt_config(self) -> AdaptConfig:
        """The adaptation's settings (the recipe has an `adapt`)."""
        return config_from_dict(AdaptConfig, self.adapt["config"], "adapt: config")

    @property
    def sha256(self) -> str:
        return _sha256(self.as_dict())

    def needed(self, built: Callable[[str], bool] = lambda name: False) -> list[Stage]:
        """The stages the checkpoint needs, in the recipe's order: the estimator's three and what they start from
        (an AGM stage also needs the reader, which validates it and goes into its checkpoint), except what a stage
        already `built` (done or adopted) started from."""
        want: set[str] = set()
        todo = [self.estimator[k] for k in ("agm", "reader", "localiser")]
        while todo:
            name = todo.pop()
            if name in want:
                continue
            want.add(name)
            stage = self.stage(name)
            if built(name):
                continue
            todo += [stage.init] if stage.init else []
            todo += [self.estimator["reader"]] if stage.trainer == "agm" else []
        return [s for s in self.stages if s.name in want]


def _stage_dict(stage: Stage) -> dict[str, Any]:
    d = dataclasses.asdict(stage)
    if stage.fresh_trunk is None:  # the records of recipes from before the key stay as they were
        del d["fresh_trunk"]
    d["schedule"] = [{k: v for k, v in dataclasses.asdict(s).items() if k != "data" or v} for s in stage.schedule]
    return d


def _sha256(data: Any) -> str:
    return hashlib.sha256(json.dumps(data, sort_keys=True, default=list).encode()).hexdigest()


def _merge(base: dict[str, Any], changes: dict[str, Any]) -> dict[str, Any]:
    """`base` with `changes` merged in at every depth (a mapping merges into a mapping, unless it names another
    `kind`: another class fills that slot, and none of the old one's fields carry over; anything else replaces)."""
    out = copy.deepcopy(base)
    for k, v in changes.items():
        merges = isinstance(v, dict) and isinstance(out.get(k), dict) and v.get("kind", out[k].get("kind")) == out[k].get("kind")
        out[k] = _merge(out[k], v) if merges else copy.deepcopy(v)
    return out


def _yaml_file(path: str, near: Path) -> dict[str, Any]:
    """A YAML mapping from `path`: relative to the current folder, else to the recipe's folder and those above it
    (a recipe in config/recipes/ names config/train_agm.yaml as from the repository's root)."""
    candidates = [Path(path)] + [d / path for d in (near, *near.parents)]
    found = next((p for p in candidates if p.is_file()), None)
    if found is None:
        raise RecipeError(f"config file {path} not found")
    data = yaml.safe_load(found.read_text()) or {}
    if not isinstance(data, dict):
        raise RecipeError(f"{found}: expected a mapping")
    return data


def _unknown(what: str, keys: set[str], allowed: set[str]) -> None:
    if extra := keys - allowed:
        raise RecipeError(f"{what}: unknown key(s) {', '.join(sorted(extra))} (allowed: {', '.join(sorted(allowed))})")


def _schedule(name: str, raw: Any, steps: int) -> tuple[Segment, ...]:
    if raw is None:
        return (Segment(steps),)
    if not isinstance(raw, list) or not raw:
        raise RecipeError(f"stage {name}: schedule must be a list of segments {{steps, until}}")
    segments = []
    for seg in raw:
        _unknown(f"stage {name}: schedule segment", set(seg), {"steps", "until", "data"})
        until = seg.get("until")
        segments.append(Segment(int(seg["steps"]), None if until is None else int(until), tuple(seg.get("data") or ())))
    untils = [s.until for s in segments[:-1]]
    if None in untils or untils != sorted(untils) or (segments[-1].until is not None and untils and segments[-1].until <= untils[-1]):
        raise RecipeError(f"stage {name}: every segment but the last stops at `until`, at increasing steps")
    if any(s.until is not None and s.until > s.steps for s in segments):
        raise RecipeError(f"stage {name}: a segment cannot stop after its schedule's end (until > steps)")
    return tuple(segments)


def load_recipe(path: str | Path) -> Recipe:
    """Read and resolve a recipe, checking every stage's config against its trainer's config class and every name
    a stage or the estimator refers to, so that a mistake shows before hours of training."""
    path = Path(path)
    try:
        raw = yaml.safe_load(path.read_text()) or {}
    except (OSError, yaml.YAMLError) as err:
        raise RecipeError(f"{path}: cannot read the recipe ({err})") from err
    if not isinstance(raw, dict):
        raise RecipeError(f"{path}: expected a mapping")
    _unknown(str(path), set(raw), {"models", "data", "stages", "estimator", "adapt"})
    data = {str(k): dict(v or {}) for k, v in (raw.get("data") or {}).items()}
    for name, spec in data.items():
        _unknown(f"data {name}", set(spec), SYNTH_KEYS)
        if "scenes" not in spec or "seed" not in spec:
            raise RecipeError(f"data {name}: needs scenes and seed")
        try:
            synth_config(spec)  # an unknown frame recipe or a bad randomization key, named
        except (ConfigError, TypeError, ValueError) as err:
            raise RecipeError(f"data {name}: {err}") from err
    stages: list[Stage] = []
    last: dict[str, dict[str, Any]] = {}
    for i, s in enumerate(raw.get("stages") or []):
        name = str(s.get("name", f"#{i}"))
        _unknown(f"stage {name}", set(s), STAGE_KEYS)
        trainer = s.get("trainer")
        if trainer not in CONFIGS:
            raise RecipeError(f"stage {name}: trainer must be one of {', '.join(CONFIGS)}, got {trainer!r}")
        if any(st.name == name for st in stages):
            raise RecipeError(f"stage {name}: the name is taken by an earlier stage")
        base = s.get("config")
        base = _yaml_file(base, path.parent) if isinstance(base, str) else dict(base) if base else last.get(trainer, {})
        config = _merge(base, s.get("changes") or {})
        try:
            cfg = config_from_dict(CONFIGS[trainer], config, f"stage {name}")
        except (ConfigError, TypeError, ValueError) as err:
            raise RecipeError(str(err)) from err
        schedule = _schedule(name, s.get("schedule"), cfg.optim.steps)
        config = _merge(config, {"optim": {"steps": schedule[-1].steps}})
        last[trainer] = config
        init = s.get("init")
        if init is not None and not any(st.name == init and st.trainer == trainer for st in stages):
            raise RecipeError(f"stage {name}: init {init!r} is not an earlier {trainer} stage")
        fresh = s.get("fresh_trunk")
        if fresh is not None and (trainer != "agm" or init is None or type(fresh) is not int):
            raise RecipeError(f"stage {name}: fresh_trunk (a seed) is for an agm stage with an init")
        refs = (tuple(s.get("data") or ()), tuple(s.get("val") or ()))
        if trainer == "localiser" and not refs[0]:
            raise RecipeError(f"stage {name}: a localiser stage needs data")
        if missing := [d for d in (*refs[0], *refs[1], *(d for seg in schedule for d in seg.data)) if d not in data]:
            raise RecipeError(f"stage {name}: data {', '.join(missing)} not in the recipe's data")
        stages.append(Stage(name, trainer, config, init, *refs, schedule, fresh))
    est = dict(raw.get("estimator") or {})
    _unknown("estimator", set(est), ESTIMATOR_KEYS)
    for part in ("agm", "reader", "localiser"):
        if not any(st.name == est.get(part) and st.trainer == part for st in stages):
            raise RecipeError(f"estimator: {part} must name a {part} stage, got {est.get(part)!r}")
    _unknown("estimator: config", set(est.get("config") or {}), ESTIMATOR_SETTINGS)
    if "refine" in (est.get("config") or {}):
        refine_config(est["config"]["refine"])
    if "verifier" in est:
        verifier_spec(dict(est["verifier"] or {}), data)
    est = {"config": {}, "half": False} | est
    return Recipe(str(raw.get("models", "")), data, tuple(stages), est, _adapt(raw.get("adapt"), path.parent))


def _adapt(raw: Any, near: Path) -> dict[str, Any] | None:
    """The recipe's `adapt`, its config resolved to a mapping and checked against AdaptConfig."""
    if raw is None:
        return None
    if not isinstance(raw, dict) or not raw.get("recording"):
        raise RecipeError("adapt: needs recording (a BOP scene folder of the scene's frames)")
    _unknown("adapt", set(raw), ADAPT_KEYS)
    config = raw.get("config")
    config = _yaml_file(config, near) if isinstance(config, str) else dict(config or {})
    try:
        config_from_dict(AdaptConfig, config, "adapt: config")
    except (ConfigError, TypeError, ValueError) as err:
        raise RecipeError(str(err)) from err
    return {"recording": str(raw["recording"]), "config": config}


def refine_config(spec: Any) -> RefineConfig:
    """The estimator's `config.refine`: the contour refiner's settings (a mapping; {} for the defaults)."""
    try:
        return config_from_dict(RefineConfig, spec or {}, "estimator: config.refine")
    except (ConfigError, TypeError, ValueError) as err:
        raise RecipeError(str(err)) from err


def verifier_spec(spec: dict[str, Any], data: dict[str, dict[str, Any]]) -> tuple[tuple[str, ...], VerifierFitConfig]:
    """The estimator's `verifier` entry: the recipe's data it is fitted on and how."""
    names = tuple(spec.pop("data", None) or ())
    if not names or any(d not in data for d in names):
        raise RecipeError(f"estimator: verifier needs data from the recipe's data, got {names or 'none'}")
    try:
        return names, config_from_dict(VerifierFitConfig, spec, "estimator: verifier")
    except (ConfigError, TypeError, ValueError) as err:
        raise RecipeError(str(err)) from err


def synth_config(spec: dict[str, Any]) -> SynthConfig:
    """A data entry's frames: its frame recipe's scenes and look, changed where `scene` and `randomization` say
    (a partial SceneConfig and RandomizationConfig: what they leave out stays the frame recipe's)."""
    scene, randomization = synth_recipe(spec.get("recipe", "plain"))
    if "scene" in spec:
        scene = config_from_dict(SceneConfig, spec["scene"], "scene", scene)
    if "randomization" in spec:
        randomization = config_from_dict(RandomizationConfig, spec["randomization"], "randomization", randomization)
    return SynthConfig(
        seed=int(spec["seed"]), scenes=int(spec["scenes"]), images_per_scene=int(spec.get("images_per_scene", 20)),
        objects=tuple(spec.get("objects", ())), scene=scene, randomization=randomization, depth=bool(spec.get("depth", False)),
    )  # fmt: skip
