"""Tracking settings compared on rendered camera paths: the node's frame loop without ROS, per setting.

Each setting runs every scene (a BOP folder from `axispose synth --camera-path`, frames in order at `--fps`),
either single-frame (the localiser's boxes, each posed on its own: `{"tracking": false}`) or through a `Tracker`
whose `TrackingConfig` fields and `filter` (a `FilterConfig`) the setting gives; `"follow": true` follows the
tracks by their contours (`Estimator.follow`), the AGM posing only new and lost objects; `"refine": false` poses
without contour refinement; `"live": true` feeds the frames at `--fps` in real time, the newest taken whenever the
last is done (the node's latest-frame-wins), and scores only those it took; `"view_window": n` gives the tracker the
camera's pose the scene records (scene_camera.json's `cam_R_w2c`, as odometry would) to fuse each pose over its
object's views; `"background": true` runs the node's own poser (`axispose_core.tracking.poser.FramePoser`,
`video_odometry`: the localiser and the AGM in a process of their own) on frames delivered in real time at
`--fps`, the newest taken whenever the last is done, with the node's defaults but for the setting's
`redetect_period`, `view_window` and `follow_passes` (`"follow_passes": n` follows with the last n passes of the
refiner's schedule, in any setting); `"search_delay": n` runs that poser lock-step, its search in this process, each
search's result coming n frames after the frame it searched (`LockStepFinder`: the same run every time, unlike real
time); `[a, b]`: after a + b x the boxes it posed seconds.
Each GT instance is matched to the nearest pose of its object in its frame. Prints, per setting, ADD(-S)@0.1d and
Reproj@15px (mean over scenes), and per scene jitter (`tracking/jitter.py`), drift and recovery
(`tracking/stream_scores.py`; an instance's visibility counts the part of it outside the image as unseen), the median
and mean frame time and the share of frames processed, as one JSON line; `--out` writes them all.
`--there-and-back` plays each scene forward and then backward, so that its last frames are its first ones and drift
compares the same views.

    python bench/tracking_paths.py --scene V777/000000 --scene V778/000000 \\
        --setting '{"tracking": false}' --setting '{}' --setting '{"follow": true}'
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from axispose_core.data.bop_models import model_path
from axispose_core.data.bop_scene import BopScene
from axispose_core.data.meshes import load_ply
from axispose_core.estimator import SHIPPED_ESTIMATOR, EstimateOptions, Estimator
from axispose_core.evaluation.records import instance_scores, object_symmetries
from axispose_core.tracking.background import LockStepFinder
from axispose_core.tracking.config import TrackingConfig
from axispose_core.tracking.filter import FilterConfig
from axispose_core.tracking.jitter import PosePair, jitter
from axispose_core.tracking.poser import FramePoser, PoserSettings
from axispose_core.tracking.stream_scores import Seen, drift, recovery, visibility
from axispose_core.tracking.tracker import Tracker
from axispose_core.tracking.tracks import Sighting

Pose = tuple[int, np.ndarray, np.ndarray]


class Bench:
    def __init__(self, checkpoint: str, models: str, threshold: float, options: EstimateOptions, fps: float,
                 there_and_back: bool = False) -> None:  # fmt: skip
        self.est, self.checkpoint = Estimator.load(checkpoint), checkpoint
        self.specs = {o.obj_id: o for o in self.est.config.objects}
        self.points = {i: load_ply(model_path(models, i)).vertices for i in self.specs}
        self.syms = object_symmetries(self.specs.values(), self.points)
        self.threshold, self.options, self.fps, self.there_and_back = threshold, options, fps, there_and_back

    def _frames(self, scene: BopScene) -> list[int]:
        """The scene's images in the order played: forward, and with `there_and_back` back again (the last image
        once), so that the stream ends on the views it began with and drift compares like with like."""
        ids = list(scene.image_ids)
        return ids + ids[-2::-1] if self.there_and_back else ids

    def scene(self, setting: dict, scene: BopScene) -> dict:
        """One setting on one scene: its scores, jitter, frame time and the tracker's counts. With `"live": true`
        the frames come at `fps` whatever the time each takes, and the newest one is taken when the last is done
        (the node's latest-frame-wins): only those are posed and scored (`processed`, their share)."""
        if setting.get("background", False) or "search_delay" in setting:
            return self._background(setting, scene)
        tracker = self._tracker(setting) if setting.get("tracking", True) else None
        rows, pairs, times = [], [], []
        options = dataclasses.replace(self.options, refine=setting.get("refine", True), follow_passes=setting.get("follow_passes", 0))
        live, free, due = setting.get("live", False), 0.0, 0
        frames = self._frames(scene)
        cameras = [_camera_to_world(scene, im) for im in frames]
        for k, im in enumerate(frames):
            if live and k < due:
                continue
            rgb, K = scene.rgb(im), scene.cameras[im]
            start = time.perf_counter()
            poses = self._frame(rgb, K, k / self.fps, tracker, setting, options, cameras[k])
            times.append(time.perf_counter() - start)
            free = max(free, k / self.fps) + times[-1]
            due = int(np.floor(free * self.fps))  # the newest frame by the time this one is done
            self._score(scene, k, im, rgb.shape[:2], poses, rows, pairs)
        return self._summary(rows, pairs, times, len(frames), tracker.counts if tracker else {})

    def _background(self, setting: dict, scene: BopScene) -> dict:
        """The node's poser in `video_odometry`: frames delivered at `fps` in real time (frame k at k / fps
        after the first), the newest one taken whenever the last is done; or, with `search_delay`, every frame in
        turn, the search done in this process and handed over that many frames after the frame searched (the same
        run every time, for choosing between designs: live runs differ by the machine's timing)."""
        live = "search_delay" not in setting
        finder = None if live else LockStepFinder(self.est, _frames_late(setting["search_delay"], self.fps))
        poser, settings, counts = self._poser(setting, finder)
        if live:
            poser.start_background(settings, wait=120.0)  # the search process loaded before the first frame comes
        rows, pairs, times, k = [], [], [], 0
        frames, start = self._frames(scene), time.perf_counter()
        try:
            while k < len(frames):
                im = frames[k]
                if live:
                    time.sleep(max(0.0, start + k / self.fps - time.perf_counter()))
                rgb, began = scene.rgb(im), time.perf_counter()
                posed = poser.pose(rgb, scene.cameras[im], k / self.fps, [], settings, lambda: False, _camera_to_world(scene, im))
                times.append(time.perf_counter() - began)
                self._score(scene, k, im, rgb.shape[:2], [(e.obj_id, e.R, e.t) for e in posed.estimates if e.ok], rows, pairs)
                k = max(k + 1, int(np.floor((time.perf_counter() - start) * self.fps))) if live else k + 1  # live: the newest frame by now
        finally:
            poser.stop()
        return self._summary(rows, pairs, times, len(frames), counts)

    def _poser(self, setting: dict, finder: LockStepFinder | None = None) -> tuple[FramePoser, PoserSettings, dict[str, int]]:
        """The node's poser and settings for background detection (searching with `finder`, None: the node's
        process): its defaults but for the setting's `redetect_period`, `view_window` and `follow_passes`; and the
        counts it reports."""
        chosen = {k: setting.get(k, default) for k, default in (("redetect_period", 5), ("view_window", 80), ("follow_passes", 0))}
        settings = PoserSettings(**chosen, checkpoint=self.checkpoint, mode="video_odometry", ddim_steps=self.options.steps,
                                 num_threads=torch.get_num_threads())  # fmt: skip
        counts: dict[str, int] = {}
        poser = FramePoser(
            self.est, {i: str(i) for i in self.specs}, lambda key, n: counts.__setitem__(key, counts.get(key, 0) + n), finder=finder
        )
        return poser, settings, counts

    def _score(self, scene: BopScene, k: int, im: int, size: tuple[int, int], poses: list[Pose], rows: list[Seen],
               pairs: list[PosePair]) -> None:  # fmt: skip
        """Each GT instance of frame `k` (image `im`, of `size`) against the nearest pose of its object."""
        K = scene.cameras[im]
        visible = {id(g): info.visib_fract for g, info in scene.instances(im)}
        for g in scene.gt[im]:
            if g.obj_id not in self.specs:
                continue
            pose = _nearest(poses, g.obj_id, g.t)
            s = instance_scores(self.specs[g.obj_id], self.points[g.obj_id], K, g.R, g.t, pose, self.syms.get(g.obj_id, ()))
            seen = visibility(visible.get(id(g), 1.0), K, g.R, g.t, self.points[g.obj_id], size)
            rows.append(Seen(k, g.obj_id, seen, s["add_0.1d"], s["reproj_15px"]))
            if pose is not None:
                pairs.append(PosePair(k, g.obj_id, *pose, g.R, g.t))

    def _summary(self, rows: list[Seen], pairs: list[PosePair], times: list[float], frames: int, counts: dict) -> dict:
        return {"add": float(np.mean([r.add for r in rows])), "rp15": float(np.mean([r.rp15 for r in rows])), **jitter(pairs, self.syms),
                **drift(rows), **recovery(rows), "frame_ms": 1000 * float(np.median(times[1:])),
                "frame_ms_mean": 1000 * float(np.mean(times[1:])), "processed": len(times) / frames, "counts": counts}  # fmt: skip

    def _tracker(self, setting: dict) -> Tracker:
        fields = {k: v for k, v in setting.items() if k in TrackingConfig.__dataclass_fields__ and k != "filter"}
        return Tracker(TrackingConfig(**fields, filter=FilterConfig(**setting.get("filter", {}))))

    def _frame(self, rgb: np.ndarray, K: np.ndarray, stamp: float, tracker: Tracker | None, setting: dict, options,
               camera: np.ndarray | None = None) -> list[Pose]:  # fmt: skip
        if tracker is None:  # as the node: the localiser's objects, rescored by the verifier where there is one
            found = self.est.find(rgb, K, self.threshold, options)
            return [(d.obj_id, e.R, e.t) for d, e in zip(found.detections, found.poses, strict=True) if e.ok]

        following, verifier = setting.get("follow", False), self.est.config.verifier

        def detect() -> list:
            """As the node's tracker gets them: posed and verified where the checkpoint has a verifier, unless
            following (then the new ones are verified once posed)."""
            if verifier is None or following:
                return self.est.detect(rgb, self.threshold if verifier is None else verifier.min_score)
            found = self.est.find(rgb, K, self.threshold, options)
            return [Sighting(d.obj_id, d.score, d.box, p) for d, p in zip(found.detections, found.poses, strict=True)]

        def measure(crops: list) -> list:
            out = self.est.estimate(rgb, K, [(c.obj_id, c.box) for c in crops], options=options)
            if following:
                new = [k for k, c in enumerate(crops) if c.detected]
                for k, p in zip(new, self.est.verified([crops[k].score for k in new], [out[k] for k in new], self.threshold), strict=True):
                    out[k] = p
            return out

        def follow(last: list, predicted: list) -> list:
            return self.est.follow(rgb, K, last, predicted, options)

        tracked = tracker.step(stamp, K, detect, measure, follow if following else None, camera)
        return [(p.obj_id, p.R, p.t) for p in tracked]


def _frames_late(delay: int | list[float], fps: float) -> Callable[[int], int]:
    """Frames from a search's frame to the one it is handed to, by the boxes it posed: `delay` frames, or [a, b]: a +
    b x boxes seconds."""
    if isinstance(delay, list):
        a, b = delay
        return lambda boxes: max(1, int(np.ceil(fps * (a + b * boxes))))
    return lambda boxes: max(1, int(delay))


def _camera_to_world(scene: BopScene, im_id: int) -> np.ndarray | None:
    """The camera's pose in the scene's world frame (4x4, camera to world) where the scene records one."""
    if im_id not in scene.camera_poses:
        return None
    R, t = scene.camera_poses[im_id]
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R.T, -R.T @ t
    return T


def _nearest(poses: list[Pose], obj_id: int, t_gt: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The pose of `obj_id` nearest t_gt, taken out of `poses` (one GT instance per pose)."""
    mine = [i for i, p in enumerate(poses) if p[0] == obj_id]
    if not mine:
        return None
    _, R, t = poses.pop(min(mine, key=lambda i: np.linalg.norm(poses[i][2] - t_gt)))
    return R, t


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", action="append", required=True, help="BOP scene folder (repeat)")
    ap.add_argument("--setting", action="append", default=None, help="JSON setting (repeat; default: the tracker's)")
    ap.add_argument("--checkpoint", default=str(SHIPPED_ESTIMATOR))
    ap.add_argument("--models", default="../shared/data/lmo/models_eval")
    ap.add_argument("--fps", type=float, default=15.0)
    ap.add_argument("--steps", type=int, default=3)
    ap.add_argument("--threshold", type=float, default=0.3)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--there-and-back", action="store_true", help="play each scene forward, then backward (drift on the same views)")
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    options = EstimateOptions(steps=args.steps, max_boxes=8)
    bench = Bench(args.checkpoint, args.models, args.threshold, options, args.fps, args.there_and_back)
    scenes = [BopScene(Path(s)) for s in args.scene]
    rows = []
    for setting in [json.loads(s) for s in args.setting or ["{}"]]:
        per = [bench.scene(setting, sc) for sc in scenes]
        row = {"setting": setting, "add": float(np.mean([r["add"] for r in per])),
               "rp15": float(np.mean([r["rp15"] for r in per])), "scenes": per}  # fmt: skip
        rows.append(row)
        print(json.dumps(row), flush=True)
    if args.out:
        args.out.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
