"""`axispose train --recipe`'s runner: a recipe (`recipe.py`) built into OUT and assembled into one checkpoint.

The runner builds, in the recipe's order, the stages the checkpoint needs. A stage with OUT/NAME.done.json is done
and must have been built from the same config; one with a resume state goes on from it; others start. An existing
checkpoint may stand in for a stage (`adopt`); the record says so. The checkpoint's `training` record holds the
resolved recipe (configs, not file names), its hash and each stage's steps, time and hardware. A recipe with `adapt`
assembles into OUT/NAME.assembled.safetensors, adapts that on its recording in OUT/adapt (`axispose adapt`'s rounds,
resumed by the next call) and writes the adapted checkpoint as OUT/NAME.safetensors.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import shutil
import time
from pathlib import Path
from typing import Any

import torch

from axispose_core.adapt.recording import RecordingError, read_recording
from axispose_core.adapt.run import STATE, Adaptation, AdaptError, copy_whole
from axispose_core.agm.model import fresh_trunk
from axispose_core.checkpoint import ESTIMATOR, read_metadata
from axispose_core.data.meshes import refiner_meshes
from axispose_core.data.synth.generate import generate
from axispose_core.estimator import Estimator
from axispose_core.localiser.weights import load_localiser
from axispose_core.objects import dataset_objects
from axispose_core.tbm.reader import load_reader
from axispose_core.train.agm import train_agm
from axispose_core.train.localiser import train_localiser
from axispose_core.train.loop import DEFAULT_RUN, RunOptions
from axispose_core.train.reader import train_reader
from axispose_core.train.recipe import Recipe, RecipeError, Segment, Stage, refine_config, synth_config, verifier_spec
from axispose_core.train.resume import state_path
from axispose_core.train.sources import CropSources
from axispose_core.train.verifier import fit_verifier


def _training_record(meta: dict[str, str]) -> dict[str, Any]:
    """The `training` record a trainer wrote into its checkpoint, from the checkpoint's metadata (an estimator's config
    holds it, other kinds their extra metadata)."""
    if meta.get("kind") == ESTIMATOR:
        return dict(json.loads(meta.get("config", "{}")).get("training", {}))
    return dict(json.loads(meta.get("extra", "{}")).get("training", {}))


def _stage_record(record: dict[str, Any], name: str, own: bool) -> dict[str, Any]:
    """What an adopted file's `training` record says of how stage `name` was made: where a recipe assembled the
    file, the record of its stage of that name, followed through that stage's own adoptions to the run that trained
    it (a checkpoint re-assembled from itself would otherwise nest its whole record once more each time); otherwise
    the whole record where it is this stage's (`own`), else nothing: an estimator's record tells how its AGM was
    trained, not its localiser or reader."""
    while "recipe" in record and (stage := next((s for s in record.get("stages", ()) if s.get("name") == name), None)):
        if "training" not in stage:
            return {k: v for k, v in stage.items() if k not in ("name", "config_sha256")}
        record, own = stage["training"], True
    return record if own else {}


def _saved_step(state: Path) -> int:
    """The step a resume state was saved at (0: none yet), read without loading its tensors (memory-mapped)."""
    return int(torch.load(state, map_location="cpu", weights_only=False, mmap=True)["step"]) if state.is_file() else 0


class RecipeRunner:
    """Builds a recipe's stages into OUT and assembles its checkpoint (OUT/NAME.safetensors)."""

    def __init__(self, recipe: Recipe, out: str | Path, run: RunOptions = DEFAULT_RUN, adopt: dict[str, str] | None = None,
                 render_workers: int = 1, name: str = "estimator") -> None:  # fmt: skip
        self.recipe, self.out, self.run = recipe, Path(out), run
        self.adopt = {k: Path(v) for k, v in (adopt or {}).items()}
        if unknown := set(self.adopt) - {s.name for s in recipe.stages}:
            raise RecipeError(f"adopt: no stage named {', '.join(sorted(unknown))}")
        self.render_workers, self.name = render_workers, name
        self.deadline = None if run.max_minutes is None else time.time() + 60 * run.max_minutes

    def checkpoint(self, stage: str) -> Path:
        return self.out / f"{stage}.safetensors"

    def done_file(self, stage: str) -> Path:
        return self.out / f"{stage}.done.json"

    def built(self, stage: str) -> bool:
        """Done in OUT, or to be adopted: what it started from is not needed, unless that is adopted too."""
        return (self.done_file(stage).is_file() or stage in self.adopt) and not self._init_adopted(stage)

    def _init_adopted(self, stage: str) -> bool:
        """`stage` starts from a stage adopted too (in this call, or into OUT by an earlier one): then the chain goes
        on to it, so that the checkpoint records how the adopted weights were trained, stage by stage."""
        init = self.recipe.stage(stage).init
        if not init:
            return False
        done = self.done_file(init)
        return init in self.adopt or (done.is_file() and "adopted" in json.loads(done.read_text()))

    def run_all(self) -> Path | None:
        """Build what is missing and assemble; returns the checkpoint, or None when the time cap stopped a stage
        (the same call again goes on where it stopped)."""
        self.out.mkdir(parents=True, exist_ok=True)
        (self.out / "recipe.json").write_text(json.dumps(self.recipe.as_dict(), indent=1, default=list))
        for stage in self.recipe.needed(self.built):
            if not self.build(stage):
                return None
        return self.assemble() if self.recipe.adapt is None else self.adapt()

    def adapt(self) -> Path | None:
        """The assembled checkpoint adapted to the recipe's recording (module docstring); None when the time cap
        stopped the adaptation (the same call goes on). An adaptation under way keeps the checkpoint it started from."""
        source, folder = self.checkpoint(f"{self.name}.assembled"), self.out / "adapt"
        started = (folder / STATE).is_file()
        if not (started and source.is_file()):
            self.assemble(source)
        left = None if self.deadline is None else (self.deadline - time.time()) / 60
        if left is not None and left <= 0:
            return None
        try:
            recording = read_recording(self.recipe.adapt["recording"])
            adaptation = Adaptation(recording, source, self.recipe.models, folder, self.recipe.adapt_config(),
                                    dataclasses.replace(self.run, max_minutes=left), resume=started)  # fmt: skip
            final = adaptation.run(progress=self.run.progress)
        except (AdaptError, RecordingError) as err:
            raise RecipeError(f"adapt: {err}") from err
        if final is None:
            print(f"adapt: stopped at the time cap; the same command goes on from {folder}")
            return None
        path = self.checkpoint(self.name)
        copy_whole(final, path)
        return path

    def build(self, stage: Stage) -> bool:
        """Make sure `stage` is done; False when the time cap stopped it first."""
        done, ckpt = self.done_file(stage.name), self.checkpoint(stage.name)
        if done.is_file():
            if json.loads(done.read_text()).get("config_sha256") != stage.sha256:
                raise RecipeError(f"{ckpt} was built by another config of stage {stage.name}; "
                                  f"remove {self.out}/{stage.name}.* to build it again")  # fmt: skip
            return True
        if stage.name in self.adopt:
            source = self.adopt[stage.name]
            read_metadata(source, None)  # a readable checkpoint, or CheckpointError
            shutil.copyfile(source, ckpt)
            digest = hashlib.sha256(ckpt.read_bytes()).hexdigest()
            self._finish(stage, {"adopted": str(source), "file_sha256": digest})
            print(f"stage {stage.name}: adopted {source}")
            return True
        state = state_path(ckpt)
        for segment in stage.schedule:
            step = _saved_step(state)
            end = segment.until if segment.until is not None else segment.steps
            if step >= end:
                continue
            left = None if self.deadline is None else (self.deadline - time.time()) / 60
            if left is not None and left <= 0:
                return False
            print(f"stage {stage.name}: {stage.trainer} from step {step} to {end} (schedule {segment.steps} steps)")
            run = dataclasses.replace(self.run, resume=state if state.is_file() else None, stop_at=segment.until, max_minutes=left)
            init = self._init(stage) if stage.init and not state.is_file() else None
            if self._train(stage, segment, run, init) < end:
                print(f"stage {stage.name}: stopped at the time cap; the same command goes on from {state}")
                return False
        self._finish(stage, {})
        return True

    def _init(self, stage: Stage) -> Path:
        """The checkpoint `stage` starts from: its init stage's, or with `fresh_trunk` that AGM with its trunk anew
        (OUT/NAME.init.safetensors; seeded before the load, which draws too, so the same file gives the same start)."""
        if stage.fresh_trunk is None:
            return self.checkpoint(stage.init)
        torch.manual_seed(stage.fresh_trunk)
        est = Estimator.load(self.checkpoint(stage.init))
        reset = fresh_trunk(est.agm)
        path = self.out / f"{stage.name}.init.safetensors"
        est.save(path)
        print(f"stage {stage.name}: {stage.init}'s AGM with a new trunk (seed {stage.fresh_trunk}; {len(reset)} tensors anew)")
        return path

    def _finish(self, stage: Stage, extra: dict[str, Any]) -> None:
        """Mark the stage done with its record: the trainer's (steps, time, hardware), or under "training" what an
        adopted file's record says of this stage (`_stage_record`)."""
        meta = read_metadata(self.checkpoint(stage.name), None)
        record = _training_record(meta)
        if "adopted" in extra:
            own = stage.trainer == "agm" or meta.get("kind") != ESTIMATOR
            record = {"training": found} if (found := _stage_record(record, stage.name, own)) else {}
        else:
            record.pop("data", None)
        record = {"name": stage.name, "config_sha256": stage.sha256, **record, **extra}
        tmp = self.done_file(stage.name).with_suffix(".tmp")
        tmp.write_text(json.dumps(record, indent=1))
        tmp.replace(self.done_file(stage.name))

    def _data(self, names: tuple[str, ...]) -> list[Path]:
        """The named synthetic folders, rendered where missing (a rerun renders only the scenes a folder lacks)."""
        folders = []
        for name in names:
            folder = self.out / "data" / name
            spec = synth_config(self.recipe.data[name])
            generate(spec, self.recipe.models, folder, workers=self.render_workers, progress=self.run.progress)
            folders.append(folder)
        return folders

    def _train(self, stage: Stage, segment: Segment, run: RunOptions, init: Path | None) -> int:
        cfg = stage.segment_config(segment)
        if stage.trainer == "reader":
            return train_reader(cfg, self.checkpoint(stage.name), run)
        if stage.trainer == "agm":
            reader = self.checkpoint(self.recipe.estimator["reader"])
            return train_agm(cfg, CropSources((), (), self.recipe.models), self.checkpoint(stage.name), run, reader, init)
        data, val = self._data(segment.data or stage.data), self._data(stage.val)
        if not cfg.localiser.obj_ids:  # as `axispose train-localiser`: the objects the training data shows
            ids = tuple(o.obj_id for o in dataset_objects(data))
            cfg = dataclasses.replace(cfg, localiser=dataclasses.replace(cfg.localiser, obj_ids=ids))
        return train_localiser(cfg, data, self.checkpoint(stage.name), val or None, run, init)

    def assemble(self, path: Path | None = None) -> Path:
        """One estimator checkpoint from the estimator's stages, with the recipe and every stage's record, at `path`
        (default OUT/NAME.safetensors)."""
        est = self.recipe.estimator
        agm = Estimator.load(self.checkpoint(est["agm"]))
        reader = load_reader(self.checkpoint(est["reader"]))
        localiser = load_localiser(self.checkpoint(est["localiser"]))
        done = {s.name: json.loads(self.done_file(s.name).read_text()) for s in self.recipe.stages if self.done_file(s.name).is_file()}

        def chain_ends(name: str) -> bool:  # at an adopted stage, unless what it started from was adopted too
            return "adopted" in done[name] and not self._init_adopted(name)

        stages = [done[s.name] for s in self.recipe.needed(chain_ends)]  # the whole chain
        training = {"recipe": self.recipe.as_dict(), "recipe_sha256": self.recipe.sha256, "stages": stages}
        settings = dict(est["config"])
        refine = refine_config(settings.pop("refine")) if "refine" in settings else None
        config = dataclasses.replace(agm.config, reader=reader.config, localiser=localiser.config, verifier=None, refine=None,
                                     training=training, **settings)  # fmt: skip
        path = path or self.checkpoint(self.name)
        estimator = Estimator(config, agm.agm, reader, "cpu", localiser)
        if refine is not None:  # the objects' meshes from the recipe's models (BOP's decimated models_eval beside them)
            estimator = estimator.with_refiner(refiner_meshes(self.recipe.models, [o.obj_id for o in config.objects]), refine)
        estimator.save(path, half=bool(est["half"]))
        if "verifier" in est:  # fitted on the checkpoint as it runs: its stored weights, in float32
            names, fit_config = verifier_spec(dict(est["verifier"]), self.recipe.data)
            assembled = Estimator.load(path)
            verifier, record = fit_verifier(assembled, self._data(names), fit_config, progress=self.run.progress)
            assembled.with_verifier(verifier, record).save(path, half=bool(est["half"]))
        return path
