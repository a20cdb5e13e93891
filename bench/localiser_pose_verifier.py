"""Does the pose the estimator finds for a detection tell a real object from a false alarm? Every detection down to
--min-score is posed as the node poses it (1 sample, 3 steps, float32), and described by the localiser's score and
two signals of the pose: the rotation and translation variance of the dense fusion's covariance (a crop whose
points do not fit the object's model gets a wide one). The verifier (`axispose_core/localiser/verifier.py`) is fitted
on the synthetic frames (--fit) only, as `axispose fit-verifier` fits it, and read on every set: each signal's AUC,
the average precision of the score alone and of the verifier's probability, and recall / precision at the node's
threshold 0.3 on either, and where the probability's threshold gives the fit set the recall of score >= 0.3.

    python bench/localiser_pose_verifier.py --checkpoint EST --fit data/lmo_val \
        --data ../shared/data/lmo_real_val/test HELDOUT/test --json bench/results/localiser_pose_verifier.json
"""

from __future__ import annotations

import argparse

import numpy as np
from node_estimator import add_common_arguments, node_estimator
from scipy.stats import rankdata
from write_results import write_results

from axispose_core.data.bop_scene import bop_frames
from axispose_core.data.visibility import gt_info_from_models
from axispose_core.localiser.decode import Detection
from axispose_core.localiser.scoring import Instance, detection_outcomes, frame_instances, tally
from axispose_core.localiser.verifier import FEATURES, fit
from axispose_core.train.verifier import pose_signals

SIGNS = (1, -1, -1)
"""Which way each of `FEATURES` points to a hit (for its AUC)."""

Frame = tuple[list[Detection], list[Instance], np.ndarray]
"""A frame's detections, its instances and one feature row per detection."""


def labels(frames: list[Frame], min_visib: float) -> np.ndarray:
    """Per detection: 1 hit, 0 false alarm, -1 neither (it found an instance less visible than `min_visib`)."""
    return np.array([o for dets, insts, _ in frames for o in detection_outcomes(dets, insts, min_visib)], int)


def auc(y: np.ndarray, x: np.ndarray) -> float:
    """Area under the ROC curve of x separating y == 1 from y == 0 (Mann-Whitney)."""
    r, n1 = rankdata(x), int(y.sum())
    return float((r[y == 1].sum() - n1 * (n1 + 1) / 2) / (n1 * (len(y) - n1)))


def kept(frames: list[Frame], z: np.ndarray, threshold: float) -> list[tuple[list[Detection], list[Instance]]]:
    """The frames with only the detections whose combined value `z` reaches `threshold`."""
    out, start = [], 0
    for dets, insts, _ in frames:
        zs = z[start : start + len(dets)]
        out.append(([d for d, v in zip(dets, zs, strict=True) if v >= threshold], insts))
        start += len(dets)
    return out


def recall_precision(frames: list[Frame], z: np.ndarray, threshold: float, ids: tuple[int, ...], min_visib: float) -> tuple[float, float]:
    """(recall, precision) over all instances of the detections whose `z` reaches `threshold` (pooled, `tally`)."""
    scores = tally(kept(frames, z, threshold), ids, min_visib)
    return scores["recall"], scores["precision"]


def average_precision(frames: list[Frame], z: np.ndarray, ids: tuple[int, ...], min_visib: float) -> float:
    """Area under the recall / precision curve swept over every threshold (rectangles, as sklearn's)."""
    points = [recall_precision(frames, z, t, ids, min_visib) for t in np.unique(z)[::-1]]
    recalls = np.array([0.0] + [r for r, _ in points])
    return float(np.sum(np.diff(recalls) * np.array([p for _, p in points])))


def summary(result: dict) -> str:
    """One line of a set's result."""
    pairs = {k: result[k] for k in ("score_0.3", "combined_0.3", "combined_at_fit_recall")}
    points = "; ".join(f"{k} {r:.3f} / {p:.3f}" for k, (r, p) in pairs.items())
    aucs = ", ".join(f"{n} {v:.3f}" for n, v in result["auc"].items())
    ap = result["average_precision"]
    return f"AP {ap['score']:.3f} -> {ap['combined']:.3f}; recall / precision {points}; AUC {aucs}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_common_arguments(ap, "visibility from these models")
    ap.add_argument("--fit", required=True, help="synthetic BOP frames the logistic model is fitted on")
    ap.add_argument("--data", nargs="+", required=True, help="BOP frame folders it is read on")
    ap.add_argument("--min-score", type=float, default=0.2, help="detections down to this score are posed")
    args = ap.parse_args()
    est = node_estimator(args)
    ids = tuple(o.obj_id for o in est.config.objects)
    info = gt_info_from_models(args.models)
    frames: dict[str, list[Frame]] = {}
    for path in [args.fit, *args.data]:
        frames[path] = []
        for scene, im_id in bop_frames([path], info):
            rgb, K = scene.rgb(im_id), scene.cameras[im_id]
            dets = est.detect(rgb, args.min_score)
            rows = pose_signals(est, rgb, K, dets, 3)
            frames[path].append((dets, frame_instances(scene, im_id, ids), rows))
        print(f"{path}: {sum(len(d) for d, _, _ in frames[path])} detections", flush=True)
    rows = {k: np.concatenate([r for _, _, r in v]) for k, v in frames.items()}
    y = {k: labels(v, args.min_visib) for k, v in frames.items()}
    fit_rows, fit_y = rows[args.fit], y[args.fit]
    counted = fit_y >= 0
    verifier = fit(fit_rows[counted], fit_y[counted], args.min_score)
    z = {k: verifier.probability(r) for k, r in rows.items()}
    # Beside the node's threshold, the probability's that gives the fit set the recall of score >= 0.3.
    base_recall, _ = recall_precision(frames[args.fit], rows[args.fit][:, 0], 0.3, ids, args.min_visib)
    at_fit = [(t, *recall_precision(frames[args.fit], z[args.fit], t, ids, args.min_visib)) for t in np.unique(z[args.fit])]
    t_recall = min(at_fit, key=lambda a: (abs(a[1] - base_recall), -a[2]))[0]
    out = {
        "checkpoint": args.checkpoint,
        "fit": args.fit,
        "min_score": args.min_score,
        "weights": dict(zip([*FEATURES, "constant"], verifier.weights, strict=True)),
        "sets": {},
    }
    for k in frames:
        c = y[k] >= 0
        result = {
            "detections": len(y[k]),
            "auc": {n: auc(y[k][c], SIGNS[j] * rows[k][c, j]) for j, n in enumerate(FEATURES)} | {"combined": auc(y[k][c], z[k][c])},
            "average_precision": {"score": average_precision(frames[k], rows[k][:, 0], ids, args.min_visib),
                                  "combined": average_precision(frames[k], z[k], ids, args.min_visib)},
            "score_0.3": recall_precision(frames[k], rows[k][:, 0], 0.3, ids, args.min_visib),
            "combined_0.3": recall_precision(frames[k], z[k], 0.3, ids, args.min_visib),
            "combined_at_fit_recall": recall_precision(frames[k], z[k], t_recall, ids, args.min_visib),
        }  # fmt: skip
        out["sets"][k] = result
        print(f"{k}: {summary(result)}", flush=True)
    if args.json:
        write_results(args.json, out)


if __name__ == "__main__":
    main()
