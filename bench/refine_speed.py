"""The contour refiner's time per instance and per frame beside the unrefined frame's, as the node runs it (the
shipped estimator, float32, GT boxes of a BOP folder, one frame's objects refined together).

    python bench/refine_speed.py --data ../shared/data/lmo_real_val/test --threads 2 --out bench/results/refine_speed.json
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from axispose_core.data.bop_scene import bop_frames
from axispose_core.data.visibility import gt_info_from_models
from axispose_core.estimator import SHIPPED_ESTIMATOR, EstimateOptions, Estimator
from axispose_core.refine.refiner import Start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", required=True, help="a BOP split folder")
    parser.add_argument("--models", default="../shared/data/lmo/models_eval", help="models for the frames' visibility")
    parser.add_argument("--checkpoint", default=str(SHIPPED_ESTIMATOR))
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--frames", type=int, default=40)
    parser.add_argument("--out", default=None, help="JSON to write")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    est = Estimator.load(args.checkpoint)
    est.set_precision("float32")
    if est.refiner is None:
        raise SystemExit(f"{args.checkpoint} has no contour refiner")
    est.refiner.prepare()
    options = EstimateOptions(steps=3, refine=False)
    frames = bop_frames([args.data], gt_info_from_models(args.models))[: args.frames]
    per_instance, refine_frame, unrefined_frame = [], [], []
    for scene, im_id in frames:
        boxes = [(g.obj_id, info.bbox_obj) for g, info in scene.instances(im_id) if info.visib_fract >= 0.1]
        rgb, K = scene.rgb(im_id), scene.cameras[im_id]
        start = time.perf_counter()
        poses = est.estimate(rgb, K, boxes, options)
        unrefined_frame.append(time.perf_counter() - start)
        starts = [Start(p.obj_id, p.R, p.t, p.covariance) for p in poses if p.ok]
        start = time.perf_counter()
        est.refiner.refine(rgb, K, starts)
        refine_frame.append(time.perf_counter() - start)
        per_instance.append(refine_frame[-1] / max(1, len(starts)))
    ms = {name: {"median": 1000 * float(np.median(v)), "p90": 1000 * float(np.percentile(v, 90))}
          for name, v in (("refine_per_instance", per_instance), ("refine_per_frame", refine_frame),
                          ("unrefined_frame", unrefined_frame))}  # fmt: skip
    result = {"data": args.data, "frames": len(frames), "threads": args.threads, "ms": ms}
    print(json.dumps(result, indent=1))
    if args.out:
        Path(args.out).write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
