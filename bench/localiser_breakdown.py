"""Where a localiser's misses and false alarms come from, on held-out BOP frames.

For each checkpoint (a localiser's own, or an estimator carrying one): recall and precision at IoU 0.5 over a
sweep of score thresholds (the protocol of `detection_scores`: GT are instances with visib_fract >= 0.3,
detections of less visible instances are neither hits nor false alarms); at the checkpoint's own threshold,
recall per visibility band and per box size, each false alarm's kind: another object's instance
(IoU >= 0.3 with a GT of a different object), a poorly placed box on its own object (0.1 <= IoU < 0.5), or
background; and each missed instance's kind: found below the threshold (a detection of its object at
IoU >= 0.5 scoring under it), a poor box (one of its object above it that did not match it, IoU >= 0.1), taken
for another object (a detection of a different object at IoU >= 0.5 above it), or nothing there. Prints tables
and writes JSON. `--across-objects IOU` first drops every detection that overlaps a higher-scoring detection of
another object at IoU >= IOU (class-agnostic NMS on top of the per-object peaks), to see whether confusions
between objects can be removed that way. False alarms are also counted per object, and `--sheet PNG` draws them
and the misses as contact sheets of their crops (PNG_alarms.png: object id, kind, score; PNG_misses.png: object id,
kind, visibility): what the localiser takes for an object, and what it does not see. `--models` gives frames
without scene_gt_info.json (the real slice) their visibility from the object models.
Recall at the checkpoint's threshold comes with its instance counts and a 95 % Wilson interval, so a held-out set's
size shows in the figure; `--data` may be given several times to pool sets.

    python bench/localiser_breakdown.py --checkpoint stage1=runs/det_long/localiser.safetensors \\
        --checkpoint shipped=axispose_core/models/axispose_lmo.safetensors --data data/lmo_val
    python bench/localiser_breakdown.py --checkpoint lite0=LOCALISER.safetensors --min-visib 0.1 \\
        --data ../shared/data/lmo_real_val/test --models ../shared/data/lmo/models_eval --sheet /tmp/lite0.png
"""

from __future__ import annotations

import argparse
import datetime
import platform

import cv2
import numpy as np
import torch
from scipy.stats import binomtest
from tqdm import tqdm
from write_results import write_results

from axispose_core.data.bop_scene import BopScene, bop_frames
from axispose_core.data.visibility import gt_info_from_models
from axispose_core.localiser.decode import Detection, iou
from axispose_core.localiser.model import Localiser
from axispose_core.localiser.scoring import frame_instances, frame_outcome
from axispose_core.localiser.weights import load_localiser

THRESHOLDS = (0.05, 0.1, 0.15, 0.2, 0.25, 0.3, 0.4, 0.5, 0.6, 0.7)
VISIB = ((0.3, 0.5), (0.5, 0.8), (0.8, 1.01))
SIZES = ((0, 60), (60, 100), (100, 160), (160, 10_000))
TILE = 128
"""Side (px) of a crop on the sheets."""


def miss_kind(inst: tuple[int, tuple[float, float, float, float], float], dets: list[Detection], threshold: float) -> str:
    """Why an instance was missed at `threshold`, judged from all detections down to the sweep's lowest score."""
    obj, box, _ = inst
    same = [(d.score, iou(d.box, box)) for d in dets if d.obj_id == obj]
    if any(s < threshold and o >= 0.5 for s, o in same):
        return "low_score"
    if any(s >= threshold and o >= 0.1 for s, o in same):
        return "poor_box"
    if any(d.score >= threshold and d.obj_id != obj and iou(d.box, box) >= 0.5 for d in dets):
        return "other_object"
    return "nothing"


def suppress_across_objects(dets: list[Detection], min_iou: float) -> list[Detection]:
    """`dets` without those overlapping a higher-scoring detection of another object at IoU >= min_iou."""
    kept: list[Detection] = []
    for d in sorted(dets, key=lambda d: -d.score):
        if not any(k.obj_id != d.obj_id and iou(k.box, d.box) >= min_iou for k in kept):
            kept.append(d)
    return kept


