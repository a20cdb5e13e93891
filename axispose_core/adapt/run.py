"""`axispose adapt`: a checkpoint adapted to the user's scene from their own unlabeled recording, in rounds.

Each round poses every frame with the round's estimator (`pseudo`), makes the poses consistent across the
recording (`scene`), turns the scene's predictions into labels on the frames' pixels (`labels`), fine-tunes the
AGM on those crops mixed with the crop stream (`train`), then the localiser on those frames' boxes mixed with
rendered frames (`localiser`); the next round poses with the adapted estimator. Rounds
stop when the labels stop growing. Everything a round makes lives in OUT/round<k>/; OUT/adapt.json says what is
done, so a stopped or killed run goes on where it stopped (`resume`), and a checkpoint is only ever written whole.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from axispose_core.adapt.geometry import IDENTITY, ObjectGeometry
from axispose_core.adapt.labels import FillConfig, Label, label_frame, write_labels
from axispose_core.adapt.localiser import AdaptLocaliserConfig, adapt_localiser, render_frames
from axispose_core.adapt.pseudo import AcceptConfig, Candidate, PoseSettings, pose_frames
from axispose_core.adapt.recording import Recording
from axispose_core.adapt.report import contact_sheet, round_counts
from axispose_core.adapt.scene import ConsistencyConfig, SceneResult, consistent
from axispose_core.adapt.search import Discovery, Scene, SearchConfig, read_discoveries, search, with_discoveries, write_discoveries
from axispose_core.adapt.train import AdaptTrainConfig, adapt_agm
from axispose_core.estimator import Estimator
from axispose_core.evaluation.records import object_symmetries
from axispose_core.train.loop import DEFAULT_RUN, RunOptions
from axispose_core.train.resume import state_path

STATE = "adapt.json"
REPORT = "report.json"
SEARCH = "search.json"
"""A round's search for the objects no frame accepted (`search.Discovery` each): done once, read on resume."""
ADAPTED = "adapted.safetensors"
AGM = "agm.safetensors"
"""A round's checkpoint with its AGM adapted (its localiser as it was): what the localiser's stage starts from."""
FRAMES = "frames"
"""OUT's folder of the rendered frames the localiser's stage mixes in."""


class AdaptError(ValueError):
    """An adaptation that cannot start or go on: the one-line reason."""


@dataclass(frozen=True)
class AdaptConfig:
    """The whole adaptation: how frames are posed and accepted, when poses agree across the recording, how the
    scene is searched for the objects no frame accepted, how the scene's predictions become labels, how the AGM
    trains on them, and how many rounds at most (a round after the first only while the labels grew by
    `min_growth` over the round before)."""

    rounds: int = 1
    min_growth: float = 0.05
    pose: PoseSettings = field(default_factory=PoseSettings)
    accept: AcceptConfig = field(default_factory=AcceptConfig)
    consistency: ConsistencyConfig = field(default_factory=ConsistencyConfig)
    search: SearchConfig = field(default_factory=SearchConfig)
    fill: FillConfig = field(default_factory=FillConfig)
    train: AdaptTrainConfig = field(default_factory=AdaptTrainConfig)
    localiser: AdaptLocaliserConfig = field(default_factory=AdaptLocaliserConfig)

    def __post_init__(self) -> None:
        if self.rounds < 1:
            raise ValueError(f"rounds must be >= 1, got {self.rounds}")


def object_geometry(est: Estimator) -> dict[int, ObjectGeometry]:
    """Each object's diameter and symmetries (from the refiner's meshes the checkpoint carries)."""
    if est.meshes is None:
        raise AdaptError("the checkpoint carries no object meshes (no contour refiner): adaptation refines its labels on them")
    symmetries = object_symmetries(est.config.objects, {i: np.asarray(v) for i, (v, _) in est.meshes.items()})
    return {o.obj_id: ObjectGeometry(o.diameter, tuple(symmetries.get(o.obj_id, IDENTITY))) for o in est.config.objects}


