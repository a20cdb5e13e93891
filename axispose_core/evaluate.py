"""`axispose eval`: pose metrics of an estimator on BOP scenes, as JSON, with error CDFs and a crop grid.

Protocol (BOP19 / LM-O): instances with visib_fract < 0.1 are skipped (visibility from scene_gt_info.json, or
estimated from the models where a scene has none: `BopScene`);
ADD-S replaces ADD for symmetric objects under the same keys, and their rotation and reprojection errors are
minimised over their symmetric poses (`metrics.pose_scores`); a pose the estimator cannot give counts as wrong
at every threshold. With `--crops gt` the crop is the square around the GT box (the paper's protocol).

Stress: `visib` narrows the instances to a visibility band (heavy occlusion: 0.1-0.5) and `perturb` degrades
each frame before detection and estimation (low light, motion blur; see stress.py), seeded per frame.
"""

from __future__ import annotations

import dataclasses
import json
import time
import zlib
from collections import Counter
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np
from tqdm import tqdm

from axispose_core.axis_image import draw_axes
from axispose_core.bop19 import BopImage, BopObject, ImageErrors, average_recall, image_errors
from axispose_core.camera import crop_image, crop_intrinsics, square_around_box
from axispose_core.data.bop import BopEstimate, BopScene, GTInfo, GTInstance, bop_frames, load_models_info, model_path, read_bgr
from axispose_core.data.meshes import load_ply
from axispose_core.data.visibility import gt_info_from_models
from axispose_core.localiser.decode import Detection, match
from axispose_core.localiser.scoring import false_alarms
from axispose_core.metrics import ADD_THRESHOLDS, REPROJ_THRESHOLDS, Symmetry, half_turn_symmetries, mahalanobis_sq, pose_scores
from axispose_core.objects import ObjectSpec

if TYPE_CHECKING:  # evaluate scores any predictor; `estimator_runs` adapts the estimator's
    from axispose_core.estimator import EstimateOptions, Estimator

MIN_VISIB = 0.1
SUMMARY_KEYS = [f"add_{f:g}d" for f in ADD_THRESHOLDS] + [f"reproj_{p:g}px" for p in REPROJ_THRESHOLDS]


@dataclass
class Prediction:
    R: np.ndarray
    t: np.ndarray
    ok: bool
    spread_deg: float = float("nan")
    """Rotation spread of the estimator's samples (multi-hypothesis), NaN for a single sample."""
    covariance: np.ndarray | None = None
    """(6, 6) pose covariance the estimator reports (x, y, z, rotation about X, Y, Z; camera frame), if any."""
    unrefined: tuple[np.ndarray, np.ndarray] | None = None
    """The pose before contour refinement, where the refiner saw this one."""
    refine_kept: str = ""
    """Why the refiner kept the unrefined pose, if it did."""


ObjectBox = tuple[int, tuple[float, float, float, float]]
"""(obj_id, box): an instance's object and its box (x, y, w, h) in image pixels, as BOP's bbox_obj."""
Predictor = Callable[[np.ndarray, np.ndarray, list[ObjectBox]], list[Prediction]]
"""(rgb image, K, [(obj_id, box)]) -> one Prediction per box."""


@dataclass
class Record:
    obj_id: int
    scene: str
    im_id: int
    scores: dict[str, float]
    seconds: float
    R_gt: np.ndarray
    t_gt: np.ndarray
    R: np.ndarray
    t: np.ndarray
    ok: bool
    K: np.ndarray
    rgb_path: Path | None
    box: tuple[int, int, int, int]
    spread_deg: float = float("nan")
    visib_fract: float = float("nan")
    covariance: np.ndarray | None = None
    unrefined: tuple[np.ndarray, np.ndarray] | None = None
    """The pose before contour refinement, where the refiner saw it, and its scores."""
    unrefined_scores: dict[str, float] | None = None
    refine_kept: str = ""

    @property
    def sigma_deg(self) -> float:
        """The covariance's rotation standard deviation (`rotation_sigma_deg`)."""
        return rotation_sigma_deg(self.covariance)


