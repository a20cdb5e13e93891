"""How far a scene's consecutive frames lie apart, from its ground truth alone: what a tracker can carry over.

Between consecutive frames (image ids in order) the camera's motion is the rigid motion on which most objects agree
(each object's GT pose change is a candidate; the one that moves the most object centres to within `tol` of their
next positions wins). A camera stream at its own rate turns a degree or so and moves objects a few pixels per frame;
`scene_motion` tells whether a recording is such a stream (`bench/sequence_motion.py`).
"""

from __future__ import annotations

import itertools
from typing import Any

import numpy as np

from axispose_core.data.bop import GTInstance
from axispose_core.data.bop_scene import BopScene
from axispose_core.metrics import re


def _transform(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    M = np.eye(4)
    M[:3, :3], M[:3, 3] = R, t
    return M


def camera_motion(before: list[GTInstance], after: list[GTInstance], tol: float) -> tuple[np.ndarray, list[float]] | None:
    """The camera's motion from one frame to the next (4x4, camera-before to camera-after) and each common object's
    centre distance (m) from where that motion puts it, in order of object id; None without a common object."""
    a = {g.obj_id: _transform(g.R, g.t) for g in before}
    b = {g.obj_id: _transform(g.R, g.t) for g in after}
    common = sorted(set(a) & set(b))
    if not common:
        return None
    best, best_off, best_on = None, None, -1
    for j in common:
        motion = b[j] @ np.linalg.inv(a[j])
        off = [float(np.linalg.norm((motion @ a[i])[:3, 3] - b[i][:3, 3])) for i in common]
        if (on := sum(o <= tol for o in off)) > best_on:
            best, best_off, best_on = motion, off, on
    return best, best_off


def scene_motion(scene: BopScene, tol: float) -> dict[str, Any]:
    """Median and 75th percentile of the camera's rotation (deg) and of the objects' image motion (px) between
    consecutive frames, the share of object steps that move against the rest and, per object id, its steps that do
    (`moves`: none for a still scene); ValueError where no two consecutive frames share an object."""
    ids = sorted(scene.gt)
    rotation, pixels, moved, steps = [], [], 0, 0
    moves: dict[int, int] = {}
    for im_a, im_b in itertools.pairwise(ids):
        found = camera_motion(scene.gt[im_a], scene.gt[im_b], tol)
        if found is None:
            continue
        motion, off = found
        rotation.append(re(motion[:3, :3], np.eye(3)))
        moved, steps = moved + sum(o > tol for o in off), steps + len(off)
        common = sorted({g.obj_id for g in scene.gt[im_a]} & {g.obj_id for g in scene.gt[im_b]})
        for obj_id, o in zip(common, off, strict=True):
            moves[obj_id] = moves.get(obj_id, 0) + int(o > tol)
        K = scene.cameras[im_b]
        after = {g.obj_id: g.t for g in scene.gt[im_b]}
        for g in scene.gt[im_a]:
            if g.obj_id in after:
                p, q = K @ g.t, K @ after[g.obj_id]
                pixels.append(float(np.linalg.norm(p[:2] / p[2] - q[:2] / q[2])))
    if not rotation:
        raise ValueError(f"{scene.root}: no two consecutive frames share an annotated object")
    return {
        "frames": len(ids),
        "rotation_deg_median": float(np.median(rotation)),
        "rotation_deg_q75": float(np.percentile(rotation, 75)),
        "image_motion_px_median": float(np.median(pixels)),
        "image_motion_px_q75": float(np.percentile(pixels, 75)),
        "objects_moved_share": moved / max(steps, 1),
        "moves": moves,
    }
