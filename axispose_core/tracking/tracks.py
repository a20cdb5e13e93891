"""Tracks across a camera stream: each object instance keeps an id, a filtered pose and the box it is cropped from.

A tracked object's crop comes from its predicted pose (the box it had, moved with the pose's projection and scaled
with its depth). Each pose the estimator gives for it is a measurement for its track's `PoseFilter` (a detection the
caller has posed already, a `Sighting`, brings its pose and is not posed again); with `measure_every` n the tracks
take turns between localiser runs, the others publishing their filters' predictions. Tracks end after
`track_timeout` seconds without a measurement, `max_misses` frames in a row without a pose, or `max_unseen`
localiser runs in a row that do not find them (`search`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from axispose_core.tracking.config import TrackingConfig
from axispose_core.tracking.filter import PoseFilter

Box = tuple[float, float, float, float]
"""(x, y, w, h) in image pixels."""
MIN_DEPTH = 0.05
"""A track whose predicted depth (m) falls below this ends: its filter has run off."""


class Measurement(Protocol):
    """What the tracker reads of an estimator's pose (`pose_estimate.PoseEstimate` is one)."""

    ok: bool
    R: np.ndarray
    t: np.ndarray
    covariance: np.ndarray | None


class Detected(Protocol):
    """What the tracker reads of a localiser's detection (`localiser.decode.Detection` is one)."""

    obj_id: int
    score: float

    @property
    def box(self) -> Box: ...


@dataclass(frozen=True)
class Sighting:
    """A detection with the pose its caller made of its box (e.g. to verify it, `Estimator.find`): the tracker takes
    that pose as the measurement of the detection's crop instead of posing the box again."""

    obj_id: int
    score: float
    box: Box
    measurement: Measurement


@dataclass(frozen=True)
class Crop:
    """One box to estimate: a track's (`track` its id) or a new detection's;
    `measurement`: its pose where a `Sighting` brought one (the estimator is not asked)."""

    obj_id: int
    box: Box
    score: float
    track: int | None = None
    measurement: Measurement | None = None
    detected: bool = False
    """The box is the localiser's on this frame (a caller verifies such poses where it verifies detections)."""
    checks: int | None = None
    """The id of the followed track this localiser's box found: its pose checks the track's (`Following.check`)."""


@dataclass
class Track:
    id: int
    obj_id: int
    filter: PoseFilter
    box: Box
    """The box the object was last cropped from."""
    anchor: tuple[np.ndarray, float]
    """The box's centre minus the pose's projection (px), and the depth (m), when `box` was set."""
    score: float
    stamp: float
    """The filter's time (s)."""
    updated: float
    """When a measurement was last accepted (s)."""
    misses: int = 0
    rejects: int = 0
    unseen: int = 0
    measured: bool = False
    """This frame gave a pose (accepted or refused at the gate)."""
    last: Measurement | None = None
    """The latest pose the estimator gave for it."""
    lost: bool = False
    """Its contour was lost on this frame: the AGM's pose re-initialises it."""
    held: int = 0
    """Frames its contour has held since the AGM last posed it."""
    checked: int = -1
    """The frame its pose was last checked against the AGM's pose of a localiser's box (`Following.check`)."""
    fixed: tuple[np.ndarray, np.ndarray] | None = None
    """Its latest published pose in the camera's fixed frame (`view_window`): where it is followed from next, moved
    into the camera by the camera's own motion (the filter's constant velocity does not know where a hand-held
    camera turns, nor how far when frames are dropped)."""


@dataclass(frozen=True)
class TrackedPose:
    """One track's output for a frame: its filtered pose and covariance, and the frame's raw measurement."""

    track_id: int
    obj_id: int
    R: np.ndarray
    t: np.ndarray
    covariance: np.ndarray
    score: float
    measurement: Measurement
    accepted: bool
    """The measurement went into the filter (False: refused at the gate, or not measured; the pose is the
    prediction)."""
    box: Box
    """The box the object was cropped from."""
    measured: bool = True
    """The track was posed on this frame (False: not its turn, `measure_every`; `measurement` is its latest)."""