def instance_scores(
    spec: ObjectSpec,
    points: np.ndarray,
    K: np.ndarray,
    R_gt: np.ndarray,
    t_gt: np.ndarray,
    pose: tuple[np.ndarray, np.ndarray] | None,
    syms: Sequence[Symmetry] = (),
) -> dict[str, float]:
    """One GT instance's scores in every report: `pose_scores` of its estimate (R, t), or a failure's without one;
    `syms`, a symmetric object's equivalent poses (`object_symmetries`)."""
    if pose is None:
        return {k: 0.0 for k in SUMMARY_KEYS} | {"rot_err_deg": 180.0, "trans_err_mm": float("inf")}
    return pose_scores(*pose, R_gt, t_gt, K, points, spec.diameter, syms if spec.symmetric else None)


def object_symmetries(objects: Iterable[ObjectSpec], points: Mapping[int, np.ndarray]) -> dict[int, list[Symmetry]]:
    """Each symmetric object's equivalent poses (`metrics.half_turn_symmetries` of its points), by object id."""
    return {o.obj_id: half_turn_symmetries(points[o.obj_id], o.diameter) for o in objects if o.symmetric and o.obj_id in points}


Finder = Callable[[np.ndarray, np.ndarray], tuple[list[Detection], list[Prediction]]]
"""(rgb image, K) -> the objects the localiser finds, each with its pose (`Estimator.find`)."""


def estimator_runs(est: Estimator, options: EstimateOptions, threshold: float | None = None) -> tuple[Predictor, Finder]:
    """The estimator's poses of given boxes and what it finds itself (at `threshold`, None: its own), as `evaluate`
    takes them."""

    def predictions(poses: list) -> list[Prediction]:
        return [Prediction(p.R, p.t, p.ok, p.spread_deg, p.covariance, p.unrefined, p.refine_kept) for p in poses]

    def predict(image: np.ndarray, K: np.ndarray, boxes: list[ObjectBox]) -> list[Prediction]:
        return predictions(est.estimate(image, K, boxes, options))

    def find(image: np.ndarray, K: np.ndarray) -> tuple[list[Detection], list[Prediction]]:
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
        found_dets, found_poses = self.options.detector(rgb, K)
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


def summarize(
    records: list[Record],
    objects: list[ObjectSpec],
    config: dict,
    detection_counts: dict[int, dict[str, int]] | None = None,
    bop: list[ImageErrors] | None = None,
) -> dict:
    """The report JSON: per object, mean over objects, latency, config; detection precision/recall when given;
    BOP19 average recall (`bop19`: overall and per object) from `bop`'s image errors."""
    per: dict[str, dict[str, float]] = {}
    for o in objects:
        rs = [r for r in records if r.obj_id == o.obj_id]
        if not rs:
            continue
        entry = {"n": len(rs), "name": o.name}
        for k in SUMMARY_KEYS:
            entry[k] = float(np.mean([r.scores[k] for r in rs]))
        entry["rot_err_median_deg"] = float(np.median([r.scores["rot_err_deg"] for r in rs]))
        entry["trans_err_median_mm"] = float(np.median([r.scores["trans_err_mm"] for r in rs]))
        entry |= depth_errors(rs)
        if (refine := refinement_summary(rs)) is not None:
            entry["refine"] = refine
        if detection_counts is not None:
            c = detection_counts.get(o.obj_id, {"tp": 0, "fp": 0, "n": 0})
            entry["det_recall"] = c["tp"] / c["n"] if c["n"] else float("nan")
            entry["det_precision"] = c["tp"] / (c["tp"] + c["fp"]) if c["tp"] + c["fp"] else float("nan")
        per[str(o.obj_id)] = entry
    keys = [*SUMMARY_KEYS, "rot_err_median_deg", "trans_err_median_mm", *DEPTH_KEYS] + (
        ["det_recall", "det_precision"] if detection_counts is not None else []
    )
    mean = {k: _mean_of_defined([e[k] for e in per.values()]) for k in keys} if per else {}
    refined = [e["refine"] for e in per.values() if "refine" in e]
    if refined:  # an object the refiner never saw counts as it is
        before = [e["refine"]["unrefined"] if "refine" in e else e for e in per.values()]
        mean["refine"] = {"unrefined": {k: _mean_of_defined([b[k] for b in before]) for k in refined[0]["unrefined"]},
                          "refined": sum(r["refined"] for r in refined),
                          "kept": dict(sum((Counter(r["kept"]) for r in refined), Counter()))}  # fmt: skip
    ms = np.array([1000 * r.seconds for r in records]) if records else np.zeros(1)
    report = {
        "objects": per,
        "mean": mean,
        "instances": pooled(records) | ({"unrefined": pooled(unrefined_records(records))} if refined else {}),
        "ms_per_object": {"median": float(np.median(ms)), "p90": float(np.percentile(ms, 90))},
        "config": config,
    }
    if bop is not None:
        ar = average_recall(bop)
        names = {o.obj_id: o.name for o in objects}
        ar["objects"] = {str(i): {"name": names.get(i, str(i))} | e for i, e in ar["objects"].items()}
        report["bop19"] = ar
    measures = {name: q for name, key in UNCERTAINTY.items() if (q := uncertainty_quality(records, key))}
    calibration = covariance_calibration(records, objects)
    return report | measures | ({"calibration": calibration} if calibration else {})


