"""Where the pose error of a checkpoint comes from: rotation, or depth along the viewing ray, or across it.

Runs `axispose_core.evaluation.run.evaluate` with GT crops (the code `axispose eval` runs) and splits each posed
instance's translation error into its part along the camera's z axis and the part across it. For the
instances whose rotation is within `--rot-ok` degrees it asks what ADD(-S)@0.1d would be if depth were right:
once with the true depth (an oracle), and once with the depth that makes the object model's projected box
as large as the crop's box (which needs the mesh at run time, so the model-free estimator does not do it).

Depth sources: the poses are estimated with head_depth_weight 0 (the TBM's depth from the drawn axis lengths),
and each instance's encoder depth (`PoseEstimate.head_depth`) is kept, so one run scores the TBM's depth, the
encoder's, and their fusion at every weight in `--weights` on the same rotations: the table that sets the
checkpoint's head_depth_weight (choose it on validation frames, not on the test set). Two more sources read the
encoder's dense surface points (model coordinates in λ_O units at half the crop's resolution, where its mask is
above 0.5): "dense", t solved from them with the TBM's rotation (`tbm/dense.py`); "PnP", rotation and
translation from the same correspondences by OpenCV's EPnP in RANSAC; and "fused", the estimator's own pose
(`fuse_pose` with the checkpoint's dense_fusion: R and t from the points with the TBM's rotation and origin and
the encoder's depth as priors). Their rotation errors and the fused pose's ADD(-S)@0.1d are printed too. One more
oracle, "exact, fused R": t solved from the model's vertices at their true projections with the fused rotation,
scored as that pose: the depth a dense output as precise as the model would give with the estimator's rotation.
Last, the correlation of the head's and the dense points' log depth errors and their best fixed blend.

    python bench/agm_error_sources.py --checkpoint axispose_core/models/axispose_lmo.safetensors \\
        --data data/lmo_val --models ../shared/data/lmo/models_eval --json bench/results/agm_error_sources.json
"""

from __future__ import annotations

import argparse
import dataclasses
import platform
import time

import cv2
import numpy as np
import torch
from write_results import write_results

from axispose_core.agm.correspondences import dense_correspondences
from axispose_core.camera import project_model
from axispose_core.data.bop_models import model_path
from axispose_core.data.meshes import load_ply
from axispose_core.estimator import EstimateOptions, Estimator
from axispose_core.estimator_stages import crop_batch, fuse_depth
from axispose_core.evaluation.records import Prediction
from axispose_core.evaluation.run import evaluate
from axispose_core.metrics import add_or_adi, re
from axispose_core.tbm.dense import DensePoints, fuse_pose, translation_from_points

BANDS = ((0.1, 0.5), (0.5, 0.8), (0.8, 1.0))
"""Visible-fraction bands the depth errors are split by."""


def box_side(R: np.ndarray, t: np.ndarray, K: np.ndarray, pts: np.ndarray) -> float:
    """sqrt(width * height) of the model's projected bounding box."""
    q = project_model(K, R, t, pts)
    w, h = q.max(0) - q.min(0)
    return float(np.sqrt(w * h))


