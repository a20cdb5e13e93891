"""Keypoint readers on clean and degraded axis images: network (shipped) against the classical line fit.

For random LM-O poses in detector-like crops, the axis image is rendered, optionally degraded the way a
generator fails (broken strokes, blur, noise, stray blobs, uneven gain), read, and back-projected with the
re-projection refinement. Prints a table and writes JSON.

    python bench/reader_accuracy.py --samples 500 --json bench/results/reader_accuracy.json
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch
from tqdm import tqdm
from write_results import write_results

from axispose_core.metrics import re
from axispose_core.tbm.backproject import backproject
from axispose_core.tbm.line_fit import fit_axis_keypoints
from axispose_core.tbm.reader import SHIPPED_READER, load_reader
from axispose_core.train.reader import synth_batch


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--reader", default=str(SHIPPED_READER))
    ap.add_argument("--samples", type=int, default=500)
    ap.add_argument("--seed", type=int, default=123, help="never a training seed (training uses 0)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--json", default="bench/results/reader_accuracy.json")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    reader = load_reader(args.reader)
    rows = []
    for condition, prob in (("clean", 0.0), ("degraded", 1.0)):
        rng = np.random.default_rng(args.seed)
        gen = torch.Generator().manual_seed(args.seed)
        # synth_batch draws the same pose distribution the reader trains on; keep K' and poses for the TBM.
        images, kps, Ks, Rs, lens = [], [], [], [], []
        for _ in tqdm(range(args.samples), desc=f"render {condition}", leave=False):
            img, kp, sample, lengths = synth_batch(rng, gen, reader.config, 1, prob, return_samples=True)
            images.append(img[0])
            kps.append(kp[0].numpy())
            Ks.append(sample[0].K_patch)
            Rs.append(sample[0].R)
            lens.append(lengths[0])
        for name in ("net", "line-fit"):
            kp_err, rot, times = [], [], []
            for i in tqdm(range(args.samples), desc=f"{name} {condition}", leave=False):
                start = time.perf_counter()
                if name == "net":
                    read = reader.read(images[i][None])[0]
                else:
                    read = fit_axis_keypoints(images[i].permute(1, 2, 0).numpy())
                res = backproject(Ks[i], read.origin, read.endpoints, lens[i], refine=True) if read.ok else None
                times.append(time.perf_counter() - start)
                kp_err.append(float(np.abs(read.array - kps[i]).mean()) if read.ok else float("inf"))
                rot.append(re(res.R, Rs[i]) if res is not None and res.ok else 180.0)
            rot_a = np.array(rot)
            rows.append(
                {
                    "condition": condition,
                    "reader": name,
                    "samples": args.samples,
                    "size": reader.config.size,
                    "kp_err_median_px": float(np.median(kp_err)),
                    "rot_err_median_deg": float(np.median(rot_a)),
                    "rot_within_2deg": float(np.mean(rot_a < 2.0)),
                    "rot_within_5deg": float(np.mean(rot_a < 5.0)),
                    "ms_median": 1000 * float(np.median(times)),
                }
            )
    print(f"{'condition':<9} {'reader':<8} {'kp err px':>9} {'rot med':>8} {'<2 deg':>7} {'<5 deg':>7} {'ms':>6}")
    for r in rows:
        print(
            f"{r['condition']:<9} {r['reader']:<8} {r['kp_err_median_px']:9.2f} {r['rot_err_median_deg']:8.2f} "
            f"{100 * r['rot_within_2deg']:6.1f}% {100 * r['rot_within_5deg']:6.1f}% {r['ms_median']:6.2f}"
        )
    write_results(args.json, rows)


if __name__ == "__main__":
    main()
