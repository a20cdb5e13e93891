"""Cube-corner solver under Gaussian keypoint noise, over the LM-O pose range in the full 640x480 image.

Prints a table and writes JSON: median/p90 rotation and translation errors and the refusal rate, for the
analytic solution and with the re-projection refinement; the time per solve one at a time, and with refinement
also per solve when all of them go through `backproject_many` at once (as the estimator's hypotheses do).

    python bench/solver_noise.py --poses 1000 --json bench/results/solver_noise.json
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from tqdm import tqdm
from write_results import write_results

from axispose_core.axis_image import AxisSpec, axis_keypoints
from axispose_core.lmo import LMO_DIAMETERS, LMO_K
from axispose_core.metrics import re, te
from axispose_core.pose_sampling import sample_pose
from axispose_core.tbm.backproject import backproject, backproject_many


def run(poses: int, sigmas: list[float], seed: int) -> list[dict]:
    rows = []
    diameters = np.array(list(LMO_DIAMETERS.values()))
    for sigma in sigmas:
        rng = np.random.default_rng(seed)
        for refine in (False, True):
            rot, trans, refused, secs, batch = [], [], 0, [], []
            for _ in tqdm(range(poses), desc=f"sigma={sigma} refine={refine}", leave=False):
                R, t = sample_pose(rng)
                lengths = AxisSpec.from_diameter(rng.choice(diameters)).lengths
                kp = axis_keypoints(LMO_K, R, t, lengths) + rng.normal(0.0, sigma, (4, 2))
                start = time.perf_counter()
                res = backproject(LMO_K, kp[0], kp[1:], lengths, refine=refine)
                secs.append(time.perf_counter() - start)
                batch.append((kp, lengths))
                if not res.ok:
                    refused += 1
                    continue
                rot.append(re(res.R, R))
                trans.append(1000 * te(res.t, t))
            start = time.perf_counter()
            backproject_many(
                np.repeat(LMO_K[None], poses, axis=0), np.stack([b[0] for b in batch]), np.stack([b[1] for b in batch]), refine
            )
            batched_ms = 1000 * (time.perf_counter() - start) / poses
            rows.append(
                {
                    "noise_px": sigma,
                    "refine": refine,
                    "poses": poses,
                    "refused": refused / poses,
                    "rot_err_median_deg": float(np.median(rot)),
                    "rot_err_p90_deg": float(np.percentile(rot, 90)),
                    "trans_err_median_mm": float(np.median(trans)),
                    "trans_err_p90_mm": float(np.percentile(trans, 90)),
                    "ms_median": 1000 * float(np.median(secs)),
                    "ms_batched": batched_ms,
                }
            )
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--poses", type=int, default=1000)
    ap.add_argument("--sigmas", type=float, nargs="+", default=[0.0, 0.5, 1.0, 2.0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", default="bench/results/solver_noise.json")
    args = ap.parse_args()
    rows = run(args.poses, args.sigmas, args.seed)
    print(f"{'noise px':>8} {'refine':>6} {'refused':>8} {'rot med':>8} {'rot p90':>8} {'t med mm':>9} {'t p90 mm':>9} "
          f"{'ms':>6} {'ms batch':>8}")  # fmt: skip
    for r in rows:
        print(
            f"{r['noise_px']:8.1f} {r['refine']!s:>6} {100 * r['refused']:7.1f}% {r['rot_err_median_deg']:8.3f} "
            f"{r['rot_err_p90_deg']:8.3f} {r['trans_err_median_mm']:9.2f} {r['trans_err_p90_mm']:9.2f} {r['ms_median']:6.2f} "
            f"{r['ms_batched']:8.2f}"
        )
    write_results(args.json, rows)


if __name__ == "__main__":
    main()
