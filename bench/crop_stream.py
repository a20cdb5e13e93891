"""Throughput of the crop stream alone: samples per second through a DataLoader with W worker processes.

Each worker renders whole samples (`stream_loader`: batches of 32 collated as training would take them);
the first batches, while workers start and load their meshes, are not timed. Prints a line and writes JSON.

    python bench/crop_stream.py --seconds 60 --workers 2 --size 64 --json bench/results/crop_stream_64.json
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import os
import platform
import time

import torch
from write_results import write_results

from axispose_core.cli import _config
from axispose_core.data.synth.config import StreamConfig
from axispose_core.data.synth.stream import CropStream, stream_loader
from axispose_core.lmo import SHARED_LMO
from axispose_core.train.agm import TrainConfig


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--mesh-cell", type=float, default=None, help="override StreamConfig.mesh_cell")
    ap.add_argument("--config", default=None, help="a TrainConfig YAML whose stream to measure (default: StreamConfig())")
    ap.add_argument("--models", default=str(SHARED_LMO / "models"))
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    torch.set_num_threads(1)
    cfg = _config(TrainConfig, args.config).stream if args.config else StreamConfig()
    cfg = dataclasses.replace(cfg, size=args.size, mesh_cell=args.mesh_cell if args.mesh_cell is not None else cfg.mesh_cell)
    it = iter(stream_loader(CropStream(cfg, args.models), args.batch, workers=args.workers))
    for _ in range(max(1, args.workers)):  # warm-up: every worker has started and delivered once
        next(it)
    n, start = 0, time.perf_counter()
    while time.perf_counter() - start < args.seconds:
        n += len(next(it)["crop"])
    seconds = time.perf_counter() - start
    del it
    result = {
        "crops_per_s": n / seconds,
        "workers": args.workers,
        "size": args.size,
        "mesh_cell": cfg.mesh_cell,
        "config": args.config,
        "samples": n,
        "seconds": seconds,
        "cores": os.cpu_count(),
        "machine": platform.processor() or platform.machine(),
        "date": datetime.date.today().isoformat(),
    }
    print(
        f"{result['crops_per_s']:.0f} crops/s ({n} in {seconds:.1f} s; {args.workers} workers, {args.size} px, mesh_cell {cfg.mesh_cell})"
    )
    if args.json:
        write_results(args.json, result)


if __name__ == "__main__":
    main()
