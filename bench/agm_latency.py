"""Latency on this machine: the AGM's encoder (once per crop) against one denoiser step (per step and
hypothesis), by objects per frame and threads; the full crop -> AGM -> reader -> TBM path of a checkpoint; the
localiser per frame.

Part 1 times `AxisGenerator.encode` and one `Denoiser` call of the checkpoint's network, so that the cost of
steps and hypotheses can be read off (encoder + steps x hypotheses x step). Part 2 times `Estimator.estimate` on
a real frame (TBM cost depends on what the reader sees). Part 3 times the checkpoint's localiser, if any.

    python bench/agm_latency.py --checkpoint runs/main/agm.safetensors --json bench/results/agm_latency.json
"""

from __future__ import annotations

import argparse
import platform
import time

import numpy as np
import torch
from write_results import write_results

from axispose_core.data.bop_scene import bop_frames
from axispose_core.estimator import EstimateOptions, Estimator
from axispose_core.localiser.scoring import frame_instances


def _median_ms(fn, repeats: int) -> float:
    fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return 1000 * float(np.median(times))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoint", required=True)
    ap.add_argument("--data", default="data/lmo_val", help="a BOP folder with a frame for part 2")
    ap.add_argument("--steps", type=int, nargs="+", default=[1, 2, 4, 8])
    ap.add_argument("--objects", type=int, nargs="+", default=[1, 3, 8])
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--repeats", type=int, default=10)
    ap.add_argument("--json", default="bench/results/agm_latency.json")
    args = ap.parse_args()
    est = Estimator.load(args.checkpoint)
    size = est.size
    sampler_rows, path_rows, localiser_rows = [], [], []
    print("part 1: AGM encoder (per crop) and one denoiser step (per step and hypothesis), ms per call (batch = objects)")
    agm = est.agm
    for threads in args.threads:
        torch.set_num_threads(threads)
        for n in args.objects:
            crops, objects = torch.randint(0, 256, (n, 3, size, size), dtype=torch.uint8), torch.zeros(n, dtype=torch.long)
            with torch.inference_mode():
                enc = agm.encode(crops, objects)
                x, t = torch.randn(n, 3, size, size), torch.full((n,), 500)
                enc_ms = _median_ms(lambda crops=crops, objects=objects: agm.encode(crops, objects), args.repeats)
                step_ms = _median_ms(lambda x=x, t=t, enc=enc: agm.denoiser(x, t, enc), args.repeats)
            sampler_rows.append({"threads": threads, "objects": n, "encoder_ms": enc_ms, "step_ms": step_ms})
            print(f"  threads {threads} objects {n}: encoder {enc_ms:6.1f} ms, one step {step_ms:6.1f} ms")
    scene, im_id = bop_frames([args.data])[0]
    rgb = scene.rgb(im_id)
    K = scene.cameras[im_id]
    boxes = [(obj_id, box) for obj_id, box, _ in frame_instances(scene, im_id, tuple(est.objects))]
    print(f"part 2: full path of {args.checkpoint}, ms per frame")
    for threads in args.threads:
        torch.set_num_threads(threads)
        for n in args.objects:
            frame_boxes = (boxes * n)[:n]
            for steps in args.steps:
                ms = _median_ms(lambda b=frame_boxes, s=steps: est.estimate(rgb, K, b, EstimateOptions(steps=s)), args.repeats)
                path_rows.append({"threads": threads, "objects": n, "steps": steps, "ms_per_frame": ms, "ms_per_object": ms / n})
                print(f"  threads {threads} objects {n} steps {steps:>2}: {ms:7.1f} ms per frame, {ms / n:6.1f} per object")
        if est.localiser is not None:
            ms = _median_ms(lambda: est.detect(rgb), args.repeats)
            localiser_rows.append({"threads": threads, "ms_per_frame": ms, "frame": list(rgb.shape[:2])})
            print(f"part 3: localiser, threads {threads}: {ms:.1f} ms per {rgb.shape[1]}x{rgb.shape[0]} frame")
    out = {"machine": platform.processor() or platform.machine(), "date": time.strftime("%Y-%m-%d"), "checkpoint": args.checkpoint,
           "sampler": sampler_rows, "full_path": path_rows, "localiser": localiser_rows}  # fmt: skip
    write_results(args.json, out)


if __name__ == "__main__":
    main()
