"""Frame-to-frame jitter of a pose stream against ground truth: what users of a pose node see as "jumpy output".

Over consecutive frames k-1, k where an object has both a pose and its truth, the change of the pose error:
‖(t_pred − t_gt)_k − (t_pred − t_gt)_{k−1}‖ for translation and the angle of R_err,k R_err,k−1ᵀ with
R_err = R_pred R_gtᵀ for rotation. A camera or object that moves does not count; only the error's change does.
For a symmetric object, R_gt is the symmetric GT pose nearest the prediction, so choosing another of its
equivalent poses is not a jump.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from axispose_core.metrics import Symmetry, nearest_truth, re


@dataclass(frozen=True)
class PosePair:
    """One object's prediction and truth in one frame (metres)."""

    frame: int
    obj_id: int
    R_pred: np.ndarray
    t_pred: np.ndarray
    R_gt: np.ndarray
    t_gt: np.ndarray


def jitter(pairs: Sequence[PosePair], syms: dict[int, Sequence[Symmetry]] | None = None) -> dict[str, float | int]:
    """Median change of the pose error between consecutive frames, per object then pooled: `jitter_mm`,
    `jitter_deg` and the number of frame pairs `n` (NaN medians when there are none)."""
    syms = syms or {}
    by_obj: dict[int, list[PosePair]] = {}
    for p in sorted(pairs, key=lambda p: (p.obj_id, p.frame)):
        by_obj.setdefault(p.obj_id, []).append(p)
    dt, dr = [], []
    for obj_id, seq in by_obj.items():
        errors = {}
        for p in seq:
            R_gt, t_gt = nearest_truth(p.R_pred, p.R_gt, p.t_gt, syms.get(obj_id, ()))
            errors[p.frame] = (p.R_pred @ R_gt.T, p.t_pred - t_gt)
        for frame, (R_err, t_err) in errors.items():
            if frame - 1 in errors:
                R_prev, t_prev = errors[frame - 1]
                dt.append(1000.0 * float(np.linalg.norm(t_err - t_prev)))
                dr.append(re(R_err, R_prev))
    nan = float("nan")
    return {"jitter_mm": float(np.median(dt)) if dt else nan, "jitter_deg": float(np.median(dr)) if dr else nan, "n": len(dt)}
