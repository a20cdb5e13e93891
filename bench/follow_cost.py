"""What following costs per frame against the number of objects (1, 3, 5, 8): LM-O's objects rendered apart over a
textured background, the camera turning a little each frame, each frame's objects followed by their contours from
the last frame's poses with the colours they learned (`ContourRefiner.refine` as `Estimator.follow` calls it). It
imports only what every refiner had, so an earlier tree runs it too (`PYTHONPATH=<worktree>`).

    python bench/follow_cost.py --threads 2 --out bench/results/follow_cost.json
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch
from scipy.spatial.transform import Rotation

import axispose_core
from axispose_core.data.meshes import load_render_mesh
from axispose_core.data.synth.raster import Light, render
from axispose_core.estimator import SHIPPED_ESTIMATOR, Estimator
from axispose_core.lmo import LMO_K
from axispose_core.refine.refiner import Start

K = np.asarray(LMO_K, dtype=np.float64)
LIGHT = Light(np.array([0.3, 0.5, 1.0]) / np.linalg.norm([0.3, 0.5, 1.0]), np.ones(3), 0.4)
OBJECTS = (1, 5, 6, 8, 9, 10, 11, 12)
PLACES = [(-0.16, -0.09), (0.0, -0.09), (0.16, -0.09), (-0.16, 0.02), (0.16, 0.02), (-0.16, 0.12), (0.0, 0.12), (0.16, 0.12)]


def frames(models: Path, count: int, n: int, seed: int = 0) -> list[tuple[np.ndarray, list[tuple[int, np.ndarray, np.ndarray]]]]:
    """`count` frames of the first `n` objects standing apart at 0.8 m, the camera turning 0.3° a frame."""
    rng = np.random.default_rng(seed)
    cells = (rng.random((60, 80, 3)) * 255).astype(np.uint8)
    bg = np.asarray(torch.nn.functional.interpolate(torch.from_numpy(cells).permute(2, 0, 1)[None].float(), (480, 640),
                                                    mode="bilinear")[0].permute(1, 2, 0).byte())  # fmt: skip
    meshes = {i: load_render_mesh(models, i) for i in OBJECTS[:n]}
    poses = [(i, Rotation.random(random_state=seed + i).as_matrix(), np.array([*PLACES[k], 0.8])) for k, i in enumerate(OBJECTS[:n])]
    out = []
    for f in range(count):
        turn = Rotation.from_euler("y", 0.3 * f, degrees=True).as_matrix()
        centre = np.array([0.0, 0.0, 0.8])
        posed = [(i, turn @ R, turn @ (t - centre) + centre) for i, R, t in poses]
        r = render([(meshes[i], R, t) for i, R, t in posed], K, 640, 480, LIGHT)
        out.append((np.where(r.instance[..., None] >= 0, (r.rgb * 255).astype(np.uint8), bg), posed))
    return out


def follow_times(refiner, seq) -> list[float]:
    """Seconds per followed frame after the first (refined from the truth with the whole schedule)."""
    image, posed = seq[0]
    first = refiner.refine(image, K, [Start(i, R, t) for i, R, t in posed])
    state = [(i, r.R, r.t, r.covariance, r.colours) for (i, _, _), r in zip(posed, first, strict=True)]
    times = []
    for image, _ in seq[1:]:
        start = time.perf_counter()
        out = refiner.refine(image, K, [Start(i, R, t, c) for i, R, t, c, _ in state], [h for *_, h in state])
        times.append(time.perf_counter() - start)
        state = [(s[0], r.R, r.t, r.covariance if r.refined else s[3], r.colours or s[4]) for s, r in zip(state, out, strict=True)]
    return times


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--models", default="../shared/data/lmo/models", help="the objects' BOP models (rendered)")
    parser.add_argument("--checkpoint", default=str(SHIPPED_ESTIMATOR))
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--frames", type=int, default=41)
    parser.add_argument("--out", default=None, help="JSON to write")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    refiner = Estimator.load(args.checkpoint).refiner
    refiner.prepare()
    rows = {}
    for n in (1, 3, 5, 8):
        t = 1000 * np.asarray(follow_times(refiner, frames(Path(args.models), args.frames, n)))
        rows[str(n)] = {"median_ms": float(np.median(t)), "p90_ms": float(np.percentile(t, 90)), "per_object_ms": float(np.median(t)) / n}
        print(n, json.dumps(rows[str(n)]))
    result = {"threads": args.threads, "frames": args.frames - 1, "refiner": axispose_core.__file__, "objects": rows}
    if args.out:
        Path(args.out).write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
