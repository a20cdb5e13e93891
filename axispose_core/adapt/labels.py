"""From the scene's predictions to labels on the frames' pixels, and the labels as a BOP folder the trainers read.

Every prediction of the consistency stage is refined on its frame's contours (the frame's objects together, each
masking the lines of those behind it; the scene's pose as the prior) and becomes a label where the contour took it
and agrees with the image (`FillConfig.min_agreement`) without leaving the scene's gates. A prediction the frame had
accepted itself stays a label even where the contour cannot refine it (its own pose, which the scene checked).
Poses that stand on their frame's evidence alone are labels as they are.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from axispose_core.adapt.geometry import ObjectGeometry, pose_matrix
from axispose_core.adapt.pseudo import Candidate
from axispose_core.adapt.recording import Frame
from axispose_core.adapt.scene import ConsistencyConfig, Prediction, agree
from axispose_core.data.bop import GTInstance, write_scene_camera, write_scene_gt, write_scene_gt_info
from axispose_core.data.visibility import estimate_gt_info
from axispose_core.refine.refiner import ContourRefiner, Start
from axispose_core.rotation import nearest_rotation

SOURCES = ("checked", "filled", "alone")
"""Where a label comes from: a frame's accepted pose the scene agrees with, a prediction where the frame accepted
none, a frame's accepted pose the scene could not check."""


@dataclass(frozen=True)
class FillConfig:
    """How predictions become labels: refined from the scene's pose with a prior of `prior_deg` (rotation) and
    `prior_lateral` / `prior_depth` (position across / along the line of sight, fractions of the distance), kept
    where the refined contour agrees with the image at least `min_agreement`."""

    min_agreement: float = 0.7
    prior_deg: float = 5.0
    prior_lateral: float = 0.01
    prior_depth: float = 0.03


@dataclass(frozen=True)
class Label:
    """A pose taken for the truth on a frame, where it came from (`SOURCES`) and its contour's agreement there."""

    im_id: int
    obj_id: int
    R: np.ndarray
    t: np.ndarray
    source: str
    agreement: float

    def to_json(self) -> dict:
        d = asdict(self) | {"R": self.R.ravel().tolist(), "t": self.t.tolist()}
        return d | {"agreement": None if not math.isfinite(self.agreement) else self.agreement}

    @classmethod
    def from_json(cls, d: dict) -> Label:
        agreement = float("nan") if d["agreement"] is None else float(d["agreement"])
        R = nearest_rotation(np.asarray(d["R"], float).reshape(3, 3))
        return cls(int(d["im_id"]), int(d["obj_id"]), R, np.asarray(d["t"], float), d["source"], agreement)


def prior(R: np.ndarray, t: np.ndarray, cfg: FillConfig) -> np.ndarray:
    """The refiner's prior covariance of a scene pose (geometry_msgs' order, camera frame)."""
    d = float(np.linalg.norm(t))
    ray = t / max(d, 1e-9)
    lateral, depth = cfg.prior_lateral * d, cfg.prior_depth * d
    cov = np.zeros((6, 6))
    cov[:3, :3] = lateral**2 * np.eye(3) + (depth**2 - lateral**2) * np.outer(ray, ray)
    cov[3:, 3:] = np.radians(cfg.prior_deg) ** 2 * np.eye(3)
    return cov


def label_frame(
    refiner: ContourRefiner, image: np.ndarray, K: np.ndarray, predictions: Sequence[Prediction], alone: Sequence[Candidate],
    geometry: Mapping[int, ObjectGeometry], consistency: ConsistencyConfig, cfg: FillConfig,
) -> list[Label]:  # fmt: skip
    """One frame's labels: its predictions refined on it (or the frame's own pose where the scene checked it), and
    the poses that stand alone."""
    starts = [Start(p.obj_id, p.R, p.t, prior(p.R, p.t, cfg)) for p in predictions]
    refined = refiner.refine(image, K, starts) if starts else []
    labels = []
    for p, r in zip(predictions, refined, strict=True):
        took = r.refined and r.agreement >= cfg.min_agreement
        took = took and agree(consistency, pose_matrix(r.R, r.t), pose_matrix(p.R, p.t), geometry[p.obj_id])
        if took:
            labels.append(Label(p.im_id, p.obj_id, r.R, r.t, "checked" if p.own is not None else "filled", float(r.agreement)))
        elif p.own is not None:
            labels.append(Label(p.im_id, p.obj_id, p.own.R, p.own.t, "checked", p.own.agreement))
    return labels + [Label(c.im_id, c.obj_id, c.R, c.t, "alone", c.agreement) for c in alone]


def write_labels(out: str | Path, frames: Sequence[Frame], labels: Sequence[Label], models_dir: str | Path) -> Path:
    """The labelled frames as a BOP scene folder OUT (rgb/ linked to the recording's images, scene_camera.json,
    scene_gt.json of the labels, scene_gt_info.json from the models at the labels), and OUT/labels.json with where
    each label came from; frames without a label are left out. Returns OUT."""
    out = Path(out)
    (out / "rgb").mkdir(parents=True, exist_ok=True)
    by_frame: dict[int, list[Label]] = {}
    for lab in labels:
        by_frame.setdefault(lab.im_id, []).append(lab)
    kept = [f for f in frames if f.im_id in by_frame]
    gt, info = {}, {}
    for f in kept:
        link = out / "rgb" / f"{f.im_id:06d}{f.path.suffix}"
        if not link.exists():
            os.symlink(f.path.resolve(), link)
        gt[f.im_id] = [GTInstance(lab.obj_id, lab.R, lab.t) for lab in by_frame[f.im_id]]
        h, w = f.rgb().shape[:2]
        info[f.im_id] = estimate_gt_info(f.K, gt[f.im_id], models_dir, w, h)
    write_scene_camera(out / "scene_camera.json", {f.im_id: f.K for f in kept})
    write_scene_gt(out / "scene_gt.json", gt)
    write_scene_gt_info(out / "scene_gt_info.json", info)
    (out / "labels.json").write_text(json.dumps([lab.to_json() for f in kept for lab in by_frame[f.im_id]]))
    return out
