"""How right an adaptation round's pseudo-poses are, measured against a recording's ground truth (which adaptation
never reads): per object and in all, the candidates, those accepted on their own evidence, and the labels by source
(checked, filled, alone), each as right / all, where right is within 2 cm and 15 degrees of the truth (up to the
object's symmetries), and those turned more than 30 degrees from it; and the share of the annotated instances (at
least 10 % visible) that got a label.

    python bench/adapt_labels.py OUT/round0 --truth SCENE_FOLDER [--json results.json]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from axispose_core.adapt.geometry import IDENTITY, ObjectGeometry, rotation_gap_deg
from axispose_core.adapt.labels import Label
from axispose_core.adapt.pseudo import AcceptConfig, read_candidates
from axispose_core.data.bop_scene import BopScene
from axispose_core.data.visibility import gt_info_from_models
from axispose_core.estimator import Estimator
from axispose_core.lmo import SHARED_LMO

RIGHT_M, RIGHT_DEG = 0.02, 15.0
FLIP_DEG = 30.0


def nearest_error(obj_id: int, R: np.ndarray, t: np.ndarray, truths: list, geometry: ObjectGeometry) -> tuple[float, float]:
    """(translation m, rotation deg) to the nearest annotated instance of the object in the frame (inf without)."""
    errs = [(float(np.linalg.norm(t - g.t)), rotation_gap_deg(R, g.R, geometry)) for g in truths if g.obj_id == obj_id]
    return min(errs, default=(float("inf"), 180.0))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("round", help="an adaptation round's folder (OUT/round<k>)")
    parser.add_argument("--truth", required=True, help="the recording's BOP scene folder with its scene_gt.json")
    parser.add_argument("--checkpoint", default=None, help="for the objects and their symmetries (default: the shipped one)")
    parser.add_argument("--models", default=str(SHARED_LMO / "models"))
    parser.add_argument("--json", default=None)
    args = parser.parse_args()
    from axispose_core.adapt.run import object_geometry

    est = Estimator.load(args.checkpoint or Path("axispose_core/models/axispose_lmo.safetensors"))
    geometry = object_geometry(est)
    names = {o.obj_id: o.name for o in est.config.objects}
    scene = BopScene(Path(args.truth), gt_info_from_models(args.models))
    folder = Path(args.round)
    state = json.loads((folder.parent / "adapt.json").read_text())
    accept = AcceptConfig(**state["config"]["accept"])
    cands = read_candidates(folder / "candidates.jsonl")
    labels = [Label.from_json(d) for d in json.loads((folder / "labels" / "labels.json").read_text())]
    rows: dict[str, dict[str, list[int]]] = {}
    flips: dict[str, list[int]] = {}

    def count(obj_id: int, kind: str, right: bool) -> None:
        cell = rows.setdefault(names[obj_id], {}).setdefault(kind, [0, 0])
        cell[0] += int(right)
        cell[1] += 1

    def is_right(im_id: int, obj_id: int, R: np.ndarray, t: np.ndarray, kind: str = "") -> bool:
        dt, dr = nearest_error(obj_id, R, t, scene.gt.get(im_id, []), geometry.get(obj_id, ObjectGeometry(1.0, IDENTITY)))
        if kind:
            flips.setdefault(kind, [0, 0])[0] += int(dr > FLIP_DEG)
            flips[kind][1] += 1
        return dt <= RIGHT_M and dr <= RIGHT_DEG

    for im_id, cs in cands.items():
        for c in cs:
            count(c.obj_id, "candidates", is_right(im_id, c.obj_id, c.R, c.t, "candidates"))
            if accept.accepts(c):
                count(c.obj_id, "accepted", is_right(im_id, c.obj_id, c.R, c.t, "accepted"))
    labelled = set()
    for lab in labels:
        right = is_right(lab.im_id, lab.obj_id, lab.R, lab.t, "labels")
        is_right(lab.im_id, lab.obj_id, lab.R, lab.t, lab.source)
        count(lab.obj_id, "labels", right)
        count(lab.obj_id, lab.source, right)
        labelled.add((lab.im_id, lab.obj_id))
    for im_id in cands:
        for g, info in scene.instances(im_id):
            if info.visib_fract >= 0.1:
                count(g.obj_id, "visible instances labelled", (im_id, g.obj_id) in labelled)
    kinds = ["candidates", "accepted", "labels", "checked", "filled", "alone", "visible instances labelled"]
    total = {k: [sum(r.get(k, [0, 0])[i] for r in rows.values()) for i in (0, 1)] for k in kinds}
    print(f"{'object':<12} " + " ".join(f"{k.split()[0]:>12}" for k in kinds))
    for name, r in [*sorted(rows.items()), ("all", total)]:
        print(f"{name:<12} " + " ".join(f"{r.get(k, [0, 0])[0]:>5}/{r.get(k, [0, 0])[1]:<6}" for k in kinds))
    print("turned more than 30 degrees: " + ", ".join(f"{k} {v[0]}/{v[1]}" for k, v in flips.items()))
    print(f"right: within {RIGHT_M * 100:.0f} cm and {RIGHT_DEG:.0f} degrees of the truth; the last column: annotated instances "
          "at least 10 % visible that got a label")  # fmt: skip
    if args.json:
        Path(args.json).write_text(json.dumps({"round": str(folder), "rows": rows, "all": total, "turned": flips}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
