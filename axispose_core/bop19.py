"""BOP19 average recall: AR_VSD, AR_MSSD and AR_MSPD, as the BOP Challenge scores 6D object localisation.

The definitions are bop_toolkit's (`eval_bop19_pose.py`, `eval_calc_errors.py`, `eval_calc_scores.py`,
`pose_matching.py`, `score.py`): per image and object, the top-scoring estimates, as many as the instances to find
(n_top = -1), get errors against each of those instances; for every correctness threshold (and VSD tolerance τ)
estimates are matched greedily in order of decreasing score to the unmatched instance with the lowest error below
the threshold; recall is matched instances over all instances to find, pooled over objects; AR_e is the mean
recall over e's thresholds, and AR the mean of AR_VSD, AR_MSSD and AR_MSPD (without depth images, of the two).

Errors are computed image by image (`image_errors`), so an evaluation holds no frames; `average_recall` then
matches and counts.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from axispose_core.data.bop_models import ObjectInfo, model_path
from axispose_core.data.bop_results import BopEstimate
from axispose_core.data.meshes import load_ply
from axispose_core.data.synth.raster import RenderMesh, render_depth
from axispose_core.metrics import Symmetry, mspd, mssd, symmetry_transformations, vsd

VSD_DELTA = 0.015
"""VSD's visibility tolerance (m): BOP's 15 mm for LM-O and every dataset but ITODD."""
FRACTIONS = tuple(round(0.05 * k, 2) for k in range(1, 11))
"""0.05, 0.10, ..., 0.50: VSD's misalignment tolerances τ, and the correctness thresholds of VSD and of MSSD
(the latter as a fraction of the object's diameter)."""
MSPD_PX = tuple(float(p) for p in range(5, 51, 5))
"""MSPD's correctness thresholds (px) at an image width of 640; errors are scaled by 640 / width."""
MAX_SYM_DISC_STEP = 0.01
"""How finely continuous symmetries are sampled (bop_toolkit's max_sym_disc_step)."""
KINDS = ("vsd", "mssd", "mspd")


@dataclass(frozen=True)
class BopObject:
    """What the errors need of one object: its evaluation model (points in metres, faces for the depth renders of
    VSD), diameter and symmetry transformations."""

    obj_id: int
    points: np.ndarray
    faces: np.ndarray
    diameter: float
    symmetries: list[Symmetry]

    @classmethod
    def load(cls, models_dir: str | Path, info: ObjectInfo) -> BopObject:
        mesh = load_ply(model_path(models_dir, info.obj_id))
        syms = symmetry_transformations(info.symmetries_discrete, info.symmetries_continuous, MAX_SYM_DISC_STEP)
        return cls(info.obj_id, mesh.vertices, mesh.faces, info.diameter, syms)

    def depth(self, R: np.ndarray, t: np.ndarray, K: np.ndarray, width: int, height: int) -> np.ndarray:
        """The model's depth image at pose (R, t) (m; 0 off the model)."""
        zeros = np.zeros_like(self.points)
        return render_depth(RenderMesh(self.points, self.faces, zeros, zeros), R, t, K, width, height)


@dataclass(frozen=True)
class BopImage:
    """What the errors need of one image besides the poses: its BOP ids, its camera, its size (MSPD is scaled to a
    640 px width; VSD renders at this size) and its depth image (m, 0: none; None: the scene has none, so no VSD)."""

    scene_id: int
    im_id: int
    K: np.ndarray
    width: int
    height: int
    depth: np.ndarray | None = None


@dataclass
class ImageErrors:
    """One evaluated image: its instances to find (`obj_ids`), every estimate made (for the results file), and
    the errors of the estimates that take part (`kept`, by decreasing score) against each instance, in units of
    the thresholds: VSD per τ, MSSD / diameter, MSPD in px at 640 px width; inf between different objects."""

    scene_id: int
    im_id: int
    obj_ids: np.ndarray
    estimates: list[BopEstimate]
    kept: np.ndarray
    errors: dict[str, np.ndarray]
    """kind -> (len(kept), len(obj_ids), settings): settings are the τ values for VSD, one otherwise."""


def image_errors(
    image: BopImage, estimates: list[BopEstimate], targets: list[tuple[int, np.ndarray, np.ndarray]], objects: dict[int, BopObject]
) -> ImageErrors:
    """The errors of one image's `estimates` against its `targets` [(obj_id, R, t)]: the instances to find. Per
    object, only the best-scored estimates take part, as many as it has targets (estimates of objects without
    one take none). VSD needs the image's depth and is left out without it."""
    K, width, height, depth = image.K, image.width, image.height, image.depth
    obj_ids = np.array([o for o, _, _ in targets], dtype=np.int64)
    order = sorted(range(len(estimates)), key=lambda i: -estimates[i].score)  # stable, as BOP's sort
    quota = {int(o): int(np.count_nonzero(obj_ids == o)) for o in obj_ids}
    kept = []
    for i in order:
        if quota.get(estimates[i].obj_id, 0) > 0:
            quota[estimates[i].obj_id] -= 1
            kept.append(i)
    shape = (len(kept), len(targets))
    errors = {"mssd": np.full((*shape, 1), np.inf), "mspd": np.full((*shape, 1), np.inf)}
    if depth is not None:
        errors["vsd"] = np.full((*shape, len(FRACTIONS)), np.inf)
    renders: dict[tuple[str, int], np.ndarray] = {}  # each estimate and each target rendered once

    def rendered(which: str, k: int, obj: BopObject, R: np.ndarray, t: np.ndarray) -> np.ndarray:
        if (which, k) not in renders:
            renders[which, k] = obj.depth(R, t, K, width, height)
        return renders[which, k]

    for a, i in enumerate(kept):
        e = estimates[i]
        obj = objects[e.obj_id]
        for b, (obj_id, R_gt, t_gt) in enumerate(targets):
            if obj_id != e.obj_id:
                continue
            errors["mssd"][a, b, 0] = mssd(e.R, e.t, R_gt, t_gt, obj.points, obj.symmetries) / obj.diameter
            errors["mspd"][a, b, 0] = mspd(e.R, e.t, R_gt, t_gt, K, obj.points, obj.symmetries) * 640.0 / width
            if depth is not None:
                d_est, d_gt = rendered("est", a, obj, e.R, e.t), rendered("gt", b, obj, R_gt, t_gt)
                errors["vsd"][a, b] = vsd(d_est, d_gt, depth, K, VSD_DELTA, FRACTIONS, obj.diameter)
    return ImageErrors(image.scene_id, image.im_id, obj_ids, list(estimates), np.array(kept, dtype=np.int64), errors)


def _matched(errors: np.ndarray, threshold: float) -> np.ndarray:
    """Which instances (columns) the estimates (rows, by decreasing score) match greedily: each estimate takes the
    unmatched instance with the lowest error below `threshold` (the first on a tie)."""
    matched = np.zeros(errors.shape[1], dtype=bool)
    for row in errors:
        candidates = np.where(matched | ~(row < threshold), np.inf, row)
        if candidates.size and np.isfinite(candidates.min()):
            matched[int(np.argmin(candidates))] = True
    return matched


def thresholds(kind: str) -> tuple[float, ...]:
    return MSPD_PX if kind == "mspd" else FRACTIONS


def average_recall(images: list[ImageErrors]) -> dict:
    """AR per kind (VSD only where every image had depth), their mean, and the same per object, with the count of
    instances to find: {"ar": .., "ar_vsd": .., "ar_mssd": .., "ar_mspd": .., "kinds": [...], "targets": n,
    "objects": {obj_id: {...}}}."""
    kinds = [k for k in KINDS if images and all(k in im.errors for im in images)]
    obj_ids = sorted({int(o) for im in images for o in im.obj_ids})
    targets = {o: sum(int(np.count_nonzero(im.obj_ids == o)) for im in images) for o in obj_ids}
    total = sum(targets.values())
    out: dict = {"kinds": kinds, "targets": total, "objects": {o: {"targets": n} for o, n in targets.items()}}
    for kind in kinds:
        recalls, per_object = [], {o: [] for o in obj_ids}
        for setting in range(len(FRACTIONS) if kind == "vsd" else 1):
            for th in thresholds(kind):
                found = {o: 0 for o in obj_ids}
                for im in images:
                    hit = _matched(im.errors[kind][:, :, setting], th)
                    for o in obj_ids:
                        found[o] += int(np.count_nonzero(hit & (im.obj_ids == o)))
                recalls.append(sum(found.values()) / total if total else 0.0)
                for o in obj_ids:
                    per_object[o].append(found[o] / targets[o])
        out[f"ar_{kind}"] = float(np.mean(recalls))
        for o in obj_ids:
            out["objects"][o][f"ar_{kind}"] = float(np.mean(per_object[o]))
    if kinds:
        out["ar"] = float(np.mean([out[f"ar_{k}"] for k in kinds]))
        for o in obj_ids:
            out["objects"][o]["ar"] = float(np.mean([out["objects"][o][f"ar_{k}"] for k in kinds]))
    return out
