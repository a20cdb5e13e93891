"""The search for the objects no frame accepted (`adapt/search.py`), scored against the truth (read only to score):
the consistency stage on a recording's candidates (posed by the checkpoint first where the log is missing), the
objects of --drop taken out of every frame's candidates (never accepted), the search at its defaults, and per object
searched its support, takes and, where found, how far its place lies from the truth and how many of its fills in
every fourth placed frame are right (within 2 cm and 15 degrees); and how well its contour, refined from its
annotated pose in the searched frames, agrees with them (what the search's contour check would see at the truth).

    python bench/adapt_search.py RECORDING --candidates LOG [--drop 9] [--out results.json]
    python bench/adapt_search.py --desk DIR [--seed 93] [--frames 48] [--objects 1,5,8,9,11]

--desk first renders DIR/render/000000: recoloured objects (`data/recolour.py`) resting on a table among clutter,
the camera circling them 3 degrees a frame (the `desk` recipe), and measures on it.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import numpy as np

from axispose_core.adapt.geometry import inverse, rotation_gap_deg
from axispose_core.adapt.labels import FillConfig, label_frame, prior
from axispose_core.adapt.pseudo import AcceptConfig, PoseSettings, pose_frames, read_candidates
from axispose_core.adapt.recording import read_recording
from axispose_core.adapt.run import object_geometry
from axispose_core.adapt.scene import ConsistencyConfig, consistent
from axispose_core.adapt.search import Scene, SearchConfig, search, spread, with_discoveries
from axispose_core.estimator import SHIPPED_ESTIMATOR, Estimator
from axispose_core.lmo import SHARED_LMO
from axispose_core.refine.refiner import Start


def render_desk(out: Path, seed: int, frames: int, objects: tuple[int, ...]) -> Path:
    from axispose_core.data.recolour import recoloured_models
    from axispose_core.data.synth.config import CameraPathConfig, SynthConfig, recipe
    from axispose_core.data.synth.generate import generate

    scene, randomization = recipe("desk")
    scene = dataclasses.replace(scene, table_prob=1.0)
    models = recoloured_models(SHARED_LMO / "models", out / "models", seed)
    cfg = SynthConfig(seed=seed, scenes=1, images_per_scene=frames, objects=objects, scene=scene, randomization=randomization,
                      camera_path=CameraPathConfig(orbit_deg=3.0))  # fmt: skip
    generate(cfg, models, out / "render", workers=2)
    return out / "render" / "000000"


def truth_of(gt: dict, f: int, obj_id: int) -> tuple[np.ndarray, np.ndarray] | None:
    g = [x for x in gt.get(str(f), []) if x["obj_id"] == obj_id]
    return (np.asarray(g[0]["cam_R_m2c"], float).reshape(3, 3), np.asarray(g[0]["cam_t_m2c"], float) / 1000) if g else None


def truth_agreement(est: Estimator, frames: dict, scene, gt: dict, obj_id: int, views: list[int], fill: FillConfig) -> list[float]:
    """The object's refined contour agreement in each of the views, started at its annotated pose (the scene's
    other predictions of the frame masking it, as in a fill)."""
    out = []
    for f in views:
        if (truth := truth_of(gt, f, obj_id)) is None:
            continue
        starts = [Start(p.obj_id, p.R, p.t, prior(p.R, p.t, fill)) for p in scene.predictions.get(f, [])]
        starts.append(Start(obj_id, truth[0], truth[1], prior(truth[0], truth[1], fill)))
        r = est.refiner.refine(frames[f].rgb(), frames[f].K, starts)[-1]
        out.append(float(r.agreement) if r.refined else float("nan"))
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("recording", nargs="?")
    parser.add_argument("--candidates", help="the round's candidates.jsonl (written here where missing)")
    parser.add_argument("--checkpoint", default=str(SHIPPED_ESTIMATOR))
    parser.add_argument("--drop", default="", help="object ids taken out of every frame's candidates")
    parser.add_argument("--desk", help="render a desk recording of recoloured objects into DIR and measure on it")
    parser.add_argument("--seed", type=int, default=93)
    parser.add_argument("--frames", type=int, default=48)
    parser.add_argument("--objects", default="1,5,8,9,11")
    parser.add_argument("--out")
    args = parser.parse_args()
    if args.desk:
        root = Path(args.desk) / "render" / "000000"
        if not root.is_dir():
            render_desk(Path(args.desk), args.seed, args.frames, tuple(int(x) for x in args.objects.split(",")))
        recording, log = root, Path(args.candidates or Path(args.desk) / "candidates.jsonl")
    else:
        recording, log = Path(args.recording), Path(args.candidates)
    est = Estimator.load(args.checkpoint)
    est.set_precision("float32")
    geometry = object_geometry(est)
    rec = read_recording(recording)
    if not log.exists():
        pose_frames(est, rec.frames, PoseSettings(), log)
    drop = {int(x) for x in args.drop.split(",") if x}
    cands = {f: [c for c in cs if c.obj_id not in drop] for f, cs in read_candidates(log).items()}
    odometry = {f.im_id: f.camera for f in rec.frames} if rec.has_odometry else None
    consistency, fill = ConsistencyConfig(), FillConfig()
    scene = consistent(cands, geometry, AcceptConfig(), consistency, odometry)
    frames = {f.im_id: f for f in rec.frames}
    found = search(Scene(est, frames, scene, geometry, consistency, fill), SearchConfig())
    filled = with_discoveries(scene, found)
    gt = json.loads((recording / "scene_gt.json").read_text())
    rows = []
    for d in found:
        row = {"obj_id": d.obj_id, "support": d.support, "takes": d.takes, "views": d.views, "found": d.pose is not None,
               "present": any(x["obj_id"] == d.obj_id for xs in gt.values() for x in xs)}  # fmt: skip
        if d.pose is not None and row["present"]:
            errors, right, fills = [], 0, 0
            for f in sorted(scene.cameras):
                if (truth := truth_of(gt, f, d.obj_id)) is not None:
                    T = inverse(scene.cameras[f]) @ d.pose
                    errors.append((np.linalg.norm(T[:3, 3] - truth[1]), rotation_gap_deg(T[:3, :3], truth[0], geometry[d.obj_id])))
            for f in sorted(scene.cameras)[::4]:
                predictions = filled.predictions.get(f, [])
                labels = label_frame(est.refiner, frames[f].rgb(), frames[f].K, predictions, [], geometry, consistency, fill)
                for lab in (lab for lab in labels if lab.obj_id == d.obj_id):
                    fills += 1
                    truth = truth_of(gt, f, d.obj_id)
                    near = truth is not None and np.linalg.norm(lab.t - truth[1]) < 0.02
                    right += near and rotation_gap_deg(lab.R, truth[0], geometry[d.obj_id]) < 15
            row |= {"place_error_m": float(np.median([e[0] for e in errors])), "place_error_deg": float(np.median([e[1] for e in errors])),
                    "fills": fills, "fills_right": int(right), "frames_checked": len(sorted(scene.cameras)[::4])}  # fmt: skip
        if row["present"]:
            agreement = truth_agreement(est, frames, scene, gt, d.obj_id, spread(sorted(scene.cameras), d.views), fill)
            row["truth_agreement"] = [round(a, 3) for a in agreement if np.isfinite(a)]
            row["truth_unrefined"] = int(np.sum(~np.isfinite(agreement)))
        print(row, flush=True)
        rows.append(row)
    if args.out:
        Path(args.out).write_text(json.dumps({"recording": str(recording), "drop": sorted(drop), "objects": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