def tile(image: np.ndarray, box: tuple[float, float, float, float], label: str) -> np.ndarray:
    """The box (x, y, w, h) with a quarter of its side around it, as a labelled BGR tile (black where the box lies
    outside the image)."""
    x, y, w, h = box
    x0, y0 = max(0, int(x - w / 4)), max(0, int(y - h / 4))
    x1, y1 = min(image.shape[1], int(x + 1.25 * w) + 1), min(image.shape[0], int(y + 1.25 * h) + 1)
    crop = image[y0:y1, x0:x1, ::-1]
    out = cv2.resize(np.ascontiguousarray(crop), (TILE, TILE)) if crop.size else np.zeros((TILE, TILE, 3), np.uint8)
    cv2.putText(out, label, (2, 12), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 255, 0), 1)
    return out


def write_sheet(path: str, tiles: list[np.ndarray], columns: int = 12) -> None:
    rows = max(1, -(-len(tiles) // columns))
    sheet = np.zeros((rows * TILE, columns * TILE, 3), np.uint8)
    for k, one in enumerate(tiles):
        r, c = divmod(k, columns)
        sheet[r * TILE : (r + 1) * TILE, c * TILE : (c + 1) * TILE] = one
    cv2.imwrite(path, sheet)


def breakdown(
    model: Localiser,
    frames: list[tuple[BopScene, int]],
    min_visib: float,
    across_objects: float | None = None,
    tiles: dict[str, list[np.ndarray]] | None = None,
) -> dict:
    """The breakdown at the checkpoint's threshold and the sweep; each false alarm's and miss's tile appended to
    `tiles["alarms"]` and `tiles["misses"]`."""
    sweep = {t: [0, 0, 0] for t in THRESHOLDS}  # hits, false alarms, GT
    at = model.config.threshold
    found, visib, size = [], [], []
    alarms = {"other_object": 0, "poor_box": 0, "background": 0}
    alarms_by_object = {obj: dict.fromkeys(alarms, 0) for obj in model.config.obj_ids}
    misses = {"low_score": 0, "poor_box": 0, "other_object": 0, "nothing": 0}
    for scene, im_id in tqdm(frames, desc="detect", leave=False):
        image = scene.rgb(im_id)
        all_dets = model.detect(image, threshold=min(THRESHOLDS))
        if across_objects is not None:
            all_dets = suppress_across_objects(all_dets, across_objects)
        insts = frame_instances(scene, im_id, model.config.obj_ids)
        for t in sorted({*THRESHOLDS, at}):
            dets = [d for d in all_dets if d.score >= t]
            hits, false_alarms = frame_outcome(dets, insts, min_visib)
            if t in sweep:
                sweep[t][0] += sum(hits.values())
                sweep[t][1] += len(false_alarms)
                sweep[t][2] += len(hits)
            if t != at:
                continue
            for g, hit in hits.items():
                found.append(hit)
                visib.append(insts[g][2])
                size.append(max(insts[g][1][2], insts[g][1][3]))
                if not hit:
                    kind = miss_kind(insts[g], all_dets, at)
                    misses[kind] += 1
                    if tiles is not None:
                        tiles["misses"].append(tile(image, insts[g][1], f"{insts[g][0]} {kind} {insts[g][2]:.2f}"))
            for d in (dets[k] for k in false_alarms):
                same = max([iou(d.box, b) for o, b, _ in insts if o == d.obj_id], default=0.0)
                other = max([iou(d.box, b) for o, b, _ in insts if o != d.obj_id], default=0.0)
                kind = "other_object" if other >= 0.3 and same < 0.1 else "poor_box" if same >= 0.1 else "background"
                alarms[kind] += 1
                alarms_by_object[d.obj_id][kind] += 1
                if tiles is not None:
                    tiles["alarms"].append(tile(image, d.box, f"{d.obj_id} {kind} {d.score:.2f}"))
    found_a, visib_a, size_a = np.array(found), np.array(visib), np.array(size)

    def band(values: np.ndarray, lo: float, hi: float) -> dict:
        sel = (values >= lo) & (values < hi)
        return {"range": [lo, hi], "n": int(sel.sum()), "recall": float(found_a[sel].mean()) if sel.any() else float("nan")}

    nan = float("nan")
    hits = int(found_a.sum())
    ci = binomtest(hits, len(found_a)).proportion_ci(method="wilson") if len(found_a) else None
    curve = [{"threshold": t, "recall": h / n if n else nan, "precision": h / (h + f) if h + f else nan} for t, (h, f, n) in sweep.items()]
    return {
        "threshold": at,
        "sweep": curve,
        "recall": float(found_a.mean()) if len(found_a) else float("nan"),
        "instances": len(found_a),
        "hits": hits,
        "recall_ci95": [float(ci.low), float(ci.high)] if ci else [nan, nan],
        "by_visibility": [band(visib_a, lo, hi) for lo, hi in VISIB],
        "by_box_side_px": [band(size_a, lo, hi) for lo, hi in SIZES],
        "false_alarms": alarms,
        "false_alarms_by_object": {str(obj): kinds for obj, kinds in alarms_by_object.items()},
        "misses": misses,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoint", action="append", required=True, help="LABEL=PATH (repeatable)")
    ap.add_argument("--data", action="append", required=True, help="held-out BOP folder (repeatable: pooled)")
    ap.add_argument("--min-visib", type=float, default=0.3)
    ap.add_argument("--across-objects", type=float, default=None, metavar="IOU",
                    help="drop detections overlapping a better one of another object at IoU >= IOU")  # fmt: skip
    ap.add_argument("--models", default=None, help="BOP models folder: visibility of frames without scene_gt_info.json")
    ap.add_argument("--sheet", default=None, metavar="PNG", help="false alarms and misses as contact sheets (_LABEL added per checkpoint)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--json", default="bench/results/localiser_breakdown.json")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    frames = bop_frames(args.data, gt_info_from_models(args.models))
    results = {}
    for item in args.checkpoint:
        label, _, path = item.partition("=")
        model = load_localiser(path)
        tiles: dict[str, list[np.ndarray]] | None = {"alarms": [], "misses": []} if args.sheet else None
        r = results[label] = breakdown(model, frames, args.min_visib, args.across_objects, tiles) | {"checkpoint": path}
        if tiles is not None:
            stem = args.sheet.removesuffix(".png") + ("" if len(args.checkpoint) == 1 else f"_{label}")
            r["sheets"] = {what: f"{stem}_{what}.png" for what in tiles}
            for what, sheet in r["sheets"].items():
                write_sheet(sheet, tiles[what])
        lo, hi = r["recall_ci95"]
        print(f"\n{label} ({path}), {len(frames)} frames; recall {r['recall']:.3f} ({r['hits']}/{r['instances']}, "
              f"95 % interval {lo:.3f}-{hi:.3f}) at its threshold {r['threshold']}")  # fmt: skip
        print("threshold  " + "  ".join(f"{s['threshold']:>5}" for s in r["sweep"]))
        print("recall     " + "  ".join(f"{s['recall']:5.3f}" for s in r["sweep"]))
        print("precision  " + "  ".join(f"{s['precision']:5.3f}" for s in r["sweep"]))
        for name, key in (("visib_fract", "by_visibility"), ("box side px", "by_box_side_px")):
            print(f"{name:<11}" + "  ".join(f"[{b['range'][0]:g},{b['range'][1]:g}) n={b['n']} {b['recall']:.3f}" for b in r[key]))
        print("false alarms: " + ", ".join(f"{k} {v}" for k, v in r["false_alarms"].items()))
        print("  by object: " + ", ".join(f"{o} {sum(k.values())}" for o, k in r["false_alarms_by_object"].items()))
        print("misses: " + ", ".join(f"{k} {v}" for k, v in r["misses"].items()))
    meta = {"machine": f"{platform.machine()} {platform.processor()}".strip(), "threads": args.threads,
            "date": datetime.date.today().isoformat(), "data": args.data, "frames": len(frames),
            "across_objects": args.across_objects, "min_visib": args.min_visib}  # fmt: skip
    write_results(args.json, meta | {"results": results})


if __name__ == "__main__":
    main()