def project(K: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Where a camera-frame point (m) lies in the image (px)."""
    p = K @ t
    return p[:2] / p[2]


class Tracks:
    """The live tracks (`tracks`): each pose into its track's filter, tracks started and ended. `counts` tallies what
    happened (resets, refused measurements, tracks started and ended) for diagnostics."""

    def __init__(self, config: TrackingConfig) -> None:
        self.config = config
        self.tracks: list[Track] = []
        self.counts: dict[str, int] = {}
        self.frame = 0
        """Frames stepped since the start or the last reset."""
        self.look = False
        """A track ended: look for its object on the next frame."""
        self._next_id = 1

    def predict(self, stamp: float) -> None:
        """The tracks timed out end; the others' filters predict their poses at `stamp`."""
        self.end("timeout", lambda tr: stamp - tr.updated > self.config.track_timeout)
        for tr in self.tracks:
            tr.filter.predict(stamp - tr.stamp)
            tr.stamp, tr.measured, tr.lost = stamp, False, False
        self.end("behind", lambda tr: tr.filter.t[2] <= MIN_DEPTH)  # a filter run off behind the camera

    def predicted_box(self, tr: Track, K: np.ndarray) -> Box:
        """Where the track is cropped from on this frame: its box moved with its predicted pose's projection and
        scaled with its depth."""
        offset, z = tr.anchor
        scale = z / tr.filter.t[2] if tr.filter.t[2] > 0 else 1.0
        cx, cy = project(K, tr.filter.t) + offset * scale
        w, h = tr.box[2] * scale, tr.box[3] * scale
        return (cx - w / 2, cy - h / 2, w, h)

    def due_crops(self, K: np.ndarray, every: bool, skip: set[int]) -> list[Crop]:
        """The crops of the tracks whose turn it is (`measure_every`), or of `every` track, but those followed
        (`skip`): a track its contour lost, every time."""
        n = max(1, self.config.measure_every)
        due = [tr for tr in self.tracks if tr.id not in skip and (every or tr.lost or (self.frame + tr.id) % n == 0)]
        return [Crop(tr.obj_id, self.predicted_box(tr, K), tr.score, tr.id) for tr in due]

    def predicted(self, tr: Track, K: np.ndarray) -> TrackedPose:
        """A track not posed this frame: its filter's prediction, in the box it would be cropped from."""
        f = tr.filter
        return TrackedPose(tr.id, tr.obj_id, f.R.copy(), f.t.copy(), f.covariance, tr.score, tr.last, False,
                           self.predicted_box(tr, K), measured=False)  # fmt: skip

    def noise(self, m: Measurement) -> np.ndarray:
        """A pose's noise: its covariance, else `fallback_std`'s (where it has none, or not a finite one)."""
        if m.covariance is not None and np.all(np.isfinite(m.covariance)):
            return np.asarray(m.covariance, float)
        rel, rot = self.config.fallback_std
        return np.diag([(rel * m.t[2]) ** 2] * 3 + [rot**2] * 3)

    def measure(self, crop: Crop, m: Measurement, K: np.ndarray, stamp: float) -> TrackedPose | None:
        """A crop's pose into its track's filter (or an unmeasured track of its object this near, `same_distance`,
        else a new track's): the track's pose out; None where the estimator refused it (the track missed a frame)."""
        tr = self.track(crop.track)
        if not m.ok:
            if tr is not None:
                tr.misses += 1
            return None
        cov = self.noise(m)
        tr = tr or self._nearby_track(crop.obj_id, m.t)
        if tr is None:
            tr = self.start_track(crop, m, cov, stamp)
            return self.output(tr, m, True, K, crop.box)
        if tr.lost:  # its contour lost it: the AGM's pose starts it again (the next frame's contour judges it)
            tr.lost, tr.held, tr.checked = False, 0, self.frame
            tr.filter = PoseFilter.start(self.config.filter, m.R, m.t, cov)
            tr.misses, tr.measured, tr.score, tr.last, tr.updated = 0, True, crop.score, m, stamp
            self.count("tracks_reinitialised")
            return self.output(tr, m, True, K, crop.box)
        tr.misses, tr.measured, tr.score, tr.last = 0, True, crop.score, m
        if (information := getattr(m, "contour_information", None)) is not None:  # followed from the prediction
            accepted, _ = tr.filter.update_posterior(m.R, m.t, information)
        else:
            accepted, _ = tr.filter.update(m.R, m.t, cov)
        if accepted:
            tr.rejects, tr.updated = 0, stamp
        else:
            tr.rejects += 1
            self.count("measurements_gated")
            if tr.rejects >= self.config.reinit_after:
                tr.filter = PoseFilter.start(self.config.filter, m.R, m.t, cov)
                tr.rejects, tr.updated, accepted = 0, stamp, True
                self.count("tracks_restarted")
        return self.output(tr, m, accepted, K, crop.box)

    def track(self, track_id: int | None) -> Track | None:
        """The live track of this id (None: no id, or it ended)."""
        return next((tr for tr in self.tracks if tr.id == track_id), None) if track_id is not None else None

    def _nearby_track(self, obj_id: int, t: np.ndarray) -> Track | None:
        near = [tr for tr in self.tracks if tr.obj_id == obj_id and not tr.measured
                and np.linalg.norm(tr.filter.t - t) < self.config.same_distance * t[2]]  # fmt: skip
        return min(near, key=lambda tr: np.linalg.norm(tr.filter.t - t), default=None)

    def start_track(self, crop: Crop, m: Measurement, cov: np.ndarray, stamp: float) -> Track:
        """A new track of the crop's object at the pose `m`."""
        tr = Track(self._next_id, crop.obj_id, PoseFilter.start(self.config.filter, m.R, m.t, cov), crop.box,
                   (np.zeros(2), 1.0), crop.score, stamp, stamp, measured=True, last=m, checked=self.frame)  # fmt: skip
        self._next_id += 1
        self.tracks.append(tr)
        self.count("tracks_started")
        return tr

    def output(self, tr: Track, m: Measurement, accepted: bool, K: np.ndarray, box: Box) -> TrackedPose:
        """The track's pose out; the crop's box becomes the track's, anchored to the filtered pose."""
        centre = np.array([box[0] + box[2] / 2, box[1] + box[3] / 2])
        tr.box, tr.anchor = box, (centre - project(K, tr.filter.t), float(tr.filter.t[2]))
        f = tr.filter
        return TrackedPose(tr.id, tr.obj_id, f.R.copy(), f.t.copy(), f.covariance, tr.score, m, accepted, box)

    def end_tracks(self) -> None:
        """End the tracks without a pose `max_misses` frames in a row or not found by `max_unseen` localiser runs."""
        self.end("misses", lambda tr: tr.misses >= self.config.max_misses)
        self.end("unseen", lambda tr: tr.unseen >= self.config.max_unseen, look=False)

    def end(self, reason: str, ends: Callable[[Track], bool], look: bool = True) -> None:
        """End the tracks for which `ends` holds (counted as `ended_<reason>`); with `look`, run the localiser on the
        next frame to find their objects again (not for tracks it has just not found: that would run it on every
        frame while false detections start and end tracks)."""
        kept = [tr for tr in self.tracks if not ends(tr)]
        self.count(f"ended_{reason}", len(self.tracks) - len(kept))
        self.look |= look and len(kept) < len(self.tracks)
        self.tracks = kept

    def count(self, key: str, n: int = 1) -> None:
        """Tally `n` more of `key` in `counts`."""
        if n:
            self.counts[key] = self.counts.get(key, 0) + n
