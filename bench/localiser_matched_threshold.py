"""Localisers compared at equal synthetic precision rather than at one score threshold: each one's threshold is the
lowest at which its precision on synthetic validation frames reaches TARGET (fitted on renders only), and its recall /
precision on real frames are read there (and at 0.3, the node's default). Detections are taken once at 0.05.

    python bench/localiser_matched_threshold.py --target 0.85 --val data/lmo_val \
        --real ../shared/data/lmo_real_val/test HELDOUT/test --checkpoint NAME=CKPT ... --json OUT.json
"""

from __future__ import annotations

import argparse

import numpy as np
import torch
from write_results import write_results

from axispose_core.data.bop_scene import bop_frames
from axispose_core.data.visibility import gt_info_from_models
from axispose_core.localiser.decode import Detection
from axispose_core.localiser.scoring import Instance, frame_instances, tally
from axispose_core.localiser.weights import load_localiser

Frames = list[tuple[list[Detection], list[Instance]]]


def score(frames: Frames, ids: tuple[int, ...], threshold: float, min_visib: float) -> tuple[float, float]:
    """(recall, precision) over all instances of the detections at or above `threshold`."""
    scores = tally([([d for d in dets if d.score >= threshold], insts) for dets, insts in frames], ids, min_visib)
    return scores["recall"], scores["precision"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--target", type=float, default=0.85, help="synthetic validation precision every threshold reaches")
    ap.add_argument("--val", required=True, help="synthetic validation frames (BOP)")
    ap.add_argument("--real", nargs="+", required=True, help="real BOP frame folders")
    ap.add_argument("--checkpoint", nargs="+", required=True, help="NAME=localiser or estimator checkpoint")
    ap.add_argument("--models", default="../shared/data/lmo/models_eval", help="visibility from these models")
    ap.add_argument("--min-visib", type=float, default=0.1)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    info = gt_info_from_models(args.models)
    sets = {"val": args.val, **{path: path for path in args.real}}
    images = {k: [(s, i, s.rgb(i)) for s, i in bop_frames([v], info)] for k, v in sets.items()}
    grid = np.round(np.arange(0.05, 0.9, 0.01), 2)
    out = {"target": args.target, "runs": {}}
    for item in args.checkpoint:
        name, path = item.split("=", 1)
        localiser = load_localiser(path).fused()
        ids = localiser.config.obj_ids
        frames = {k: [(localiser.detect(rgb, threshold=0.05), frame_instances(s, i, ids)) for s, i, rgb in v] for k, v in images.items()}
        threshold = next((float(t) for t in grid if score(frames["val"], ids, t, args.min_visib)[1] >= args.target), float(grid[-1]))
        at = {k: score(v, ids, threshold, args.min_visib) for k, v in frames.items()}
        default = {k: score(v, ids, 0.3, args.min_visib) for k, v in frames.items()}
        out["runs"][name] = {"threshold": threshold, "at_threshold": at, "at_0.3": default}
        shown = " | ".join(f"{k}: {r:.3f} / {p:.3f}" for k, (r, p) in at.items())
        print(f"{name}: threshold {threshold:.2f} | {shown}", flush=True)
    if args.json:
        write_results(args.json, out)


if __name__ == "__main__":
    main()
