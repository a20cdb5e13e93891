"""The localiser's detection protocol on BOP frames: which instances a frame's detections find (IoU 0.5, amodal
boxes), which detections are false alarms, and recall and precision per object (`tally`)."""

from __future__ import annotations

import time
from collections.abc import Iterable
from pathlib import Path

import numpy as np
from tqdm import tqdm

from axispose_core.data.bop_scene import BopScene, bop_frames
from axispose_core.localiser.decode import Detection, match
from axispose_core.localiser.model import Localiser

Instance = tuple[int, tuple[float, float, float, float], float]
"""A frame's object instance as the protocol takes it: (obj_id, bbox_obj, visib_fract)."""


def frame_instances(scene: BopScene, im_id: int, obj_ids: tuple[int, ...]) -> list[tuple[int, tuple[int, int, int, int], float]]:
    """The frame's (obj_id, bbox_obj, visib_fract) instances of the given objects, as `frame_outcome` takes them."""
    return [(g.obj_id, info.bbox_obj, info.visib_fract) for g, info in scene.instances(im_id) if g.obj_id in obj_ids]


def false_alarms(hits: list[int | None], count: int) -> list[int]:
    """Indices of the `count` detections that no instance claimed in `match`'s `hits` (one per instance)."""
    claimed = {k for k in hits if k is not None}
    return [k for k in range(count) if k not in claimed]


def frame_outcome(dets: list[Detection], insts: list[Instance], min_visib: float) -> tuple[dict[int, bool], list[int]]:
    """The detection protocol on one frame's (obj_id, bbox_obj, visib_fract) instances: for each instance with
    visib_fract >= min_visib (by index) whether a detection found it at IoU 0.5, and the indices of the false
    alarms. A detection that matches a less visible instance is neither a hit nor a false alarm."""
    hits = match(dets, [(o, b) for o, b, _ in insts])
    found = {g: k is not None for g, ((_, _, v), k) in enumerate(zip(insts, hits, strict=True)) if v >= min_visib}
    return found, false_alarms(hits, len(dets))


def detection_outcomes(dets: list[Detection], insts: list[Instance], min_visib: float) -> list[int]:
    """The detection protocol per detection: 1 it found an instance with visib_fract >= min_visib, 0 a false alarm,
    -1 neither (it found a less visible instance)."""
    out = [0] * len(dets)
    for (_, _, visib), k in zip(insts, match(dets, [(o, b) for o, b, _ in insts]), strict=True):
        if k is not None:
            out[k] = 1 if visib >= min_visib else -1
    return out


def tally(frames: Iterable[tuple[list[Detection], list[Instance]]], obj_ids: tuple[int, ...], min_visib: float) -> dict:
    """Recall and precision per object and over all instances of frames' detections against their (obj_id, bbox_obj,
    visib_fract) instances (`frame_outcome`)."""
    tp, fp, n_gt = dict.fromkeys(obj_ids, 0), dict.fromkeys(obj_ids, 0), dict.fromkeys(obj_ids, 0)
    for dets, insts in frames:
        found, alarms = frame_outcome(dets, insts, min_visib)
        for g, hit in found.items():
            n_gt[insts[g][0]] += 1
            tp[insts[g][0]] += hit
        for k in alarms:
            fp[dets[k].obj_id] += 1
    per = {
        str(o): {"n": n_gt[o], "recall": tp[o] / n_gt[o] if n_gt[o] else float("nan"),
                 "precision": tp[o] / (tp[o] + fp[o]) if tp[o] + fp[o] else float("nan")}
        for o in obj_ids
    }  # fmt: skip
    total_gt, total_tp = sum(n_gt.values()), sum(tp.values())
    return {
        "objects": per,
        "recall": total_tp / total_gt if total_gt else float("nan"),
        "precision": total_tp / (total_tp + sum(fp.values())) if total_tp + sum(fp.values()) else float("nan"),
    }


def detection_scores(
    model: Localiser, data: list[str | Path], min_visib: float = 0.3, limit: int | None = None, progress: bool = False
) -> dict:
    """Recall and precision at IoU 0.5 per object on BOP frames (GT: bbox_obj with visib_fract >= min_visib;
    detections of less visible instances are neither hits nor false positives), and ms per frame."""
    ids = model.config.obj_ids
    outcomes, times = [], []
    for scene, im_id in tqdm(bop_frames(data)[:limit], desc="detect", disable=not progress):
        rgb = scene.rgb(im_id)
        start = time.perf_counter()
        dets = model.detect(rgb)
        times.append(time.perf_counter() - start)
        outcomes.append((dets, frame_instances(scene, im_id, ids)))
    ms = 1000 * np.array(times or [0.0])
    return {**tally(outcomes, ids, min_visib), "ms_per_frame": {"median": float(np.median(ms)), "p90": float(np.percentile(ms, 90))}}