def _mean_of_defined(values: list[float]) -> float:
    """The mean over the objects where a measure is defined (an object never posed has no depth error), NaN if none."""
    defined = [v for v in values if not np.isnan(v)]
    return float(np.mean(defined)) if defined else float("nan")


REFINE_KEYS = ("add_0.1d", "reproj_15px")


def unrefined_records(records: list[Record]) -> list[Record]:
    """The records with each pose the refiner saw as it was before refinement."""
    return [dataclasses.replace(r, R=r.unrefined[0], t=r.unrefined[1], scores=r.unrefined_scores)
            if r.unrefined is not None and r.unrefined_scores is not None else r for r in records]  # fmt: skip


def pooled(records: list[Record]) -> dict[str, float]:
    """Over all instances at once rather than per object: the median rotation error and the mean |log| depth error
    of the posed ones (what one bad object's median hides), and ADD(-S)@0.1d and Reproj@15px."""
    return {"n": len(records), "rot_err_median_deg": float(np.median([r.scores["rot_err_deg"] for r in records])) if records else np.nan,
            "depth_log_abs_mean": depth_errors(records)["depth_log_abs_mean"],
            **{k: float(np.mean([r.scores[k] for r in records])) if records else float("nan") for k in REFINE_KEYS}}  # fmt: skip


def refinement_summary(records: list[Record]) -> dict | None:
    """What contour refinement changed in one object's records: how many poses it refined and kept (by reason), and
    the scores of all its records with each pose as it was before refinement (`unrefined`: ADD(-S)@0.1d,
    Reproj@15px, median rotation error, depth; the instances it did not see, unposed ones among them, as they are),
    to set beside the report's own. None where the refiner saw none of them."""
    seen = [r for r in records if r.unrefined is not None and r.unrefined_scores is not None]
    if not seen:
        return None
    before = unrefined_records(records)
    unrefined = {k: float(np.mean([r.scores[k] for r in before])) for k in REFINE_KEYS}
    unrefined["rot_err_median_deg"] = float(np.median([r.scores["rot_err_deg"] for r in before]))
    unrefined |= depth_errors(before)
    kept = Counter(r.refine_kept for r in seen if r.refine_kept)
    return {"n": len(seen), "refined": len(seen) - sum(kept.values()), "kept": dict(kept), "unrefined": unrefined}


DEPTH_KEYS = ("depth_log_abs_mean", "depth_ratio_median")


