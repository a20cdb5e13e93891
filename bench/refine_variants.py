"""Contour-refiner settings compared on the same poses: the shipped estimator's GT-crop poses of a BOP set are made
once (cached beside --cache), then refined under each variant (a JSON of `RefineConfig` changes) and scored as
`axispose eval` scores them; one line per variant, appended to --log.

    python bench/refine_variants.py --data ../shared/data/lmo_real_val/test --set slice --cache out/refine_cache/slice.pkl \\
        --variant default '{}' --variant icg_damping '{"damping": [1000, 30000]}' --log bench/results/refine_variants.txt
"""

from __future__ import annotations

import argparse
import json
import pickle
import time
from pathlib import Path

import numpy as np
import torch

from axispose_core.config import config_from_dict
from axispose_core.data.meshes import refiner_meshes
from axispose_core.estimator import SHIPPED_ESTIMATOR, EstimateOptions, Estimator
from axispose_core.evaluation.records import Prediction
from axispose_core.evaluation.run import EvalOptions, evaluate
from axispose_core.evaluation.summary import pooled, summarize
from axispose_core.refine.config import RefineConfig
from axispose_core.refine.refiner import ContourRefiner, Start


def cached_predictor(est: Estimator, cache: dict, refiner: ContourRefiner | None, times: list[float]):
    """The estimator's unrefined poses of a frame's boxes (made once per frame and kept in `cache`), refined
    together by `refiner` (None: as they are)."""

    def predict(image: np.ndarray, K: np.ndarray, boxes: list) -> list[Prediction]:
        key = (tuple((o, tuple(np.round(b, 2))) for o, b in boxes), np.asarray(K).tobytes())
        if key not in cache:
            cache[key] = [(p.R, p.t, p.ok, p.covariance) for p in est.estimate(image, K, boxes, EstimateOptions(steps=3, refine=False))]
        poses = [Prediction(R, t, ok, covariance=c) for R, t, ok, c in cache[key]]
        if refiner is None:
            return poses
        posed = [k for k, p in enumerate(poses) if p.ok]
        start = time.perf_counter()
        out = refiner.refine(image, K, [Start(boxes[k][0], poses[k].R, poses[k].t, poses[k].covariance) for k in posed])
        times.append((time.perf_counter() - start) / max(1, len(posed)))
        for k, r in zip(posed, out, strict=True):
            poses[k] = Prediction(r.R, r.t, True, covariance=r.covariance)
        return poses

    return predict


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", required=True, help="a BOP split folder")
    parser.add_argument("--set", required=True, help="the set's name in the result lines (slice, held-out, synthetic)")
    parser.add_argument("--models", default="../shared/data/lmo/models_eval", help="models for the metrics and visibility")
    parser.add_argument("--cache", required=True, help="pickle of the estimator's poses (made on first use)")
    parser.add_argument("--variant", nargs=2, action="append", metavar=("NAME", "JSON"), default=[],
                        help="a variant: its name and its RefineConfig changes; 'off' as JSON: unrefined")  # fmt: skip
    parser.add_argument("--log", default=None, help="text file the result lines are appended to")
    args = parser.parse_args()
    torch.set_num_threads(1)
    est = Estimator.load(SHIPPED_ESTIMATOR)
    est.set_precision("float32")
    objects = list(est.config.objects)
    cache_path = Path(args.cache)
    cache = pickle.loads(cache_path.read_bytes()) if cache_path.exists() else {}
    meshes = est.meshes or refiner_meshes(Path(args.models).parent / "models", [o.obj_id for o in objects])
    for name, changes in args.variant:
        refiner = None if changes == "off" else ContourRefiner(config_from_dict(RefineConfig, json.loads(changes), name), meshes)
        times: list[float] = []
        run = evaluate(cached_predictor(est, cache, refiner, times), args.data, args.models, objects, EvalOptions(progress=False))
        report = summarize(run.records, objects, {})
        m, pool = report["mean"], pooled(run.records)
        per = " ".join(f"{e['name'][:5]} {e['add_0.1d']:.2f}" for e in report["objects"].values())
        line = (f"{args.set} {name}: ADD(-S)@0.1d {m['add_0.1d']:.3f} Reproj@15px {m['reproj_15px']:.3f} rotation "
                f"{pool['rot_err_median_deg']:.1f} depth {pool['depth_log_abs_mean']:.2%} | {per} | "
                f"{1000 * float(np.median(times)) if times else 0:.1f} ms  {changes}")  # fmt: skip
        print(line)
        if args.log:
            with open(args.log, "a") as f:
                f.write(line + "\n")
    cache_path.parent.mkdir(parents=True, exist_ok=True)
    cache_path.write_bytes(pickle.dumps(cache))


if __name__ == "__main__":
    main()
