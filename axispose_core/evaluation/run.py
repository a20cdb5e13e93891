"""`evaluate`: pose metrics of an estimator on BOP scenes, the records `axispose eval` reports.

Protocol (BOP19 / LM-O): instances with visib_fract < 0.1 are skipped (visibility from scene_gt_info.json, or
estimated from the models where a scene has none: `BopScene`);
ADD-S replaces ADD for symmetric objects under the same keys, and their rotation and reprojection errors are
minimised over their symmetric poses (`metrics.pose_scores`); a pose the estimator cannot give counts as wrong
at every threshold. With `--crops gt` the crop is the square around the GT box (the paper's protocol).

Stress: `visib` narrows the instances to a visibility band (heavy occlusion: 0.1-0.5) and `perturb` degrades
each frame before detection and estimation (low light, motion blur; see stress.py), seeded per frame.
"""

from __future__ import annotations

import time
import zlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from tqdm import tqdm

from axispose_core.bop19 import BopImage, BopObject, ImageErrors, image_errors
from axispose_core.data.bop import GTInfo, GTInstance
from axispose_core.data.bop_models import load_models_info, model_path
from axispose_core.data.bop_results import BopEstimate
from axispose_core.data.bop_scene import BopScene, bop_frames
from axispose_core.data.meshes import load_ply
from axispose_core.data.visibility import gt_info_from_models
from axispose_core.evaluation.records import ObjectBox, Prediction, Predictor, Record, instance_scores, object_symmetries
from axispose_core.localiser.decode import Detection, match
from axispose_core.localiser.scoring import false_alarms
from axispose_core.objects import ObjectSpec

if TYPE_CHECKING:  # evaluate scores any predictor; `estimator_runs` adapts the estimator's
    from axispose_core.estimator import EstimateOptions, Estimator
    from axispose_core.pose_estimate import PoseEstimate

MIN_VISIB = 0.1
"""The least visible fraction of an instance that counts (BOP19's)."""


Finder = Callable[[np.ndarray, np.ndarray, BopScene, int], tuple[list[Detection], list[Prediction]]]
"""(rgb image, K, its scene, its image id) -> the objects the localiser finds, each with its pose (`Estimator.find`).
The scene and id let a finder that follows a stream (`node_path.NodePath`) take each scene's frames in order."""


def predictions(poses: list[PoseEstimate]) -> list[Prediction]:
    """The estimator's poses as `evaluate` scores them."""
    return [Prediction(p.R, p.t, p.ok, p.spread_deg, p.covariance, p.unrefined, p.refine_kept) for p in poses]


def estimator_runs(est: Estimator, options: EstimateOptions, threshold: float | None = None) -> tuple[Predictor, Finder]:
    """The estimator's poses of given boxes and what it finds itself (at `threshold`, None: its own), as `evaluate`
    takes them."""

    def predict(image: np.ndarray, K: np.ndarray, boxes: list[ObjectBox]) -> list[Prediction]:
        return predictions(est.estimate(image, K, boxes, options))

    def find(image: np.ndarray, K: np.ndarray, scene: BopScene, im_id: int) -> tuple[list[Detection], list[Prediction]]:
        found = est.find(image, K, threshold, options)
        return found.detections, predictions(found.poses)

    return predict, find


Perturbation = Callable[[np.ndarray, np.random.Generator], np.ndarray]
"""(rgb image, seeded generator) -> the degraded image (stress.py)."""
Targets = dict[tuple[int, int], dict[int, int]]
"""(scene id, image id) -> {obj_id: inst_count}: test_targets_bop19.json (`bop.load_test_targets`)."""


@dataclass(frozen=True)
class EvalOptions:
    """How `evaluate` runs, as against what it scores.

    Instances count when their visib_fract lies in `visib` (lower bound at least MIN_VISIB); `perturb`, seeded by
    scene and frame, degrades each RGB frame first. The boxes are the GT boxes, posed by the predictor, or with
    `detector` (a `Finder`) the objects it finds with their poses, matched to the GT instances (same object,
    IoU >= 0.5, greedy by score); an instance no detection matches counts as a pose failure. `targets` limits the
    instances to BOP's: only the images it names, and per image and object the `inst_count` most visible instances
    (within `visib`). `bop` also computes each image's BOP19 errors (`Evaluation.bop`). `limit` stops after that
    many instances (at a frame's end)."""

    limit: int | None = None
    progress: bool = True
    detector: Finder | None = None
    visib: tuple[float, float] = (MIN_VISIB, 1.0)
    perturb: Perturbation | None = None
    targets: Targets | None = None
    bop: bool = False

    def __post_init__(self) -> None:
        if not MIN_VISIB <= self.visib[0] <= self.visib[1]:
            raise ValueError(f"visib must be a band ({MIN_VISIB} <= low <= high), got {self.visib}")


