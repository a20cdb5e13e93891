"""Would a second AGM pass, framed by the first pose, read a found object better? For every instance the
localiser finds (IoU 0.5, as `axispose validate` counts hits, through the checkpoint's verifier where it has one) the
pose from the detection's box (the node's path: 1 sample, 3 steps, float32) is compared with the pose from the box
of the object's hull projected at that pose (once and twice), and with the pose from the GT box. The hull is a
farthest-point sample of the model's convex hull (what a checkpoint would have to carry). It also asks how much of
the detection box's scale error the depth takes on: the slope of the depth's log error from the detection's crop,
less the GT box's, on the log ratio of the two crops' sides.

    python bench/pose_recrop.py --checkpoint EST --data HELDOUT/test --json bench/results/pose_recrop_held.json
"""

from __future__ import annotations

import argparse

import numpy as np
from node_estimator import add_common_arguments, node_estimator
from scipy.spatial import ConvexHull
from write_results import write_results

from axispose_core.camera import square_around_box
from axispose_core.data.bop import GTInstance, bbox_from_model
from axispose_core.data.bop_models import model_path
from axispose_core.data.bop_scene import bop_frames
from axispose_core.data.meshes import load_ply
from axispose_core.data.visibility import gt_info_from_models
from axispose_core.estimator import EstimateOptions, Estimator
from axispose_core.evaluation.records import object_symmetries
from axispose_core.localiser.decode import match
from axispose_core.localiser.scoring import frame_instances, frame_outcome
from axispose_core.metrics import pose_scores
from axispose_core.objects import ObjectSpec
from axispose_core.pose_estimate import PoseEstimate

PASSES = ("detection", "recrop1", "recrop2", "gt_box")


def hull_sample(points: np.ndarray, n: int) -> np.ndarray:
    """n of the convex hull's vertices, farthest-point sampled from the one farthest from the centroid."""
    hull = points[ConvexHull(points).vertices]
    pick = [int(np.argmax(np.linalg.norm(hull - hull.mean(0), axis=1)))]
    dist = np.linalg.norm(hull - hull[pick[0]], axis=1)
    while len(pick) < min(n, len(hull)):
        pick.append(int(np.argmax(dist)))
        dist = np.minimum(dist, np.linalg.norm(hull - hull[pick[-1]], axis=1))
    return hull[pick]


def recropped(est: Estimator, rgb: np.ndarray, K: np.ndarray, obj: int, first: PoseEstimate, hull: np.ndarray,
              options: EstimateOptions) -> list[PoseEstimate]:  # fmt: skip
    """The poses of one and two more passes, each cropped around the hull's box at the pose before it."""
    out, pose = [], first
    for _ in range(2):
        pose = est.estimate(rgb, K, [(obj, bbox_from_model(K, pose.R, pose.t, hull))], options)[0] if pose.ok else pose
        out.append(pose)
    return out


def scores(p: PoseEstimate, gt: GTInstance, K: np.ndarray, points: np.ndarray, spec: ObjectSpec, syms: list | None) -> dict | None:
    """`pose_scores` (symmetric objects up to their symmetries) and the depth's |log| error; None for a refused pose."""
    if not p.ok:
        return None
    s = pose_scores(p.R, p.t, gt.R, gt.t, K, points, spec.diameter, syms if spec.symmetric else None)
    depth_log = float(np.log(p.t[2] / gt.t[2]))
    return s | {"depth_log": depth_log, "depth_abs_log": abs(depth_log)}


def depth_on_framing(rows: list[dict]) -> dict[str, float]:
    """Least-squares slope and correlation of (detection crop's - GT crop's) log depth error on the crops' log side
    ratio, over the instances both posed."""
    both = [r for r in rows if r["detection"] and r["gt_box"]]
    scale = np.array([r["side_log_ratio"] for r in both])
    gap = np.array([r["detection"]["depth_log"] - r["gt_box"]["depth_log"] for r in both])
    return {"slope": float(np.polyfit(scale, gap, 1)[0]), "correlation": float(np.corrcoef(scale, gap)[0, 1]),
            "side_log_ratio_robust_std": float(1.4826 * np.median(np.abs(scale - np.median(scale))))}  # fmt: skip


def summary(rows: list[dict], key: str) -> dict[str, float]:
    """Means over the instances (a refused pose counts as wrong), the rotation's median, the depth's mean |log|."""
    got = [r[key] for r in rows]
    return {
        "add_0.1d": float(np.mean([g["add_0.1d"] if g else 0.0 for g in got])),
        "reproj_15px": float(np.mean([g["reproj_15px"] if g else 0.0 for g in got])),
        "rot_median_deg": float(np.median([g["rot_err_deg"] if g else 180.0 for g in got])),
        "depth_abs_log": float(np.mean([g["depth_abs_log"] for g in got if g])),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_common_arguments(ap, "hulls, metrics and visibility")
    ap.add_argument("--data", required=True, help="BOP frames")
    ap.add_argument("--hull-points", type=int, default=64)
    ap.add_argument("--score-threshold", type=float, default=0.3, help="the node's")
    args = ap.parse_args()
    est = node_estimator(args)
    options = EstimateOptions(steps=3)
    specs = {o.obj_id: o for o in est.config.objects}
    points = {i: load_ply(model_path(args.models, i)).vertices for i in specs}
    hulls = {i: hull_sample(p, args.hull_points) for i, p in points.items()}
    syms = object_symmetries(est.config.objects, points)
    rows = []
    for scene, im_id in bop_frames([args.data], gt_info_from_models(args.models)):
        rgb, K = scene.rgb(im_id), scene.cameras[im_id]
        found = est.find(rgb, K, args.score_threshold, options)
        insts = frame_instances(scene, im_id, tuple(specs))
        truths = [g for g, _ in scene.instances(im_id) if g.obj_id in specs]
        hits, (counted, _) = match(found.detections, [(o, b) for o, b, _ in insts]), frame_outcome(found.detections, insts, args.min_visib)
        for g, k in enumerate(hits):
            if k is None or g not in counted or not found.poses[k].ok:
                continue
            obj, first = insts[g][0], found.poses[k]
            passes = [first, *recropped(est, rgb, K, obj, first, hulls[obj], options)]
            passes.append(est.estimate(rgb, K, [(obj, insts[g][1])], options)[0])
            scored = [scores(p, truths[g], K, points[obj], specs[obj], syms.get(obj)) for p in passes]
            side = np.log(square_around_box(found.detections[k].box)[1] / square_around_box(insts[g][1])[1])
            rows.append({"side_log_ratio": float(side)} | dict(zip(PASSES, scored, strict=True)))
    results = {"checkpoint": args.checkpoint, "data": args.data, "hits": len(rows), "hull_points": args.hull_points}
    results |= {key: summary(rows, key) for key in PASSES} | {"depth_on_framing": depth_on_framing(rows)}
    for key in (*PASSES, "depth_on_framing"):
        print(key, {m: round(v, 4) for m, v in results[key].items()})
    if args.json:
        write_results(args.json, results)


if __name__ == "__main__":
    main()