class Adaptation:
    """One adaptation run into `out`: `run()` does what is left of it."""

    def __init__(self, recording: Recording, checkpoint: str | Path, models: str | Path, out: str | Path, cfg: AdaptConfig,
                 run: RunOptions = DEFAULT_RUN, resume: bool = False) -> None:  # fmt: skip
        self.recording, self.checkpoint, self.models = recording, Path(checkpoint), Path(models)
        self.frames = {f.im_id: f for f in recording.frames}
        """The recording's frames by id."""
        self.out, self.cfg, self.run_options = Path(out), cfg, run
        self.deadline = None if run.max_minutes is None else time.time() + 60 * run.max_minutes
        object_geometry(Estimator.load(self.checkpoint))  # a checkpoint that cannot be adapted says so now, not rounds later
        if not recording.frames:
            raise AdaptError(f"{recording.root}: no frames to adapt on")
        self.state = self._open(resume)

    def _open(self, resume: bool) -> dict:
        """The run's state: new (OUT must not hold another run), or the one OUT holds, made by the same call but
        for the number of rounds: a finished run resumed with more rounds goes on from its last one."""
        path = self.out / STATE
        made = {"checkpoint": str(self.checkpoint.resolve()), "recording": str(self.recording.root.resolve()),
                "frames": [f.im_id for f in self.recording.frames], "models": str(self.models.resolve()),
                "config": json.loads(json.dumps(asdict(self.cfg), default=list))}  # fmt: skip
        if path.is_file():
            if not resume:
                raise AdaptError(f"{self.out} holds an adaptation already: --resume to go on with it, or another --out")
            state = json.loads(path.read_text())
            state["config"]["rounds"] = self.cfg.rounds
            different = [k for k in made if state.get(k) != made[k]]
            if different:
                raise AdaptError(f"{self.out} was adapted with another {', '.join(different)}: give the same, or another --out")
            self._save(state)
            return state
        if resume:
            raise AdaptError(f"{path}: nothing to resume")
        if self.out.exists() and any(self.out.iterdir()):
            raise AdaptError(f"{self.out} exists and is not an adaptation: give a new or empty --out")
        self.out.mkdir(parents=True, exist_ok=True)
        state = made | {"rounds": []}
        self._save(state)
        return state

    def _save(self, state: dict | None = None) -> None:
        """adapt.json, and the report (OUT/report.json: per round what it labelled, whether it trained)."""
        state = state or self.state
        for name, data in ((STATE, state), (REPORT, {k: state[k] for k in ("checkpoint", "recording", "models", "rounds")})):
            path = self.out / name
            tmp = path.with_suffix(".tmp")
            tmp.write_text(json.dumps(data, indent=1))
            tmp.replace(path)

    def round_dir(self, k: int) -> Path:
        return self.out / f"round{k}"

    def estimator_of(self, k: int) -> Path:
        """The checkpoint round k poses with: the given one, then each round's adapted one."""
        return self.checkpoint if k == 0 else self.round_dir(k - 1) / ADAPTED

    def run(self, progress: bool = True) -> Path | None:
        """Every round still to do; the adapted checkpoint (OUT/adapted.safetensors), or None where the time cap
        stopped it (the same call with resume goes on)."""
        for k in range(self.cfg.rounds):
            rounds = self.state["rounds"]
            if k < len(rounds) and rounds[k].get("stopped"):
                break
            if k == len(rounds):
                rounds.append({})
            entry = rounds[k]
            if "labels" not in entry:
                entry.update(self._label(k, progress))
                self._save()
            if k == 0 and entry["labels"] == 0:
                raise AdaptError(f"no labels: the estimator accepted no pose on any of the {len(self.recording.frames)} frames "
                                 f"(round0/round.json counts what it found)")  # fmt: skip
            if k > 0 and entry["labels"] < (1 + self.cfg.min_growth) * rounds[k - 1]["labels"]:
                entry["stopped"] = f"labels {entry['labels']} against {rounds[k - 1]['labels']}: not grown by {self.cfg.min_growth:.0%}"
                self._save()
                break
            if not entry.get("trained"):
                if not self._train(k, progress):
                    return None
                entry["trained"] = True
                self._save()
        last = max(k for k, r in enumerate(self.state["rounds"]) if r.get("trained"))
        final = self.out / ADAPTED
        copy_whole(self.round_dir(last) / ADAPTED, final)
        return final

    def _label(self, k: int, progress: bool) -> dict:
        """Round k's pose, scene and label stages; its counts (what adapt.json and the report keep)."""
        folder = self.round_dir(k)
        folder.mkdir(parents=True, exist_ok=True)
        est = Estimator.load(self.estimator_of(k))
        est.set_precision("float32")
        geometry = object_geometry(est)
        bar = tqdm(total=len(self.recording.frames), desc=f"round {k}: posing", disable=not progress)
        candidates = pose_frames(est, self.recording.frames, self.cfg.pose, folder / "candidates.jsonl", _bar(bar))
        bar.close()
        in_view = self._in_view()
        scene = self._scene(candidates, geometry, in_view)
        discoveries = self._search(k, est, scene, geometry, progress)
        scene = with_discoveries(scene, discoveries, in_view)
        labels, unfilled = self._labels(est, scene, geometry, progress)
        write_labels(_fresh(folder / "labels"), self.recording.frames, labels, self.models)
        counts = round_counts(candidates, self.cfg.accept, scene, labels, unfilled, est.config.objects, discoveries)
        sheet = contact_sheet(folder / "contact_sheet.png", self.frames, labels, est.config.objects)
        (folder / "round.json").write_text(json.dumps(counts, indent=1))
        print(f"round {k}: {counts['total']['labels']} labels ({counts['total']['checked']} checked, {counts['total']['filled']} filled, "
              f"{counts['total']['alone']} alone), {counts['total']['rejected']} rejected; {counts['cameras_placed']} of "
              f"{counts['frames']} cameras placed; contact sheet {sheet}")  # fmt: skip
        return {"labels": counts["total"]["labels"], "counts": counts}

    def _in_view(self) -> Callable[[int, int, np.ndarray, np.ndarray], bool]:
        """Whether a frame shows a pose's origin (in front of its camera, inside its image)."""
        sizes = {f.im_id: f.rgb().shape[:2] for f in self.recording.frames}

        def in_view(im_id: int, obj_id: int, R: np.ndarray, t: np.ndarray) -> bool:
            u, v, w = self.frames[im_id].K @ t
            h, wd = sizes[im_id]
            return w > 0 and 0 <= u / w < wd and 0 <= v / w < h

        return in_view

    def _scene(self, candidates: dict[int, list[Candidate]], geometry: dict[int, ObjectGeometry],
               in_view: Callable[[int, int, np.ndarray, np.ndarray], bool]) -> SceneResult:  # fmt: skip
        odometry = {f.im_id: f.camera for f in self.recording.frames} if self.recording.has_odometry else None
        return consistent(candidates, geometry, self.cfg.accept, self.cfg.consistency, odometry, in_view)

    def _search(self, k: int, est: Estimator, scene: SceneResult, geometry: dict[int, ObjectGeometry], progress: bool) -> list[Discovery]:
        """Round k's search for the objects no frame accepted: made once (OUT/round<k>/search.json), then read."""
        path = self.round_dir(k) / SEARCH
        found = read_discoveries(path)
        if found is None:
            bar = tqdm(total=0, desc=f"round {k}: searching", disable=not progress)
            found = search(Scene(est, self.frames, scene, geometry, self.cfg.consistency, self.cfg.fill), self.cfg.search, _bar(bar))
            bar.close()
            write_discoveries(path, found)
        return found

    def _labels(self, est: Estimator, scene: SceneResult, geometry: dict[int, ObjectGeometry], progress: bool) -> tuple[list[Label], dict]:
        labels, unfilled = [], {}
        alone: dict[int, list[Candidate]] = {}
        for c in scene.alone:
            alone.setdefault(c.im_id, []).append(c)
        for frame in tqdm(self.recording.frames, desc="labelling", disable=not progress):
            preds = scene.predictions.get(frame.im_id, [])
            mine = label_frame(est.refiner, frame.rgb(), frame.K, preds, alone.get(frame.im_id, []), geometry,
                               self.cfg.consistency, self.cfg.fill)  # fmt: skip
            labels += mine
            filled = {lab.obj_id for lab in mine if lab.source == "filled"}
            for p in preds:
                if p.own is None and p.obj_id not in filled:
                    unfilled[p.obj_id] = unfilled.get(p.obj_id, 0) + 1
        return labels, unfilled

    def _train(self, k: int, progress: bool) -> bool:
        """Round k's fine-tunes, the AGM's then the localiser's (where the checkpoint has one and `localiser`
        trains); False where the time cap stopped them first."""
        entry, folder = self.state["rounds"][k], self.round_dir(k)
        labels = folder / "labels"
        if not entry.get("agm"):
            if not self._fit(lambda run: adapt_agm(self.estimator_of(k), labels, self.models, folder / AGM, self.cfg.train, run),
                             folder / AGM, self.cfg.train.optim.steps):  # fmt: skip
                return False
            entry["agm"] = True
            self._save()
        est = Estimator.load(folder / AGM)
        if not (self.cfg.localiser.trains and est.localiser is not None):
            copy_whole(folder / AGM, folder / ADAPTED)
            return True
        frame = self.recording.frames[0]
        h, w = frame.rgb().shape[:2]
        objects = tuple(o.obj_id for o in est.config.objects)
        frames = render_frames(self.cfg.localiser.frames, self.models, objects, frame.K, (w, h), self.out / FRAMES, progress)
        return self._fit(lambda run: adapt_localiser(folder / AGM, labels, frames, self.models, folder / ADAPTED, self.cfg.localiser, run),
                         folder / ADAPTED, self.cfg.localiser.optim.steps)  # fmt: skip

    def _fit(self, train: Callable[[RunOptions], int], out: Path, steps: int) -> bool:
        """One fine-tune into `out`, resumed from its state where an earlier call left one, within the time cap;
        whether it reached its `steps`."""
        state = state_path(out)
        left = None if self.deadline is None else (self.deadline - time.time()) / 60
        if left is not None and left <= 0:
            return False
        return train(dataclasses.replace(self.run_options, resume=state if state.is_file() else None, max_minutes=left)) >= steps


def copy_whole(src: Path, dst: Path) -> None:
    """`src` copied to `dst` whole or not at all (a checkpoint is never half-written)."""
    tmp = dst.with_suffix(".tmp")
    shutil.copyfile(src, tmp)
    tmp.replace(dst)


def _fresh(path: Path) -> Path:
    """`path` emptied: a label folder a killed run left half-written is written anew."""
    if path.exists():
        shutil.rmtree(path)
    return path


def _bar(bar: tqdm) -> Callable[[int, int], None]:
    def update(done: int, total: int) -> None:
        bar.n = done
        bar.refresh()

    return update
