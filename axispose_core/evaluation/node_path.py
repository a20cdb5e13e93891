"""The node's way from a frame to its poses (`tracking/poser.FramePoser`) as `evaluate`'s finder, so that a
validation of the localiser's pass measures what a robot gets in any `mode`, not only `stills`.

Each BOP scene is a stream: its frames in order (by image id), stamped by their place among the scene's images at
`FRAME_RATE`, through one `FramePoser` (a new one for each scene, so no track crosses scenes). A frame `evaluate`
skips (no instance that counts) is a gap in the stamps, as a frame the node dropped. The camera's pose goes with a
frame where scene_camera.json gives one (`cam_R_w2c`, as a rendered camera path writes it) and the mode wants it;
`video_odometry` searches lock-step in this process (`LockStepFinder`: each search's result on the next frame), so
a run repeats exactly.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from axispose_core.data.bop import camera_to_fixed
from axispose_core.data.bop_scene import BopScene
from axispose_core.estimator import Estimator
from axispose_core.evaluation.records import Prediction
from axispose_core.evaluation.run import predictions
from axispose_core.localiser.decode import Detection
from axispose_core.tracking.background import LockStepFinder
from axispose_core.tracking.poser import FramePoser, PoserSettings

FRAME_RATE = 30.0
"""Frames per second the stamps of a scene's frames are spaced by (a camera's nominal rate)."""


class NodePath:
    """`evaluate`'s finder (`run.Finder`): each frame through its scene's `FramePoser` with `settings`, its posed
    boxes as detections with their poses; what the posers count (`mode_<mode>`, `tracking_<event>`, ...) adds up
    in `counts`. `stop` ends the last scene's poser."""

    def __init__(self, estimator: Estimator, settings: PoserSettings) -> None:
        self.estimator, self.settings = estimator, settings
        self.published = {o.obj_id: o.name for o in estimator.config.objects}
        self.counts: dict[str, int] = {}
        self._poser: FramePoser | None = None
        self._scene: Path | None = None
        self._place: dict[int, int] = {}
        """The scene's image ids by their place in it."""

    def __call__(self, rgb: np.ndarray, K: np.ndarray, scene: BopScene, im_id: int) -> tuple[list[Detection], list[Prediction]]:
        if scene.root != self._scene:
            self.stop()
            finder = LockStepFinder(self.estimator)
            self._poser = FramePoser(self.estimator, self.published, self._count, finder=finder)
            self._scene, self._place = scene.root, {im: k for k, im in enumerate(scene.image_ids)}
        odometry = FramePoser.uses_odometry(self.settings) and im_id in scene.camera_poses
        camera = camera_to_fixed(*scene.camera_poses[im_id]) if odometry else None
        stamp = self._place[im_id] / FRAME_RATE
        posed = self._poser.pose(rgb, K, stamp, [], self.settings, lambda: False, camera)
        dets = [Detection(e.obj_id, score, (x + w / 2, y + h / 2), (w, h))
                for e, score, (x, y, w, h) in zip(posed.estimates, posed.scores, posed.boxes, strict=True)]  # fmt: skip
        return dets, predictions(posed.estimates)

    def stop(self) -> None:
        """End the poser of the scene run last (its search, in `video_odometry`)."""
        if self._poser is not None:
            self._poser.stop()
        self._poser, self._scene = None, None

    def _count(self, key: str, n: int) -> None:
        self.counts[key] = self.counts.get(key, 0) + n