def depth_from_box(R: np.ndarray, t: np.ndarray, K: np.ndarray, pts: np.ndarray, box: tuple[float, ...], iters: int = 5) -> np.ndarray:
    """t moved along its ray until the projected model's box side matches the observed box's (fixed point)."""
    observed = float(np.sqrt(box[2] * box[3]))
    for _ in range(iters):
        t = t * box_side(R, t, K, pts) / observed
    return t


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoint", required=True)
    ap.add_argument("--data", required=True)
    ap.add_argument("--models", required=True, help="BOP models_eval folder")
    ap.add_argument("--steps", type=int, default=None)
    ap.add_argument("--rot-ok", type=float, default=15.0, help="rotation error (deg) under which the rotation counts as right")
    ap.add_argument("--weights", default="0,0.25,0.5,0.75,0.9,1", help="head_depth_weight values to score (comma-separated)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--json", default="bench/results/agm_error_sources.json")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    est = Estimator.load(args.checkpoint)
    shipped = est.config
    # t is the TBM's (the encoder's depth rides along), R the TBM's consensus: each source is scored on the same poses
    est.config = dataclasses.replace(est.config, head_depth_weight=0.0, dense_fusion=dataclasses.replace(shipped.dense_fusion, points=0.0))
    objects = list(est.config.objects)
    head_depths: list[float] = []
    dense: list[tuple] = []  # per record: dense z, PnP z, PnP rotation, the dense fusion's z and rotation
    S = est.size

    def predict(image: np.ndarray, K: np.ndarray, boxes: list) -> list[Prediction]:
        poses = est.estimate(image, K, boxes, EstimateOptions(steps=args.steps))
        head_depths.extend(p.head_depth for p in poses)
        cuts, x = crop_batch(image, K, boxes, est.objects, S, est.config.crop_pad)
        with torch.inference_mode():
            enc = est.agm.encode(x, torch.tensor([est.index[o] for o, _ in boxes], dtype=torch.long))
        scales = np.array([est.objects[o].scale for o, _ in boxes])
        for p, cut, (uv, X, w) in zip(poses, cuts, dense_correspondences(enc, scales), strict=True):
            t_dense = translation_from_points(cut.K_patch, p.R, uv, X, w) if p.ok else None
            z_pnp, R_pnp = float("nan"), None
            if len(uv) >= 6:
                ok, rvec, tvec, _ = cv2.solvePnPRansac(X, uv, cut.K_patch, None, flags=cv2.SOLVEPNP_EPNP,
                                                       reprojectionError=2.0, iterationsCount=200)  # fmt: skip
                if ok and tvec[2, 0] > 0:
                    z_pnp, R_pnp = float(tvec[2, 0]), cv2.Rodrigues(rvec)[0]
            # The estimator's pose: from the TBM's and the fused depth, solved with the dense points and both as priors
            # (the crop's frame is the image's: K_patch only moves and scales the pixels).
            start = fuse_depth(p.t, p.head_depth, shipped.head_depth_weight)
            fused = fuse_pose(cut.K_patch, p.R, start, DensePoints(uv, X, w), p.head_depth, shipped.dense_fusion) if p.ok else None
            z_fus, R_fus = (float(fused[1][2]), fused[0]) if fused is not None else (float("nan"), None)
            dense.append((float(t_dense[2]) if t_dense is not None and t_dense[2] > 0 else float("nan"), z_pnp, R_pnp, z_fus, R_fus))
        return [Prediction(p.R, p.t, p.ok) for p in poses]

    records = evaluate(predict, args.data, args.models, objects).records
    assert len(head_depths) == len(records)  # GT crops: one prediction per record, in order
    weights = [float(w) for w in args.weights.split(",")]
    specs = {o.obj_id: o for o in objects}
    points = {i: load_ply(model_path(args.models, i)).vertices for i in specs}
    rows = []
    posed = ((r, z, d) for r, z, d in zip(records, head_depths, dense, strict=True) if r.ok)
    for r, z_head, (z_dense, z_pnp, R_pnp, z_fus, R_fus) in posed:
        spec, pts = specs[r.obj_id], points[r.obj_id]
        d = r.t - r.t_gt
        thr = 0.1 * spec.diameter
        oracle = r.t * (r.t_gt[2] / r.t[2])  # the same ray, the true depth
        rows.append({
            "rot_err_deg": r.scores["rot_err_deg"],
            "depth_err_mm": 1000 * abs(d[2]),
            "lateral_err_mm": 1000 * float(np.hypot(d[0], d[1])),
            "rel_depth_err": abs(d[2]) / r.t_gt[2],
            "add_ok": r.scores["add_0.1d"] == 1.0,
            "add_ok_true_depth": add_or_adi(r.R, oracle, r.R_gt, r.t_gt, pts, spec.symmetric) < thr,
            "add_ok_box_depth": add_or_adi(r.R, depth_from_box(r.R, r.t, r.K, pts, r.box), r.R_gt, r.t_gt, pts, spec.symmetric) < thr,
            "log_depth_err_tbm": float(np.log(r.t[2] / r.t_gt[2])),
            "log_depth_err_head": float(np.log(z_head / r.t_gt[2])),
            "log_depth_err_dense": float(np.log(z_dense / r.t_gt[2])),
            "log_depth_err_pnp": float(np.log(z_pnp / r.t_gt[2])),
            "rot_err_pnp_deg": re(R_pnp, r.R_gt) if R_pnp is not None else 180.0,
            "log_depth_err_fused": float(np.log(z_fus / r.t_gt[2])),
            "rot_err_fused_deg": re(R_fus, r.R_gt) if R_fus is not None else 180.0,
            "visib_fract": r.visib_fract,
        })  # fmt: skip
        for w in weights:
            t_w = fuse_depth(r.t, z_head, w)
            rows[-1][f"add_ok_w{w:g}"] = add_or_adi(r.R, t_w, r.R_gt, r.t_gt, pts, spec.symmetric) < thr
        if R_fus is not None:  # the dense fusion's pose as it is, rotation and translation
            t_fus = r.t * (z_fus / r.t[2])
            rows[-1]["add_ok_fused_pose"] = add_or_adi(R_fus, t_fus, r.R_gt, r.t_gt, pts, spec.symmetric) < thr
        else:
            rows[-1]["add_ok_fused_pose"] = False
        # An oracle: t from exact correspondences (the model's vertices at their true projections) under the dense
        # fusion's own rotation, as its pose: what a dense output as good as the model would give with that R.
        t_con = None
        if R_fus is not None:
            t_con = translation_from_points(r.K, R_fus, project_model(r.K, r.R_gt, r.t_gt, pts), pts, np.ones(len(pts)))
        rows[-1]["log_depth_err_consistent"] = float(np.log(t_con[2] / r.t_gt[2])) if t_con is not None and t_con[2] > 0 else float("nan")
        rows[-1]["add_ok_consistent"] = t_con is not None and add_or_adi(R_fus, t_con, r.R_gt, r.t_gt, pts, spec.symmetric) < thr
        for name, z in (("dense", z_dense), ("pnp", z_pnp), ("fused", z_fus)):  # that depth on the TBM's ray, as the head's is used
            rows[-1][f"add_ok_{name}"] = (
                bool(np.isfinite(z)) and add_or_adi(r.R, fuse_depth(r.t, z, 1.0), r.R_gt, r.t_gt, pts, spec.symmetric) < thr
            )
    n = len(records)

    def summary(sel: list[dict]) -> dict:
        if not sel:
            return {"n": 0}
        col = {k: np.array([s[k] for s in sel], dtype=float) for k in sel[0]}
        return {
            "n": len(sel),
            "depth_err_mm_median": float(np.median(col["depth_err_mm"])),
            "lateral_err_mm_median": float(np.median(col["lateral_err_mm"])),
            "rel_depth_err_quartiles": [float(q) for q in np.percentile(col["rel_depth_err"], [25, 50, 75])],
            "add_0.1d": float(col["add_ok"].mean()),
            "add_0.1d_true_depth": float(col["add_ok_true_depth"].mean()),
            "add_0.1d_box_depth": float(col["add_ok_box_depth"].mean()),
        }

    right = [s for s in rows if s["rot_err_deg"] < args.rot_ok]
    out = {
        "machine": platform.processor() or platform.machine(), "date": time.strftime("%Y-%m-%d"), "checkpoint": args.checkpoint,
        "data": args.data, "instances": n, "posed": len(rows), "rot_ok_deg": args.rot_ok,
        "all_posed": summary(rows), "rotation_right": summary(right),
        "add_0.1d_of_all": {k: sum(s[k] for s in rows) / n for k in ("add_ok", "add_ok_true_depth", "add_ok_box_depth")},
    }  # fmt: skip
    print(f"{n} instances, {len(rows)} posed, {len(right)} with rotation error < {args.rot_ok:g} deg")
    print(f"{'':<22}{'n':>5}{'depth mm':>10}{'across mm':>11}{'rel. depth':>12}{'ADD0.1d':>9}{'true z':>8}{'box z':>7}")
    for name, s in (("all posed", out["all_posed"]), ("rotation right", out["rotation_right"])):
        if s["n"]:
            print(f"{name:<22}{s['n']:>5}{s['depth_err_mm_median']:>10.1f}{s['lateral_err_mm_median']:>11.1f}"
                  f"{s['rel_depth_err_quartiles'][1]:>12.3f}{s['add_0.1d']:>9.3f}{s['add_0.1d_true_depth']:>8.3f}"
                  f"{s['add_0.1d_box_depth']:>7.3f}")  # fmt: skip
    a = out["add_0.1d_of_all"]
    print(f"ADD(-S)@0.1d of all {n}: {a['add_ok']:.3f}; with the true depth {a['add_ok_true_depth']:.3f}; "
          f"with depth from the box {a['add_ok_box_depth']:.3f}")  # fmt: skip
    e_tbm = np.array([s["log_depth_err_tbm"] for s in rows])
    e_head = np.array([s["log_depth_err_head"] for s in rows])
    visib = np.array([s["visib_fract"] for s in rows])
    out["depth_sources"] = []
    print(f"\ndepth sources on the {len(rows)} posed instances (|relative depth error| quartiles; bias: the median ratio of "
          f"estimated to true depth; ADD(-S)@0.1d of all {n}; median |error| by visible fraction):")  # fmt: skip
    print(
        f"{'head_depth_weight':<20}{'q25':>8}{'median':>8}{'q75':>8}{'bias':>8}{'ADD0.1d':>9}"
        + "".join(f"{f'{a:g}-{b:g}':>9}" for a, b in BANDS)
    )
    for w in weights:
        log_err = (1 - w) * e_tbm + w * e_head  # fused log depth = (1-w) log z_tbm + w log z_head
        e = np.abs(np.expm1(log_err))
        q = [float(v) for v in np.percentile(e, [25, 50, 75])]
        bias = float(np.exp(np.median(log_err)))
        add = sum(s[f"add_ok_w{w:g}"] for s in rows) / n
        bands = {f"{a:g}-{b:g}": float(np.median(e[(visib >= a) & (visib <= b)])) if np.any((visib >= a) & (visib <= b)) else None
                 for a, b in BANDS}  # fmt: skip
        out["depth_sources"].append({"head_depth_weight": w, "rel_depth_err_quartiles": q, "bias": bias, "add_0.1d_of_all": add,
                                     "median_rel_depth_err_by_visib": bands})  # fmt: skip
        label = {0.0: "0 (TBM alone)", 1.0: "1 (encoder alone)"}.get(w, f"{w:g}")
        cells = "".join(f"{v:>9.3f}" if v is not None else f"{'-':>9}" for v in bands.values())
        print(f"{label:<20}{q[0]:>8.3f}{q[1]:>8.3f}{q[2]:>8.3f}{bias:>8.3f}{add:>9.3f}{cells}")
    for name, label in (
        ("dense", "dense points + R"),
        ("pnp", "PnP (EPnP, RANSAC)"),
        ("fused", "dense fusion (R, t)"),
        ("consistent", "exact, fused R"),
    ):
        log_err = np.array([s[f"log_depth_err_{name}"] for s in rows])
        found = np.isfinite(log_err)
        e = np.abs(np.expm1(log_err[found]))
        q = [float(v) for v in np.percentile(e, [25, 50, 75])] if found.any() else [float("nan")] * 3
        bias = float(np.exp(np.median(log_err[found]))) if found.any() else float("nan")
        add = sum(s[f"add_ok_{name}"] for s in rows) / n
        vis = visib[found]
        bands = {f"{a:g}-{b:g}": float(np.median(e[(vis >= a) & (vis <= b)])) if np.any((vis >= a) & (vis <= b)) else None
                 for a, b in BANDS}  # fmt: skip
        out["depth_sources"].append({"source": name, "solved": int(found.sum()), "rel_depth_err_quartiles": q, "bias": bias,
                                     "add_0.1d_of_all": add, "median_rel_depth_err_by_visib": bands})  # fmt: skip
        cells = "".join(f"{v:>9.3f}" if v is not None else f"{'-':>9}" for v in bands.values())
        print(f"{label:<20}{q[0]:>8.3f}{q[1]:>8.3f}{q[2]:>8.3f}{bias:>8.3f}{add:>9.3f}{cells}   ({int(found.sum())} solved)")
    out["rot_err_pnp_median_deg"] = float(np.median([s["rot_err_pnp_deg"] for s in rows]))
    out["rot_err_fused_median_deg"] = float(np.median([s["rot_err_fused_deg"] for s in rows]))
    out["add_0.1d_fused_pose"] = sum(s["add_ok_fused_pose"] for s in rows) / n
    print(f"own rotations: PnP median error {out['rot_err_pnp_median_deg']:.1f} deg, dense fusion "
          f"{out['rot_err_fused_median_deg']:.1f} deg (the TBM's: {np.median([s['rot_err_deg'] for s in rows]):.1f} deg); "
          f"the dense fusion pose's ADD(-S)@0.1d "
          f"{out['add_0.1d_fused_pose']:.3f}")  # fmt: skip
    out["log_depth_err_std"] = {"tbm": float(np.std(e_tbm)), "head": float(np.std(e_head)),
                                "correlation": float(np.corrcoef(e_tbm, e_head)[0, 1])}  # fmt: skip
    print("log depth error std: TBM {tbm:.3f}, encoder {head:.3f}, correlation {correlation:.2f}".format(**out["log_depth_err_std"]))
    # Whether the head and the dense points err independently, and what the best fixed blend of their log depths
    # reads: how much any fusion of the two could gain over the head alone.
    e_dense = np.array([s["log_depth_err_dense"] for s in rows])
    both = np.isfinite(e_dense)
    blends = {float(w): float(np.median(np.abs(np.expm1(w * e_head[both] + (1 - w) * e_dense[both])))) for w in np.linspace(0, 1, 21)}
    w_best = min(blends, key=blends.__getitem__)
    out["head_and_dense"] = {"correlation": float(np.corrcoef(e_head[both], e_dense[both])[0, 1]), "best_head_weight": w_best,
                             "best_blend_median": blends[w_best], "head_median": blends[1.0]}  # fmt: skip
    print(
        "head and dense points: log error correlation {correlation:.2f}; their best fixed blend, head weight "
        "{best_head_weight:.2f}, reads {best_blend_median:.3f} against the head's {head_median:.3f}".format(**out["head_and_dense"])
    )
    write_results(args.json, out)


if __name__ == "__main__":
    main()
