"""What an adaptation round did, per object: the poses the frames gave, those their evidence accepted, what the
scene checked, rejected and filled; and a contact sheet of the labels (per object a row of crops with the pose's
axes drawn, the border telling where the label came from)."""

from __future__ import annotations

from collections import Counter
from collections.abc import Mapping, Sequence
from pathlib import Path

import cv2
import numpy as np

from axispose_core.adapt.labels import Label
from axispose_core.adapt.pseudo import AcceptConfig, Candidate
from axispose_core.adapt.recording import Frame
from axispose_core.adapt.scene import SceneResult
from axispose_core.adapt.search import Discovery
from axispose_core.axis_image import draw_axes
from axispose_core.camera import instance_crop
from axispose_core.objects import ObjectSpec

BORDERS = {"checked": (60, 200, 60), "filled": (40, 200, 240), "alone": (230, 140, 40)}
"""Contact-sheet border per label source (BGR): green checked by the scene, yellow filled by it, blue alone."""


def round_counts(
    candidates: Mapping[int, Sequence[Candidate]], accept: AcceptConfig, scene: SceneResult, labels: Sequence[Label],
    unfilled: Mapping[int, int], objects: Sequence[ObjectSpec], discoveries: Sequence[Discovery] = (),
) -> dict:  # fmt: skip
    """Per object (by name) and in all: candidates, accepted by their own evidence, rejected by the scene (by
    reason), labels by source, predictions not filled, and where the scene was searched for it, the frames that
    agreed on its best place of those read; and the frames, those whose camera was placed, the objects found to
    have moved."""
    per: dict[str, dict] = {}
    names = {o.obj_id: o.name for o in objects}
    for o in objects:
        cands = [c for cs in candidates.values() for c in cs if c.obj_id == o.obj_id]
        sources = Counter(lab.source for lab in labels if lab.obj_id == o.obj_id)
        per[o.name] = {
            "candidates": len(cands), "accepted": sum(accept.accepts(c) for c in cands),
            "rejected": dict(Counter(why for c, why in scene.rejected if c.obj_id == o.obj_id)),
            "labels": sum(sources.values()), **{s: sources.get(s, 0) for s in BORDERS},
            "unfilled": int(unfilled.get(o.obj_id, 0)), "moved": o.obj_id in scene.moved_objects,
        }  # fmt: skip
    for d in discoveries:
        per[names[d.obj_id]]["searched"] = {"found": d.pose is not None, "support": d.support, "takes": d.takes, "views": d.views}
    total = {k: sum(v[k] for v in per.values()) for k in ("candidates", "accepted", "labels", *BORDERS, "unfilled")}
    total["rejected"] = sum(sum(v["rejected"].values()) for v in per.values())
    return {"frames": len(candidates), "cameras_placed": len(scene.cameras), "odometry": scene.odometry,
            "moved": sorted(o.name for o in objects if o.obj_id in scene.moved_objects), "objects": per, "total": total}  # fmt: skip


def contact_sheet(path: str | Path, frames: Mapping[int, Frame], labels: Sequence[Label], objects: Sequence[ObjectSpec],
                  per_object: int = 8, tile: int = 112) -> Path:  # fmt: skip
    """Per object a row of up to `per_object` of its labels, spread over the recording, each its crop with the
    pose's axes (X, Y, Z red, green, blue) and a border in its source's colour; the row starts with its name."""
    rows = []
    for o in objects:
        mine = sorted((lab for lab in labels if lab.obj_id == o.obj_id), key=lambda lab: lab.im_id)
        picks = [mine[int(k)] for k in np.linspace(0, len(mine) - 1, min(per_object, len(mine))).astype(int)] if mine else []
        row = [_name_tile(o.name, len(mine), tile)]
        for lab in picks:
            row.append(_tile(frames[lab.im_id], lab, o, tile))
        row += [np.full((tile, tile, 3), 255, np.uint8)] * (per_object - len(picks))
        rows.append(np.hstack(row))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.vstack(rows))
    return path


def _tile(frame: Frame, lab: Label, spec: ObjectSpec, tile: int) -> np.ndarray:
    """The label's crop (a square around the object's projected size) with its axes and its source's border."""
    K = frame.K
    uv = (K @ lab.t)[:2] / lab.t[2]
    side = 1.4 * spec.diameter * K[0, 0] / lab.t[2]
    crop = instance_crop(cv2.cvtColor(frame.rgb(), cv2.COLOR_RGB2BGR), K, (uv[0] - side / 2, uv[1] - side / 2, side, side), tile, pad=1.0)
    image = np.ascontiguousarray(crop.patch)
    draw_axes(image, crop.K_patch, lab.R, lab.t, spec.axes.lengths, thickness=2)
    cv2.rectangle(image, (1, 1), (tile - 2, tile - 2), BORDERS[lab.source], 3)
    return image


def _name_tile(name: str, count: int, tile: int) -> np.ndarray:
    image = np.full((tile, tile, 3), 255, np.uint8)
    cv2.putText(image, name, (4, tile // 2 - 4), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(image, f"{count} labels", (4, tile // 2 + 16), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (80, 80, 80), 1, cv2.LINE_AA)
    return image
