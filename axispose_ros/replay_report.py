"""`replay`'s scores: the node's poses against the bag's ground truth, as `axispose eval` scores them, with the
frame latency, the node's counters and the frame-to-frame jitter."""

from __future__ import annotations

import numpy as np

from axispose_core.evaluation.records import Record, instance_scores, object_symmetries
from axispose_core.evaluation.summary import summarize
from axispose_core.metrics import Symmetry
from axispose_core.tracking.jitter import PosePair, jitter
from axispose_ros.node import AxisPoseNode
from axispose_ros.replay_bag import Truth


def _jitter(records: list[Record], syms: dict[int, list[Symmetry]]) -> dict:
    """Frame-to-frame jitter of the posed instances (`tracking/jitter.py`), a symmetric object's equivalent poses
    counting as one."""
    return jitter([PosePair(r.im_id, r.obj_id, r.R, r.t, r.R_gt, r.t_gt) for r in records if r.ok], syms)


def replay_report(node: AxisPoseNode, truth: Truth, poses: dict, latency: dict[int, float], counts: dict[str, int], config: dict) -> dict:
    """Per-instance scores as `axispose eval`: each GT instance matched to the nearest estimate of its object in
    the same frame (one-to-one); a frame the node dropped or an instance without estimate counts as wrong."""
    by_name = {o.name: o for o in node.estimator.config.objects}
    gt, points = truth.gt, truth.points
    syms = object_symmetries(by_name.values(), {by_name[n].obj_id: p for n, p in points.items() if n in by_name})
    records: list[Record] = []
    for k, stamp in enumerate(sorted(gt)):
        n_inst = max(1, sum(len(v) for v in gt[stamp].values()))
        seconds = latency.get(stamp, 0.0) / 1000 / n_inst
        K = truth.cameras.get(stamp)
        for name, instances in gt[stamp].items():
            spec = by_name.get(name)
            if spec is None or name not in points or name not in node.published.values() or K is None:
                continue
            ests = list(poses.get(stamp, {}).get(name, []))
            for R_gt, t_gt in instances:
                best = min(range(len(ests)), key=lambda i: np.linalg.norm(ests[i][1] - t_gt)) if ests else None
                R, t = ests.pop(best) if best is not None else (np.eye(3), np.zeros(3))
                pose = (R, t) if best is not None else None
                scores = instance_scores(spec, points[name], K, R_gt, t_gt, pose, syms.get(spec.obj_id, ()))
                records.append(
                    Record(
                        spec.obj_id,
                        "bag",
                        k,
                        scores,
                        seconds,
                        R_gt,
                        t_gt,
                        R,
                        t,
                        best is not None,
                        K,
                        None,
                        truth.boxes.get((stamp, name), (0, 0, 0, 0)),
                    )
                )
    objects = [o for o in node.estimator.config.objects if o.name in node.published.values()]
    settings = node.settings()
    used = {"ddim_steps": settings.ddim_steps, "hypotheses": settings.hypotheses, "precision": node.precision,
            "mode": settings.mode, "redetect_period": settings.redetect_period,
            "measure_every": settings.measure_every, "refine": settings.refine and node.estimator.refiner is not None}  # fmt: skip
    report = summarize(records, objects, config | used)
    modes = {k[len("mode_") :]: n for k, n in counts.items() if k.startswith("mode_")}  # frames run in each mode
    report["tracking"] = {"modes": modes, **_jitter(records, syms)}
    lat = np.array(list(latency.values())) if latency else np.zeros(1)
    report["frame_latency_ms"] = {"median": float(np.median(lat)), "p90": float(np.percentile(lat, 90))}
    own = 1000 * np.array(node.stats.latency or [0.0])  # the node's own (its last frames): received to all published
    report["node_frame_ms"] = {"median": float(np.median(own)), "p90": float(np.percentile(own, 90)), "frames": len(node.stats.latency)}
    report["counts"] = counts
    return report
