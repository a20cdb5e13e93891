"""How an evaluation's report is shown: its tables, its JSON file and its plots (error CDFs, a grid of crops with
the GT and predicted boxes, error against uncertainty)."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from axispose_core.axis_image import draw_axes
from axispose_core.camera import crop_image, crop_intrinsics, square_around_box
from axispose_core.data.bop import read_bgr
from axispose_core.data.bop_models import model_path
from axispose_core.data.meshes import load_ply
from axispose_core.evaluation.records import Record
from axispose_core.evaluation.summary import posed_with
from axispose_core.objects import ObjectSpec

_LABELS = {"spread_deg": "spread of the samples (deg, RMS)", "sigma_deg": "rotation sigma of the covariance (deg)"}


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


def plot_uncertainty(records: list[Record], out_dir: str | Path, key: str) -> Path | None:
    """Rotation error against an uncertainty (`key`), and accuracy when only the least uncertain fraction is kept."""
    rs, u = posed_with(records, key)
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