def depth_errors(records: list[Record]) -> dict[str, float]:
    """The posed instances' depth against the truth: the mean |log(z / z_gt)| (its spread, what ADD(-S) at small
    thresholds needs within about 1 %) and the median z / z_gt (its bias); NaN without a posed instance."""
    ratios = np.array([r.t[2] / r.t_gt[2] for r in records if r.ok and r.t[2] > 0 and r.t_gt[2] > 0])
    if not len(ratios):
        return dict.fromkeys(DEPTH_KEYS, float("nan"))
    return {"depth_log_abs_mean": float(np.mean(np.abs(np.log(ratios)))), "depth_ratio_median": float(np.median(ratios))}


CHI2_3 = {"median": 2.366, "68": 3.527, "95": 7.815}
"""Quantiles of χ²(3), the law of a right covariance's squared Mahalanobis lengths of 3D errors."""


def covariance_calibration(records: list[Record], objects: list[ObjectSpec]) -> dict | None:
    """Is the reported covariance the size of the errors? Per part (translation, rotation), the median squared
    Mahalanobis length of the posed instances' errors (`metrics.mahalanobis_sq`; χ²(3)'s median 2.37 if right,
    more where the covariance is too narrow) and the fractions within χ²(3)'s 68 and 95 % quantiles. Symmetric
    objects are left out: their rotation error has no one direction. None without covariances."""
    symmetric = {o.obj_id for o in objects if o.symmetric}
    d2 = np.array([mahalanobis_sq(r.R, r.t, r.R_gt, r.t_gt, r.covariance) for r in records
                   if r.ok and r.covariance is not None and r.obj_id not in symmetric])  # fmt: skip
    if len(d2) < 4:
        return None
    out: dict[str, float] = {"n": len(d2)}
    for k, part in enumerate(("translation", "rotation")):
        out[f"{part}_median_d2"] = float(np.median(d2[:, k]))
        for q in ("68", "95"):
            out[f"{part}_within_{q}"] = float(np.mean(d2[:, k] <= CHI2_3[q]))
    return out


UNCERTAINTY = {"spread": "spread_deg", "sigma": "sigma_deg"}
"""A report's uncertainty measures: the samples' spread and the covariance's rotation sigma, by Record field."""

_LABELS = {"spread_deg": "spread of the samples (deg, RMS)", "sigma_deg": "rotation sigma of the covariance (deg)"}


def rotation_sigma_deg(covariance: np.ndarray | None) -> float:
    """A pose covariance's (x, y, z, rx, ry, rz) rotation standard deviation: √(trace of its rotation block), in
    degrees; NaN without one."""
    return float(np.degrees(np.sqrt(np.trace(covariance[3:, 3:])))) if covariance is not None else float("nan")


def _certain(records: list[Record], key: str) -> tuple[list[Record], np.ndarray]:
    """Records with a pose and a finite `key` (a Record field), and its values."""
    rs = [r for r in records if r.ok and np.isfinite(getattr(r, key))]
    return rs, np.array([getattr(r, key) for r in rs])


