"""Tracking across a camera stream, one `Tracker.step` a frame, scheduling the tracker's parts: the tracks and their
filters (`tracks`), following by contours where the estimator can (`follow`), the views in the camera's fixed frame
(`fixed_frame`) and the localiser's search (`search`).

Where the estimator can follow objects by their contours, every track is followed and the AGM poses only new
detections and the tracks whose contour was lost. Otherwise every tracked object is posed by the estimator, from the
crop its predicted pose gives or the localiser's box where the localiser runs: every crop goes through the estimator
in one batch. All tracks end when the stamps go backwards (a looped bag) or the camera's intrinsics change. With the
localiser and the AGM elsewhere (`observe`, `challenge`), `step` without `detect` only follows and recalls.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from axispose_core.tracking.config import TrackingConfig
from axispose_core.tracking.fixed_frame import FixedFrame
from axispose_core.tracking.follow import Follower, Following, follow_together
from axispose_core.tracking.search import detection_due, unfound_dropped, with_detections
from axispose_core.tracking.tracks import Crop, Detected, Measurement, TrackedPose, Tracks


def _measurements(crops: list[Crop], estimate: Callable[[list[Crop]], Sequence[Measurement]]) -> list[Measurement]:
    """Each crop's pose: the one it came with, else the estimator's (one call for all the others)."""
    todo = [c for c in crops if c.measurement is None]
    fresh = list(estimate(todo)) if todo else []
    if len(fresh) != len(todo):
        raise ValueError(f"the estimator gave {len(fresh)} poses for {len(todo)} crops")
    posed = iter(fresh)
    return [c.measurement if c.measurement is not None else next(posed) for c in crops]


class Tracker(Tracks):
    """`step(stamp, K, detect, estimate)` per frame: tracks' crops (and the localiser's, when it runs) through
    the estimator, the poses into the tracks' filters, the tracks' filtered poses out. `counts` tallies what
    happened (resets, refused measurements, tracks started and ended) for diagnostics."""

    def __init__(self, config: TrackingConfig) -> None:
        super().__init__(config)
        self._stamp: float | None = None
        self._K: np.ndarray | None = None
        self._following = Following(self)
        self._fixed = FixedFrame(self)

    def reset(self, reason: str) -> None:
        """End every track (counted as `reset_<reason>`) and forget every view."""
        if self.tracks:
            self.count(f"reset_{reason}")
        self.tracks = []
        self.frame = 0
        self._fixed.forget()
        self._following.forget()

    def step(
        self,
        stamp: float,
        K: np.ndarray,
        detect: Callable[[], Sequence[Detected]] | None,
        estimate: Callable[[list[Crop]], Sequence[Measurement]],
        follow: Follower | None = None,
        camera: np.ndarray | None = None,
    ) -> list[TrackedPose]:
        """One frame: resets and timeouts, prediction, the tracks followed by their contours (with `follow`), the
        localiser where due (never without `detect`: a lost track then ends), one estimator batch (of the crops
        without a pose), the updates; with `camera`, the camera's pose in a fixed frame (4x4, camera to fixed), and
        `view_window`, poses fused over their objects' views, tracks followed from their poses in that frame and
        objects no track holds looked for there."""
        self._start_frame(stamp, K)
        camera = np.asarray(camera, float) if camera is not None and np.all(np.isfinite(camera)) else None
        held = {tr.obj_id for tr in self.tracks}
        following = (self._following.followed(K, stamp, camera), self._fixed.recalled(K, stamp, camera, held))
        out = follow_together(follow, *following) if follow is not None else []
        followed = {pose.track_id for pose in out}
        detecting = detect is not None and detection_due(self, following=follow is not None)
        crops = self.due_crops(K, every=detecting, skip=followed)
        if detecting:
            crops = with_detections(self, crops, detect(), [tr for tr in self.tracks if tr.id in followed], K)
            self.count("localiser_runs")
        crops = unfound_dropped(self, crops)
        measurements = _measurements(crops, estimate)
        if follow is not None:
            self.count("frames_estimated" if crops else "frames_followed")
        for crop, m in zip(crops, measurements, strict=True):
            if crop.checks is None:
                out.append(self.measure(crop, m, K, stamp))
            else:
                self._following.check(crop.checks, m, camera)
        cropped = {c.track for c in crops} | followed
        quiet = [tr for tr in self.tracks if tr.id not in cropped and not tr.measured and not tr.lost and tr.last is not None]
        out += [self.predicted(tr, K) for tr in quiet]
        self.end_tracks()
        poses = self._fixed.over_views([pose for pose in out if pose is not None], camera)
        self.frame += 1
        return poses

    def observe(self, camera: np.ndarray, posed: Sequence[tuple[Detected, Measurement]]) -> int:
        """Poses made elsewhere on an earlier frame whose camera pose (4x4, camera to fixed) was `camera` (the
        localiser and the AGM in a process of their own): each joins its object's views, from where the next `step`
        follows an object no track holds (at once, however recently it was not found there; the tracks away from
        them are challenged once the search's poses are all in: `challenge`). Returns how many joined (none without
        `view_window`, a finite camera pose, or an `ok` pose)."""
        return self._fixed.observe(np.asarray(camera, float), posed)

    def challenge(self, camera: np.ndarray, posed: Sequence[tuple[Detected, Measurement]]) -> None:
        """Every pose one search made elsewhere (`observe`; the camera's pose at its frame, 4x4, camera to fixed): a
        track whose object it posed beyond `view_gate` of the track's pose (once: two poses of it may be two
        instances) is challenged: the next frame follows that pose beside the track's, and the one whose contour
        agrees more goes on (`Following.followed`), so a track stuck on a wrong pose its contour half agrees with is
        put right by the AGM's next pose of its object."""
        camera = np.asarray(camera, float)
        self._following.challenge(camera, self._fixed.placeable(camera, posed))

    def _start_frame(self, stamp: float, K: np.ndarray) -> None:
        """A new frame: everything reset where the stamps went backwards or the intrinsics changed, then the tracks
        timed out end and the others are predicted to `stamp`."""
        if self._stamp is not None and stamp < self._stamp:
            self.reset("stamps_backwards")
        if self._K is not None and not np.allclose(K, self._K):
            self.reset("camera_changed")
        self._stamp, self._K = stamp, np.array(K, float)
        self.predict(stamp)