@dataclass
class Evaluation:
    """What `evaluate` gives: a Record per counted instance, and what the data needed (`notes`: scenes whose
    visibility was estimated from the models, having no scene_gt_info.json, and GT rotations projected to the
    nearest rotation, `bop.read_scene_gt`). With a detector, `detection_counts` per object: true positives, false
    positives and instances. With `EvalOptions.bop`, `bop`: each image's BOP19 errors (`bop19.image_errors`): every
    estimate with its score (1 for a GT crop, the localiser's otherwise; with the localiser, every detection of a
    known object is posed) against the image's instances, VSD where the scene has depth images."""

    records: list[Record]
    notes: dict[str, Any]
    detection_counts: dict[int, dict[str, int]] | None = None
    bop: list[ImageErrors] | None = None


@dataclass(frozen=True)
class _Frame:
    """One frame to pose: its scene and ids, every GT instance (`pairs`) and those that count (`insts`)."""

    scene: BopScene
    im_id: int
    scene_id: int
    pairs: list[tuple[GTInstance, GTInfo]]
    insts: list[tuple[GTInstance, GTInfo]]


class _Evaluator:
    """`evaluate`'s frame-by-frame work: the predictor, the objects' models and what has been gathered so far."""

    def __init__(self, predict: Predictor, models_dir: str | Path, objects: list[ObjectSpec], options: EvalOptions) -> None:
        self.predict, self.options = predict, options
        self.specs = {o.obj_id: o for o in objects}
        self.bop_objects: dict[int, BopObject] = {}
        if options.bop:
            infos = load_models_info(Path(models_dir) / "models_info.json")
            self.bop_objects = {i: BopObject.load(models_dir, infos[i]) for i in self.specs}
            self.points = {i: o.points for i, o in self.bop_objects.items()}
        else:
            self.points = {i: load_ply(model_path(models_dir, i)).vertices for i in self.specs}
        self.syms = object_symmetries(objects, self.points)
        self.records: list[Record] = []
        self.counts: dict[int, dict[str, int]] | None = {} if options.detector is not None else None
        self.bop: list[ImageErrors] | None = [] if options.bop else None

    def frame(self, scene: BopScene, im_id: int, scene_id: int) -> _Frame | None:
        """The frame with the instances that count (object evaluated, visibility in the band, a BOP target where
        targets are given), or None without any."""
        targets, (low, high) = self.options.targets, self.options.visib
        if targets is not None and (scene_id, im_id) not in targets:
            return None
        pairs = scene.instances(im_id)
        wanted = _target_instances(pairs, targets[scene_id, im_id]) if targets is not None else range(len(pairs))
        insts = [pairs[k] for k in wanted if pairs[k][0].obj_id in self.specs and low <= pairs[k][1].visib_fract <= high]
        return _Frame(scene, im_id, scene_id, pairs, insts) if insts else None

    def pose(self, frame: _Frame) -> None:
        """Pose the frame's boxes in one batch, timed with the detection, and score every instance that counts."""
        scene, im_id, insts = frame.scene, frame.im_id, frame.insts
        K = scene.cameras[im_id]
        rgb = scene.rgb(im_id)
        if self.options.perturb is not None:
            rgb = self.options.perturb(rgb, np.random.default_rng([zlib.crc32(scene.root.name.encode()), im_id]))
        start = time.perf_counter()
        if self.options.detector is not None:
            boxes, box_scores, posed, found = self._detect(frame, rgb, K)
        else:
            boxes, box_scores, found = [(g.obj_id, info.bbox_obj) for g, info in insts], [1.0] * len(insts), None
            posed = self.predict(rgb, K, boxes) if boxes else []
        frame_seconds = time.perf_counter() - start
        missed = Prediction(np.eye(3), np.zeros(3), False)
        if found is None:
            preds = posed
        else:
            preds = [posed[found[id(g)]] if found[id(g)] is not None else missed for g, _ in insts]
        if self.bop is not None:
            made = [BopEstimate(frame.scene_id, im_id, obj_id, score, p.R, p.t, frame_seconds)
                    for (obj_id, _), score, p in zip(boxes, box_scores, posed, strict=True) if p.ok]  # fmt: skip
            image = BopImage(frame.scene_id, im_id, K, rgb.shape[1], rgb.shape[0], scene.depth(im_id))
            self.bop.append(image_errors(image, made, [(g.obj_id, g.R, g.t) for g, _ in insts], self.bop_objects))
        self._score(frame, K, preds, frame_seconds / len(insts))

    def _detect(
        self, frame: _Frame, rgb: np.ndarray, K: np.ndarray
    ) -> tuple[list[ObjectBox], list[float], list[Prediction], dict[int, int | None]]:
        """The objects found of those evaluated as boxes with their scores and poses, which detection (if any) each
        GT instance got (by id of its GTInstance), and the detection counts of the instances that count."""
        found_dets, found_poses = self.options.detector(rgb, K, frame.scene, frame.im_id)
        pairs = [(d, p) for d, p in zip(found_dets, found_poses, strict=True) if d.obj_id in self.specs]
        dets, posed = [d for d, _ in pairs], [p for _, p in pairs]
        everyone = [(g.obj_id, info.bbox_obj) for g, info in frame.pairs]
        hits = match(dets, everyone)  # detections of barely visible instances are neither hits nor false alarms
        found = dict(zip(map(id, frame.scene.gt[frame.im_id]), hits, strict=True))
        if self.counts is not None:
            for g, _ in frame.insts:
                c = self.counts.setdefault(g.obj_id, {"tp": 0, "fp": 0, "n": 0})
                c["n"] += 1
                c["tp"] += found[id(g)] is not None
            for d in (dets[k] for k in false_alarms(hits, len(dets))):
                self.counts.setdefault(d.obj_id, {"tp": 0, "fp": 0, "n": 0})["fp"] += 1
        return [(d.obj_id, d.box) for d in dets], [d.score for d in dets], posed, found

    def _score(self, frame: _Frame, K: np.ndarray, preds: list[Prediction], seconds: float) -> None:
        """A Record per instance that counts, with its prediction and its share of the frame's time."""
        for (g, info), p in zip(frame.insts, preds, strict=True):
            pose = (p.R, p.t) if p.ok else None
            args = (self.specs[g.obj_id], self.points[g.obj_id], K, g.R, g.t)
            scores = instance_scores(*args, pose, self.syms.get(g.obj_id, ()))
            unrefined = None if p.unrefined is None else instance_scores(*args, p.unrefined, self.syms.get(g.obj_id, ()))
            self.records.append(
                Record(g.obj_id, frame.scene.root.name, frame.im_id, scores, seconds, g.R, g.t, p.R, p.t, p.ok, K,
                       frame.scene.rgb_path(frame.im_id), info.bbox_obj, p.spread_deg, info.visib_fract, p.covariance, p.unrefined,
                       unrefined, p.refine_kept)
            )  # fmt: skip


