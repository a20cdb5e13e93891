"""Synthetic-data throughput: images per second at 640x480 with 3 LM-O objects plus 1-4 distractors.

Generates into a temporary folder with 1 and N worker processes (mesh parsing excluded: the mesh cache is warmed
first; worker start-up included) and prints a table; writes JSON.

    python bench/synth_speed.py --models ../shared/data/lmo/models --images 120 --workers 1 2
"""

from __future__ import annotations

import argparse
import platform
import tempfile
import time
from pathlib import Path

from write_results import write_results

from axispose_core.data.synth.config import SceneConfig, SynthConfig
from axispose_core.data.synth.generate import generate


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--models", default="../shared/data/lmo/models")
    ap.add_argument("--images", type=int, default=120)
    ap.add_argument("--images-per-scene", type=int, default=20)
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--json", default="bench/results/synth_speed.json")
    args = ap.parse_args()
    scene = SceneConfig(objects_per_image=(3, 3))
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        cache = Path(tmp) / "mesh_cache"
        generate(SynthConfig(scenes=1, images_per_scene=1, scene=scene), args.models, Path(tmp) / "warm", progress=False, mesh_cache=cache)
        for workers in args.workers:
            cfg = SynthConfig(scenes=args.images // args.images_per_scene, images_per_scene=args.images_per_scene, scene=scene, seed=1)
            start = time.perf_counter()
            n = generate(cfg, args.models, Path(tmp) / f"w{workers}", workers=workers, progress=False, mesh_cache=cache)
            secs = time.perf_counter() - start
            rows.append({"workers": workers, "images": n, "seconds": secs, "images_per_s": n / secs, "width": 640, "height": 480})
    print(f"{'workers':>7} {'images':>6} {'seconds':>8} {'img/s':>7}")
    for r in rows:
        print(f"{r['workers']:7d} {r['images']:6d} {r['seconds']:8.1f} {r['images_per_s']:7.2f}")
    write_results(args.json, {"machine": platform.processor() or platform.machine(), "rows": rows})


if __name__ == "__main__":
    main()