def uncertainty_quality(records: list[Record], key: str) -> dict | None:
    """Does an uncertainty (`key`: spread_deg or sigma_deg) predict the error? Its rank correlation with the rotation
    error, and the accuracy of all poses against that of the half with the least uncertainty (None without it)."""
    from scipy.stats import spearmanr

    rs, u = _certain(records, key)
    if len(rs) < 4:
        return None
    rot = np.array([r.scores["rot_err_deg"] for r in rs])
    half = np.argsort(u, kind="stable")[: len(rs) // 2]
    out: dict[str, float] = {"n": len(rs), "spearman_vs_rot_err": float(spearmanr(u, rot).statistic)}
    for score_key in ("add_0.2d", "reproj_15px"):
        score = np.array([r.scores[score_key] for r in rs])
        out[f"{score_key}_all_posed"] = float(score.mean())
        out[f"{score_key}_least_half"] = float(score[half].mean())
    return out


def plot_uncertainty(records: list[Record], out_dir: str | Path, key: str) -> Path | None:
    """Rotation error against an uncertainty (`key`), and accuracy when only the least uncertain fraction is kept."""
    rs, u = _certain(records, key)
    if len(rs) < 4:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rot = np.array([r.scores["rot_err_deg"] for r in rs])
    order = np.argsort(u, kind="stable")
    kept = np.arange(1, len(rs) + 1) / len(rs)
    out = Path(out_dir) / f"error_vs_{key.removesuffix('_deg')}.png"
    out.parent.mkdir(parents=True, exist_ok=True)
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 4))
    a1.scatter(np.maximum(u, 1e-2), rot, s=6, alpha=0.5)
    a1.set(xscale="log", xlabel=_LABELS[key], ylabel="rotation error (deg)", ylim=(0, 180), title="error vs uncertainty")
    for score_key, label in (("reproj_15px", "Reproj@15px"), ("add_0.2d", "ADD(-S)@0.2d")):
        score = np.array([r.scores[score_key] for r in rs])[order]
        a2.plot(kept, np.cumsum(score) / np.arange(1, len(rs) + 1), label=label)
    a2.set(xlabel="fraction kept (least uncertain first)", ylabel="accuracy of the kept poses", xlim=(0, 1), title="sparsification")
    a2.legend()
    fig.tight_layout()
    fig.savefig(out, dpi=100)
    plt.close(fig)
    return out


def format_table(report: dict) -> str:
    """The report's per-object rows and their mean, as a fixed-width table."""
    keys = ("add_0.1d", "add_0.2d", "reproj_5px", "reproj_15px")
    refined = "refine" in report["mean"]
    head = f"{'object':<12} {'n':>4} {'ADD0.1d':>8} {'ADD0.2d':>8} {'Rep5px':>8} {'Rep15px':>8} {'rot med':>8} {'t med mm':>9}"
    lines = [head + (f" | unrefined: {'ADD0.1d':>8} {'Rep15px':>8} {'rot med':>8}" if refined else "")]
    rows = [(e["name"], str(e["n"]), e) for e in report["objects"].values()]
    if report["mean"]:
        rows.append(("mean", "", report["mean"]))
    for name, n, e in rows:
        cells = " ".join(f"{e[k]:8.3f}" for k in keys)
        line = f"{name:<12} {n:>4} {cells} {e['rot_err_median_deg']:8.1f} {e['trans_err_median_mm']:9.1f}"
        if refined and "refine" in e:
            u = e["refine"]["unrefined"]
            line += f" | {'':10} {u['add_0.1d']:8.3f} {u['reproj_15px']:8.3f} {u['rot_err_median_deg']:8.1f}"
        lines.append(line)
    if refined:
        r = report["mean"]["refine"]
        kept = ", ".join(f"{k} {v}" for k, v in sorted(r["kept"].items())) or "none"
        lines.append(f"contour refinement: {r['refined']} poses refined, kept: {kept}; unrefined: the same poses before it")
    return "\n".join(lines)


def format_average_recall(ar: dict) -> str:
    """BOP19 average recall per object and overall, one row each; says when VSD is missing (no depth images)."""
    kinds = ar["kinds"]
    if not kinds:
        return "BOP19 average recall: no instances to find"
    head = f"{'object':<12} {'targets':>7} " + " ".join(f"{'AR_' + k.upper():>8}" for k in kinds) + f" {'AR':>8}"
    rows = [(e["name"], e["targets"], e) for e in ar["objects"].values()] + [("all", ar["targets"], ar)]
    lines = [head]
    for name, n, e in rows:
        lines.append(f"{name:<12} {n:>7} " + " ".join(f"{e[f'ar_{k}']:8.3f}" for k in kinds) + f" {e.get('ar', 0.0):8.3f}")
    if "vsd" not in kinds:
        lines.append("AR is the mean of AR_MSSD and AR_MSPD: the scenes have no depth images, so no VSD")
    return "\n".join(lines)


