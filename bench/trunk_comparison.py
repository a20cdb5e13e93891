"""Crop encoders on different trunks, compared through the direct-regression baseline (the encoder and a keypoint
head, no denoiser: what each trunk perceives, at a fraction of the AGM's training cost): on the GT crops of BOP
folders (a synthetic test set, the desk's held-out photographs and meshes), the median keypoint error (px, mean
over origin and axis ends) and the median |relative depth error| of the encoder's depth head; and the encoder's
float32 time for 5 crops on 2 threads.

    python bench/trunk_comparison.py scratch=runs/dir_scratch.safetensors lite=runs/dir_lite.safetensors \
        --data data/lmo_val runs/stress --json bench/results/trunk_comparison.json
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import DataLoader
from write_results import write_results

from axispose_core.agm.model import depth_from_log
from axispose_core.axis_image import axis_keypoints
from axispose_core.baseline.direct import DirectEstimator
from axispose_core.train.dataset import AxisCropDataset


@torch.inference_mode()
def crop_errors(est: DirectEstimator, root: Path, min_visib: float) -> dict[str, float]:
    model = est.model
    objects = list(model.config.objects)
    data = AxisCropDataset([root], objects, model.config.size, min_visib, jitter=None, color_aug=False)
    kp_err, depth_err = [], []
    for batch in DataLoader(data, batch_size=64):
        enc = model.encoder(batch["crop"], batch["object"])
        kps = ((model.head(enc.context).view(-1, 4, 2) + 1) * 0.5 * model.config.size - 0.5).double().numpy()
        for i, kp in enumerate(kps):
            K, R, t = (batch[k][i].numpy() for k in ("K", "R", "t"))
            lengths = objects[int(batch["object"][i])].axes.lengths
            kp_err.append(float(np.linalg.norm(kp - axis_keypoints(K, R, t, lengths), axis=1).mean()))
            depth_err.append(abs(depth_from_log(float(enc.log_depth[i]), K, lengths[0], model.config.size) / t[2] - 1))
    return {"crops": len(kp_err), "kp_err_px": float(np.median(kp_err)), "depth_err": float(np.median(depth_err))}


def encoder_ms(est: DirectEstimator, repeats: int = 30) -> float:
    crops = torch.randint(0, 256, (5, 3, est.model.config.size, est.model.config.size), dtype=torch.uint8)
    objects = torch.zeros(5, dtype=torch.long)
    times = []
    with torch.inference_mode():
        for k in range(repeats + 5):
            start = time.perf_counter()
            est.model.encoder(crops, objects)
            if k >= 5:
                times.append(time.perf_counter() - start)
    return 1000 * float(np.median(times))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("checkpoints", nargs="+", help="NAME=direct-regressor checkpoint")
    ap.add_argument("--data", nargs="+", required=True, help="BOP folders with GT")
    ap.add_argument("--min-visib", type=float, default=0.3)
    ap.add_argument("--json", help="write the results here")
    args = ap.parse_args()
    torch.set_num_threads(2)
    results = {}
    for spec in args.checkpoints:
        name, path = spec.split("=", 1)
        est = DirectEstimator.load(path)
        row = {"checkpoint": path, "trunk": est.model.config.encoder.trunk.kind, "encoder_ms_5_crops": encoder_ms(est)}
        row |= {Path(root).name: crop_errors(est, Path(root), args.min_visib) for root in args.data}
        results[name] = row
        cells = "  ".join(f"{Path(r).name}: kp {row[Path(r).name]['kp_err_px']:.2f} px, depth {100 * row[Path(r).name]['depth_err']:.1f} %"
                          for r in args.data)  # fmt: skip
        print(f"{name:>14} ({row['trunk']}, {row['encoder_ms_5_crops']:.1f} ms / 5 crops)  {cells}")
    if args.json:
        write_results(args.json, results)


if __name__ == "__main__":
    main()
