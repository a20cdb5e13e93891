"""Held-out crop-stream metrics of AGM checkpoints, all on the same crops: what `axispose train` logs as its
validation, on more samples and for checkpoints trained on different streams (e.g. an easier recipe).

    python bench/agm_stream_val.py --checkpoints runs/a.safetensors runs/b.safetensors --samples 256 \
        --json bench/results/agm_stream_val.json
"""

from __future__ import annotations

import argparse
import dataclasses
import platform
import time

import numpy as np
import torch
from tqdm import tqdm
from write_results import write_results

from axispose_core.data.synth.config import StreamConfig
from axispose_core.data.synth.stream import CropStream, CropStreamDataset
from axispose_core.estimator import Estimator
from axispose_core.lmo import SHARED_LMO
from axispose_core.train.agm import TrainConfig, validate, with_depth_target


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoints", nargs="+", required=True)
    ap.add_argument("--models", default=str(SHARED_LMO / "models"))
    ap.add_argument("--samples", type=int, default=256)
    ap.add_argument("--steps", type=int, default=2, help="DDIM steps")
    ap.add_argument("--seed", type=int, default=TrainConfig().val_seed, help="held-out stream seed (the trainer's val_seed)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--json", default="bench/results/agm_stream_val.json")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    stream = CropStream(dataclasses.replace(StreamConfig(), seed=args.seed), args.models)
    data = CropStreamDataset(stream)
    items = [data[i] for i in tqdm(range(args.samples), desc="held-out crops")]
    rows = []
    for path in args.checkpoints:
        est = Estimator.load(path)
        ids = [o.obj_id for o in est.config.objects]
        if [o.obj_id for o in stream.objects] != ids:
            raise SystemExit(f"{path} knows objects {ids}, the stream renders {[o.obj_id for o in stream.objects]}")
        scales = torch.tensor([o.scale for o in est.config.objects], dtype=torch.float64)
        batch = with_depth_target({k: torch.stack([it[k] for it in items]) for k in items[0] if k != "keypoints"}, scales, est.size)
        lengths = np.stack([est.config.objects[int(o)].axes.lengths for o in batch["object"]])
        with torch.autocast("cpu", dtype=torch.bfloat16):
            metrics = validate(est.agm, est.reader, batch, lengths, args.steps)
        row = {"checkpoint": path, "steps": est.config.training.get("steps"), **metrics}
        rows.append(row)
        print(" ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in row.items()))
    out = {"machine": platform.processor() or platform.machine(), "date": time.strftime("%Y-%m-%d"), "samples": args.samples,
           "seed": args.seed, "ddim_steps": args.steps, "rows": rows}  # fmt: skip
    write_results(args.json, out)


if __name__ == "__main__":
    main()
