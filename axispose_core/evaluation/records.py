"""What an evaluation scores: the predictor's answer for a box (`Prediction`), a scored GT instance (`Record`),
and how one instance is scored (`instance_scores`, with a symmetric object's equivalent poses)."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from axispose_core.metrics import ADD_THRESHOLDS, REPROJ_THRESHOLDS, Symmetry, half_turn_symmetries, pose_scores
from axispose_core.objects import ObjectSpec

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


def rotation_sigma_deg(covariance: np.ndarray | None) -> float:
    """A pose covariance's (x, y, z, rx, ry, rz) rotation standard deviation: √(trace of its rotation block), in
    degrees; NaN without one."""
    return float(np.degrees(np.sqrt(np.trace(covariance[3:, 3:])))) if covariance is not None else float("nan")
