"""The twin check: a checkpoint on real frames and on their rendered twins, side by side, per object.

The twins (`axispose_core/data/twins.py`) keep the real background, clutter, camera, poses and framing, and swap
the annotated objects' look for the project's renders. What a checkpoint gains on the twins over the frames is
what the objects' real appearance costs it; what it still misses on the twins comes from the scene (background,
clutter, occlusion, framing). Both passes run `axispose validate`'s settings (GT crops and the localiser).

    python bench/real_twins.py [--checkpoint CKPT] [--data ../shared/data/lmo_real_val/test] [--out out/twins]

Writes OUT/twins/ (the twin split, reused on later calls), OUT/real.json, OUT/twins.json and OUT/table.txt.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from axispose_core.data.twins import write_twins
from axispose_core.estimator import SHIPPED_ESTIMATOR
from axispose_core.lmo import REAL_SLICE, SHARED_LMO
from axispose_core.validation import COLUMNS, ValidationSettings, format_cell, report_value, validate


def table(real: dict, twins: dict) -> str:
    """`axispose validate`'s columns, means real | twins, then per object the GT crops' Reproj@15px and rotation
    median, and the localiser's recall."""
    lines = [f"{'':<12} {'real':>8} {'twins':>8}"]
    for name, crops, key, fmt in COLUMNS:
        cells = [format_cell(report_value(report, crops, key), fmt) for report in (real, twins)]
        lines.append(f"{name:<12} {cells[0]:>8} {cells[1]:>8}")
    lines.append("")
    lines.append(f"{'object':<12} {'Rp15 real':>9} {'twins':>6} {'rot real':>9} {'twins':>6} {'det R real':>10} {'twins':>6}")
    for obj, entry in real["gt"]["objects"].items():
        cells = []
        for crops, key, fmt in (("gt", "reproj_15px", ".3f"), ("gt", "rot_err_median_deg", ".1f"), ("detect", "det_recall", ".2f")):
            cells += [format_cell(report_value(real, crops, key, obj), fmt), format_cell(report_value(twins, crops, key, obj), fmt)]
        lines.append(f"{entry['name']:<12} {cells[0]:>9} {cells[1]:>6} {cells[2]:>9} {cells[3]:>6} {cells[4]:>10} {cells[5]:>6}")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--checkpoint", default=str(SHIPPED_ESTIMATOR))
    ap.add_argument("--data", default=str(REAL_SLICE), help="a BOP split of real frames (default: the real validation slice)")
    ap.add_argument("--models", default=str(SHARED_LMO / "models"), help="full-resolution models: the twins' renders")
    ap.add_argument("--eval-models", default=str(SHARED_LMO / "models_eval"), help="models the metrics and visibility use")
    ap.add_argument("--out", default="out/twins")
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    out = Path(args.out)
    twins_split = write_twins(args.data, args.models, out / "twins")
    settings = ValidationSettings()
    reports = {}
    for name, data in (("real", args.data), ("twins", twins_split)):
        reports[name] = validate(args.checkpoint, data, args.eval_models, settings)
        (out / f"{name}.json").write_text(json.dumps(reports[name], indent=1))
    text = table(reports["real"], reports["twins"])
    (out / "table.txt").write_text(text + "\n")
    print(text)


if __name__ == "__main__":
    main()
