"""Latency on a CUDA GPU: the AGM sampler on batches of instances, the whole estimate path, the localiser.

Part 1 times `AxisGenerator.sample` of the checkpoint's AGM per batch of crops (a frame's objects, or many
frames' objects together) in fp32, under bf16 autocast, and under bf16 with the denoiser compiled by
`torch.compile(mode="reduce-overhead")`, which replays it as CUDA graphs. Part 2 times `Estimator.estimate`
(crop, AGM, keypoint reader, TBM on the CPU) on a real frame, fp32 as the node runs it. Part 3 times the
localiser per frame. Each number is the median of `--repeats` synchronised calls after warm-up calls.

    python bench/agm_latency_gpu.py --checkpoint axispose_core/models/axispose_lmo.safetensors --data data/lmo_val \
        --json bench/results/agm_latency_gpu.json
"""

from __future__ import annotations

import argparse
import copy
import platform
import time
from collections.abc import Callable

import numpy as np
import torch
from write_results import write_results

from axispose_core.agm.sampler import sample
from axispose_core.data.bop import bop_frames
from axispose_core.estimator import Estimator
from axispose_core.localiser.scoring import frame_instances

MODES = ("fp32", "bf16", "bf16+graphs")


def _median_ms(fn: Callable[[], object], repeats: int, warmup: int = 3) -> float:
    for _ in range(warmup):
        fn()
    torch.cuda.synchronize()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        torch.cuda.synchronize()
        times.append(time.perf_counter() - start)
    return 1000 * float(np.median(times))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoint", required=True)
    ap.add_argument("--data", required=True, help="a BOP folder with a frame for parts 2 and 3")
    ap.add_argument("--steps", type=int, nargs="+", default=[1, 4, 8])
    ap.add_argument("--batches", type=int, nargs="+", default=[1, 8, 32, 128])
    ap.add_argument("--objects", type=int, nargs="+", default=[1, 3, 8])
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--json", default="bench/results/agm_latency_gpu.json")
    args = ap.parse_args()
    if not torch.cuda.is_available():
        raise SystemExit("no CUDA device: this benchmark times the GPU (bench/agm_latency.py times the CPU)")
    est = Estimator.load(args.checkpoint, device="cuda")
    size = est.size
    sampler_rows, path_rows, localiser_rows = [], [], []
    print(f"part 1: AGM sampler on {torch.cuda.get_device_name()}, ms per call (batch = instances)")
    for mode in MODES:
        agm = est.agm
        if mode == "bf16+graphs":
            agm = copy.deepcopy(est.agm)
            agm.denoiser = torch.compile(agm.denoiser, mode="reduce-overhead")
        for n in args.batches:
            crops = torch.randint(0, 256, (n, 3, size, size), dtype=torch.uint8, device="cuda")
            for steps in args.steps:

                def call(agm=agm, crops=crops, steps=steps, mode=mode) -> torch.Tensor:
                    with torch.inference_mode(), torch.autocast("cuda", torch.bfloat16, enabled=mode != "fp32"):
                        return sample(agm, agm.encode(crops, torch.zeros(len(crops), dtype=torch.long, device="cuda")), steps)

                start = time.perf_counter()
                try:
                    call()
                except Exception as e:  # a compile failure is a result to report
                    sampler_rows.append({"mode": mode, "batch": n, "steps": steps, "error": repr(e)[:300]})
                    print(f"  {mode:<12} batch {n:>3} steps {steps}: failed: {e!r:.200}")
                    continue
                first_ms = 1000 * (time.perf_counter() - start)
                ms = _median_ms(call, args.repeats)
                sampler_rows.append({"mode": mode, "batch": n, "steps": steps, "ms": ms, "first_call_ms": first_ms})
                print(f"  {mode:<12} batch {n:>3} steps {steps}: {ms:7.2f} ms ({ms / n:6.3f} per instance; first call {first_ms:.0f} ms)")
    scene, im_id = bop_frames([args.data])[0]
    rgb, K = scene.rgb(im_id), scene.cameras[im_id]
    boxes = [(obj_id, box) for obj_id, box, _ in frame_instances(scene, im_id, tuple(est.objects))]
    print(f"part 2: full path (fp32, TBM on the CPU), {est.config.ddim_steps} steps, ms per frame")
    for n in args.objects:
        frame_boxes = (boxes * n)[:n]
        ms = _median_ms(lambda b=frame_boxes: est.estimate(rgb, K, b), args.repeats)
        path_rows.append({"objects": n, "steps": est.config.ddim_steps, "ms_per_frame": ms, "ms_per_object": ms / n})
        print(f"  objects {n}: {ms:7.1f} ms per frame, {ms / n:6.1f} per object")
    if est.localiser is not None:
        ms = _median_ms(lambda: est.detect(rgb), args.repeats)
        localiser_rows.append({"ms_per_frame": ms, "frame": list(rgb.shape[:2])})
        print(f"part 3: localiser (fused, fp32): {ms:.2f} ms per {rgb.shape[1]}x{rgb.shape[0]} frame")
    out = {"machine": torch.cuda.get_device_name(), "host": platform.processor() or platform.machine(), "torch": torch.__version__,
           "date": time.strftime("%Y-%m-%d"), "checkpoint": args.checkpoint,
           "sampler": sampler_rows, "full_path": path_rows, "localiser": localiser_rows}  # fmt: skip
    write_results(args.json, out)


if __name__ == "__main__":
    main()