def write_report(report: dict, path: str | Path) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(report, indent=1, default=float))


def plot_cdfs(records: list[Record], objects: list[ObjectSpec], out_dir: str | Path) -> Path:
    """Rotation-error and ADD(-S)/diameter CDFs per object."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out_dir) / "error_cdfs.png"
    out.parent.mkdir(parents=True, exist_ok=True)
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 4))
    for o in objects:
        rs = [r for r in records if r.obj_id == o.obj_id]
        if not rs:
            continue
        rot = np.sort([r.scores["rot_err_deg"] for r in rs])
        add = np.sort([r.scores.get("add_err_m", np.inf) / o.diameter for r in rs])
        y = np.arange(1, len(rs) + 1) / len(rs)
        a1.step(rot, y, label=o.name)
        a2.step(np.minimum(add, 10), y, label=o.name)
    a1.set(xlabel="rotation error (deg)", ylabel="fraction of instances", xlim=(0, 180), title="rotation error CDF")
    a2.set(xlabel="ADD(-S) / diameter", xlim=(0, 1), title="ADD(-S) CDF")
    a2.axvline(0.1, ls="--", c="gray")
    a1.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out, dpi=100)
    plt.close(fig)
    return out


def _box_corners(spec: ObjectSpec, points: np.ndarray) -> np.ndarray:
    lo, hi = points.min(axis=0), points.max(axis=0)
    return np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])


def plot_grid(records: list[Record], objects: list[ObjectSpec], models_dir: str | Path, out_dir: str | Path, count: int = 24) -> Path:
    """Crops around the GT box with the GT (green) and predicted (red) 3D boxes and axes, worst cases last; records
    without an image file (a bag's) are left out."""
    specs = {o.obj_id: o for o in objects}
    corners = {i: _box_corners(specs[i], load_ply(model_path(models_dir, i)).vertices) for i in specs}
    edges = [(0, 1), (0, 2), (1, 3), (2, 3), (4, 5), (4, 6), (5, 7), (6, 7), (0, 4), (1, 5), (2, 6), (3, 7)]
    picks = sorted((r for r in records if r.rgb_path is not None), key=lambda r: r.scores["rot_err_deg"])
    picks = [picks[int(i)] for i in np.linspace(0, len(picks) - 1, min(count, len(picks)))] if picks else []
    tiles = []
    for r in picks:
        image = read_bgr(r.rgb_path)
        center, side = square_around_box(r.box, 1.5)
        Kc = crop_intrinsics(r.K, center, side, 160)
        tile = crop_image(image, center, side, 160)
        for R, t, color, ok in ((r.R_gt, r.t_gt, (0, 200, 0), True), (r.R, r.t, (0, 0, 255), r.ok)):
            if not ok:
                continue
            cam = corners[r.obj_id] @ R.T + t
            if np.any(cam[:, 2] <= 0):
                continue
            uv = cam @ Kc.T
            uv = uv[:, :2] / uv[:, 2:3]
            for a, b in edges:
                cv2.line(tile, tuple(np.round(uv[a]).astype(int)), tuple(np.round(uv[b]).astype(int)), color, 1, cv2.LINE_AA)
            draw_axes(tile, Kc, R, t, specs[r.obj_id].axes.lengths, 1)
        cv2.putText(
            tile, f"{specs[r.obj_id].name} {r.scores['rot_err_deg']:.0f}deg", (3, 12), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1
        )
        tiles.append(tile)
    out = Path(out_dir) / "crops_grid.png"
    out.parent.mkdir(parents=True, exist_ok=True)
    if tiles:
        while len(tiles) % 6:
            tiles.append(np.zeros_like(tiles[0]))
        cv2.imwrite(str(out), np.vstack([np.hstack(tiles[i : i + 6]) for i in range(0, len(tiles), 6)]))
    return out