def evaluate(
    predict: Predictor, data: str | Path, models_dir: str | Path, objects: list[ObjectSpec], options: EvalOptions = EvalOptions()
) -> Evaluation:
    """Run `predict` on every frame's boxes of the BOP scenes in `data` (one batch per frame) and score each
    instance of `objects` that counts, as `options` say (GT or detected boxes, visibility band, BOP targets)."""
    ev = _Evaluator(predict, models_dir, objects, options)
    frames = bop_frames([data], gt_info_from_models(models_dir))
    scenes = list({scene.root: scene for scene, _ in frames}.values())
    notes = {
        "visibility_estimated_scenes": sorted(s.root.name for s in scenes if s.visibility_estimated),
        "gt_rotations_projected": sum(s.rotations_projected for s in scenes),
    }
    scene_ids = {scene.root: _scene_id(scene, k) for k, scene in enumerate(scenes)}
    for scene, im_id in tqdm(frames, desc="eval", disable=not options.progress):
        frame = ev.frame(scene, im_id, scene_ids[scene.root])
        if frame is None:
            continue
        if options.limit is not None and len(ev.records) >= options.limit:
            break
        ev.pose(frame)
    return Evaluation(ev.records, notes, ev.counts, ev.bop)


def _scene_id(scene: BopScene, index: int) -> int:
    """A scene's BOP id: its folder's number, else its place among the evaluated scenes."""
    return int(scene.root.name) if scene.root.name.isdigit() else index


def _target_instances(pairs: list[tuple[GTInstance, GTInfo]], counts: dict[int, int]) -> list[int]:
    """Indices of the instances a BOP target asks for: per object, its `inst_count` most visible (file order on
    ties), in file order."""
    by_visibility = sorted(range(len(pairs)), key=lambda k: -pairs[k][1].visib_fract)
    left, keep = dict(counts), []
    for k in by_visibility:
        obj_id = pairs[k][0].obj_id
        if left.get(obj_id, 0) > 0:
            left[obj_id] -= 1
            keep.append(k)
    return sorted(keep)
