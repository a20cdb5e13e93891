"""Pose accuracy of AGM checkpoints over DDIM steps and run-time guidance, on held-out BOP scenes (GT crops).

Each row is (checkpoint label, steps, guidance scale) through `axispose_core.evaluate` (the code `axispose eval`
runs): ADD(-S)@0.1d, ADD(-S)@0.2d, Reproj@5/15 px, median rotation/translation error, ms per object.
Used for the L_geo ablation (checkpoints trained with and without it, inference guidance on and off) and for
choosing the default number of steps.

    python bench/agm_grid.py --checkpoint nogeo=runs/ablation/nogeo_12min.safetensors \\
        --checkpoint geo=runs/ablation/geo_12min.safetensors --guided geo --steps 1 2 4 8 16 50 \\
        --data data/lmo_val --models ../shared/data/lmo/models_eval --limit 60 --json bench/results/agm_ablation.json
"""

from __future__ import annotations

import argparse
import platform
import time

import torch
from write_results import write_results

from axispose_core.estimator import EstimateOptions, Estimator
from axispose_core.evaluate import EvalOptions, Prediction, evaluate, summarize

KEYS = ("add_0.1d", "add_0.2d", "reproj_5px", "reproj_15px", "rot_err_median_deg", "trans_err_median_mm")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoint", action="append", required=True, help="LABEL=PATH (repeatable)")
    ap.add_argument("--guided", nargs="*", default=[], help="labels also evaluated with run-time guidance")
    ap.add_argument("--guidance-scale", type=float, default=1.0)
    ap.add_argument("--steps", type=int, nargs="+", default=[1, 2, 4, 8, 16, 50])
    ap.add_argument("--data", required=True)
    ap.add_argument("--models", required=True)
    ap.add_argument("--limit", type=int, default=60, help="instances per row (the same ones in every row)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--json", default="bench/results/agm_grid.json")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    rows = []
    for item in args.checkpoint:
        label, _, path = item.partition("=")
        est = Estimator.load(path)
        objects = list(est.config.objects)
        for guidance in [0.0] + ([args.guidance_scale] if label in args.guided else []):
            for steps in args.steps:

                def predict(image, K, boxes, est=est, steps=steps, guidance=guidance):
                    poses = est.estimate(image, K, boxes, EstimateOptions(steps=steps, guidance_scale=guidance))
                    return [Prediction(p.R, p.t, p.ok) for p in poses]

                records = evaluate(predict, args.data, args.models, objects, EvalOptions(limit=args.limit, progress=False)).records
                report = summarize(records, objects, {})
                row = {"model": label, "steps": steps, "guidance": guidance, "n": len(records)} | {k: report["mean"][k] for k in KEYS}
                row["ms_per_object"] = report["ms_per_object"]["median"]
                rows.append(row)
                print(
                    f"{label:<10} steps {steps:>3} guid {guidance:>3g}  ADD.1d {row['add_0.1d']:.3f}  ADD.2d {row['add_0.2d']:.3f}  "
                    f"Rep5 {row['reproj_5px']:.3f}  Rep15 {row['reproj_15px']:.3f}  rot {row['rot_err_median_deg']:6.1f}  "
                    f"t {row['trans_err_median_mm']:7.1f} mm  {row['ms_per_object']:6.1f} ms/obj",
                    flush=True,
                )
    out = {"machine": platform.processor() or platform.machine(), "threads": args.threads, "date": time.strftime("%Y-%m-%d"),
           "data": args.data, "limit": args.limit, "rows": rows}  # fmt: skip
    write_results(args.json, out)


if __name__ == "__main__":
    main()
