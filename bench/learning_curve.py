"""Plot the learning curves `axispose train` logs (OUT.csv): held-out metrics against crops seen and against
training wall time, for one run or several side by side.

A resumed run appends to the same CSV and restarts its clock, so wall time is summed over the calls.

    python bench/learning_curve.py runs/agm.csv --out docs/agm_learning_curve.png --json bench/results/agm_learning_curve.json

`--at-hours H` summarises every run at the same wall time (linear between its validations) instead of at its
last validation: the equal-time comparison of designs.
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt
from write_results import write_results

PANELS = (
    ("val_loss", "diffusion loss"),
    ("val_points_err", "surface-point error (object radii)"),
    ("val_rot_median_deg", "median rotation error (°)"),
    ("val_rot_within_15deg", "share within 15°"),
    ("val_kp_err_px", "reader keypoint error (px)"),
    ("val_depth_head", "encoder |relative depth error|"),
)


def read_curve(path: str | Path) -> dict[str, list[float]]:
    """The validation rows of a trainer CSV: step, samples seen ("crops" in CSVs of older versions), cumulative
    wall hours and every PANELS column present."""
    rows = list(csv.DictReader(open(path, newline="")))
    out: dict[str, list[float]] = {"step": [], "crops": [], "hours": []}
    offset, last = 0.0, 0.0
    for row in rows:
        seconds = float(row["seconds"])
        if seconds < last:  # a resumed call: its clock started again
            offset += last
        last = seconds
        if not row.get("val_rot_median_deg"):
            continue
        out["step"].append(int(row["step"]))
        out["crops"].append(int(row.get("samples") or row.get("crops") or 0))
        out["hours"].append((offset + seconds) / 3600)
        for key, _ in PANELS:
            if row.get(key):
                out.setdefault(key, []).append(float(row[key]))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("csv", nargs="+", help="trainer CSVs (OUT.csv of `axispose train`)")
    ap.add_argument("--out", required=True, help="PNG to write")
    ap.add_argument("--json", default=None, help="JSON with each run's summary row (its last validation, or at --at-hours)")
    ap.add_argument("--at-hours", type=float, default=None, help="summarise every run at this wall time instead")
    args = ap.parse_args()
    curves = {Path(p).stem: read_curve(p) for p in args.csv}
    fig, axes = plt.subplots(2, len(PANELS), figsize=(4 * len(PANELS), 6.5), squeeze=False)
    for name, c in curves.items():
        for j, (key, label) in enumerate(PANELS):
            if key not in c:
                continue
            for i, x in enumerate(("crops", "hours")):
                axes[i][j].plot([v / 1e6 for v in c[x]] if x == "crops" else c[x], c[key], label=name, lw=1)
                axes[i][j].set_xlabel("crops seen (millions)" if x == "crops" else "training wall time (h)")
                axes[i][j].set_ylabel(label)
                axes[i][j].grid(alpha=0.3)
    axes[0][0].legend()
    fig.tight_layout()
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=90)
    if args.at_hours is None:
        summary = {name: {k: v[-1] for k, v in c.items() if v} for name, c in curves.items()}
    else:  # runs that never reached that time have no row
        h = args.at_hours
        reached = {name: c for name, c in curves.items() if c["hours"] and c["hours"][-1] >= h}
        summary = {name: {k: float(np.interp(h, c["hours"], v)) for k, v in c.items() if v} for name, c in reached.items()}
    print(f"{'run':<16}{'step':>8}{'hours':>8}" + "".join(f"{k[4:]:>20}" for k, _ in PANELS))
    for name, last in summary.items():
        cells = "".join(f"{last.get(k, float('nan')):>20.3f}" for k, _ in PANELS)
        print(f"{name:<16}{last['step']:>8.0f}{last['hours']:>8.2f}{cells}")
    if args.json:
        write_results(args.json, summary)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
