"""Tracks across a camera stream: each object instance keeps an id, a filtered pose and the box it is cropped from.

Where the estimator can follow objects by their contours (`follow`: its contour refiner, from each track's predicted
pose with the colours the track learned), every track is followed on every frame and the AGM poses only new
detections and the tracks whose contour was lost (agreement below `lost_agreement`). A track whose contour held
for at least `redetect_period` frames and is lost runs the localiser on the same frame, and the AGM's pose of the
detection that matches it re-initialises it; one no detection matches ends. A track whose contour held for less
ends when it is lost (the AGM's pose of it was not one its contour can follow: the localiser's next period finds
the object again, as soon as re-posing it each frame would have paid off). A frame on which no contour holds is one
too far from the last to follow (a slow camera, a bag of stills, a jump): every lost track is posed again from the
localiser's boxes, so such frames are posed as without tracking. Otherwise (below) every tracked object is posed by
the estimator:

A tracked object's crop comes from its predicted pose (the box it had, moved with the pose's projection and scaled
with its depth), so the localiser runs only every `redetect_period` frames, while nothing is tracked, or after a
track missed a frame or ended (but not when the localiser itself stopped finding it); its detections then refresh
the tracks' boxes (matched by object and nearness) and start tracks for new objects. Every crop goes through the
estimator in one batch, and each pose that comes back is a measurement for its track's `PoseFilter` (a detection
the caller has posed already, a `Sighting`, brings its pose and is not posed again); with
`measure_every` n the tracks take turns between localiser runs, the others publishing their filters' predictions.
Tracks end after `track_timeout` seconds without a measurement, `max_misses` frames in a row without a pose, or
`max_unseen` localiser runs in a row that do not find them; all end when the stamps go backwards (a looped bag) or
the camera's intrinsics change.

With the camera's pose in a fixed frame (odometry) and `view_window`, each measured pose is published fused with its
object's other views in that frame (`views.ObjectViews`), and, when following, an object no track holds is followed
from where its views put it: a contour that holds there starts its track without the localiser or the AGM. So the
localiser and the AGM can run elsewhere (a process of their own, on an earlier frame): `observe` adds their poses to
the views (an object so posed is tracked from there on the next frame, as a detection the AGM posed would be, and a
track away from such a pose of its object goes on from whichever of the two its contour agrees with more), and `step`
without `detect` only follows and recalls.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Protocol

import numpy as np

from axispose_core.tracking.filter import FilterConfig, PoseFilter
from axispose_core.tracking.views import ObjectViews, Remembered, View, apart, in_camera, in_fixed_frame

Box = tuple[float, float, float, float]
"""(x, y, w, h) in image pixels."""
MIN_DEPTH = 0.05
"""A track whose predicted depth (m) falls below this ends: its filter has run off."""


@dataclass(frozen=True)
class TrackingConfig:
    """When the localiser runs, when tracks end, and the filter's model."""

    redetect_period: int = 5
    """Run the localiser on every n-th frame (1: on every frame)."""
    measure_every: int = 1
    """Crop and pose each track on every n-th frame, the tracks taking turns (by id), and every track where the
    localiser runs; in between a track's pose is its filter's prediction. Bounds the estimator's work per frame
    when many objects are tracked (1: every track on every frame)."""
    track_timeout: float = 1.0
    """Seconds without an accepted measurement after which a track ends."""
    max_misses: int = 3
    """Frames in a row without a pose (the estimator refused the crop) after which a track ends."""
    reinit_after: int = 3
    """Measurements in a row refused at the gate after which the track restarts at the latest one: the object
    really moved (or the filter had locked onto a wrong pose)."""
    match_iou: float = 0.3
    """A detection refreshes the track of its object whose predicted box it overlaps at least this much..."""
    match_distance: float = 0.5
    """...or whose predicted box's centre lies within this fraction of the larger box's diagonal of its own: a
    prediction that lags a fast camera still finds its object."""
    max_unseen: int = 4
    """Localiser runs in a row that do not find a track's object near it, after which the track ends: a track
    started by a false detection, or one whose object left."""
    same_distance: float = 0.1
    """A new detection's pose this close to an unmeasured track of its object (a fraction of the depth) is that
    track's measurement, not a new track: its predicted box had drifted off the detection's."""
    fallback_std: tuple[float, float] = (0.05, 0.35)
    """Measurement noise where the estimator gives no covariance: translation as a fraction of the depth, and
    rotation (rad)."""
    lost_agreement: float = 0.7
    """With contour following: a followed contour that separates the object's colours from its surroundings' less
    than this (0.5: not at all), or that the refiner kept, has lost its object: the AGM poses it from the
    localiser's box on the same frame where its contour had held for `redetect_period` frames, else it ends."""
    check_below: float = 0.85
    """With contour following: a followed track whose contour agrees less than this may hold a wrong pose (a
    contour held at the wrong side of an object): where the localiser finds it, the AGM poses that box too, one
    such track a frame, to check its pose (`_check`)."""
    view_window: int = 0
    """With the camera's pose in a fixed frame (`step(..., camera=...)`, e.g. from odometry): a track's published
    pose is fused from its object's measurements in that frame over the last n frames (by any of its tracks: an
    object found again brings its views back), brought to the current camera: positions weighted by their
    information (each view's covariance turned into the fixed frame: precise across its line of sight, loose along
    it, so views from other directions pin the depth), rotations by their chordal mean. Objects at rest under a
    moving camera are seen from other views, and a single view's error (depth most of all) differs from view to
    view. With following, an object no track holds is looked for where its views put it (where its contour is not
    found, again after `redetect_period` frames) (0: off)."""
    view_gate: tuple[float, float] = (0.05, 15.0)
    """A view this far from the track's measurement on this frame (translation as a fraction of its depth, rotation
    in degrees) is left out: another instance of the object, the object moved, a symmetric twin, a wrong pose."""
    filter: FilterConfig = field(default_factory=FilterConfig)


class Measurement(Protocol):
    """What the tracker reads of an estimator's pose (`estimator.PoseEstimate` is one)."""

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
    """One box to estimate: a track's (`track` its id; `prior` its predicted pose) or a new detection's;
    `measurement`: its pose where a `Sighting` brought one (the estimator is not asked)."""

    obj_id: int
    box: Box
    score: float
    track: int | None = None
    prior: tuple[np.ndarray, np.ndarray] | None = None
    measurement: Measurement | None = None
    detected: bool = False
    """The box is the localiser's on this frame (a caller verifies such poses where it verifies detections)."""
    checks: int | None = None
    """The id of the followed track this localiser's box found: its pose checks the track's (`_check`)."""


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
    """The frame its pose was last checked against the AGM's pose of a localiser's box (`_check`)."""
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


Follower = Callable[[list[Measurement], list[tuple[np.ndarray, np.ndarray, np.ndarray]]], Sequence[Measurement]]
"""(each track's last measurement, its predicted (R, t, covariance)) -> each track's pose on this frame by its contour
(`Estimator.follow`): `ok` False where the contour was lost; its `contour_agreement` is read where it has one."""


@dataclass(frozen=True)
class Challenger:
    """A pose of a track's object away from the track's: (R, t) in the camera's fixed frame (`fixed`) or in the
    camera's frame of the frame it was posed on, and the measurement."""

    R: np.ndarray
    t: np.ndarray
    m: Measurement
    fixed: bool

    @classmethod
    def posed(cls, m: Measurement, camera: np.ndarray | None) -> Challenger:
        """The pose `m` made on a frame whose camera pose (4x4, camera to fixed) was `camera`: kept in the fixed frame
        where that is known, else in the camera's frame."""
        if camera is None:
            return cls(m.R, m.t, m, fixed=False)
        return cls(*in_fixed_frame(camera, m.R, m.t, np.eye(3))[:2], m, fixed=True)

    def in_camera(self, camera: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """Where it is looked for on this frame: a fixed-frame pose moved into `camera`, a camera-frame pose as it
        is (the frame it was posed on is the one before)."""
        return in_camera(camera, self.R, self.t) if self.fixed else (self.R, self.t)


def _project(K: np.ndarray, t: np.ndarray) -> np.ndarray:
    p = K @ t
    return p[:2] / p[2]


def _remembered_box(r: Remembered, K: np.ndarray) -> Box:
    """The box an object's last track had, moved to where its views put it and scaled with the depth."""
    scale = r.latest.depth / r.t[2]
    (cx, cy), w, h = _project(K, r.t), r.latest.box[2] * scale, r.latest.box[3] * scale
    return (cx - w / 2, cy - h / 2, w, h)


def _in_view(K: np.ndarray, box: Box) -> bool:
    """Part of the box lies in the image (taken as twice the principal point's size: intrinsics alone)."""
    x, y, w, h = box
    return bool(x + w > 0 and x < 2 * K[0, 2] and y + h > 0 and y < 2 * K[1, 2])


def _unseen(m: Measurement) -> bool:
    """A follower's pose that says nothing of whether its contour agrees (too few lines in view, too small): no
    evidence that the object is not there."""
    agreement = getattr(m, "contour_agreement", None)
    return not m.ok and (agreement is None or not np.isfinite(agreement))


def _agreement(m: Measurement, otherwise: float) -> float:
    """The pose's contour agreement; `otherwise` where it is lost or has none."""
    agreement = getattr(m, "contour_agreement", None)
    return float(agreement) if m.ok and agreement is not None and np.isfinite(agreement) else otherwise


def _posed(d: Detected) -> Measurement | None:
    return d.measurement if isinstance(d, Sighting) else None


def _measurements(crops: list[Crop], estimate: Callable[[list[Crop]], Sequence[Measurement]]) -> list[Measurement]:
    """Each crop's pose: the one it came with, else the estimator's (one call for all the others)."""
    todo = [c for c in crops if c.measurement is None]
    fresh = list(estimate(todo)) if todo else []
    if len(fresh) != len(todo):
        raise ValueError(f"the estimator gave {len(fresh)} poses for {len(todo)} crops")
    posed = iter(fresh)
    return [c.measurement if c.measurement is not None else next(posed) for c in crops]


def _iou(a: Box, b: Box) -> float:
    ix = max(0.0, min(a[0] + a[2], b[0] + b[2]) - max(a[0], b[0]))
    iy = max(0.0, min(a[1] + a[3], b[1] + b[3]) - max(a[1], b[1]))
    inter = ix * iy
    union = a[2] * a[3] + b[2] * b[3] - inter
    return inter / union if union > 0 else 0.0


class Tracker:
    """`step(stamp, K, detect, estimate)` per frame: tracks' crops (and the localiser's, when it runs) through
    the estimator, the poses into the tracks' filters, the tracks' filtered poses out. `counts` tallies what
    happened (resets, refused measurements, tracks started and ended) for diagnostics."""

    def __init__(self, config: TrackingConfig) -> None:
        self.config = config
        self.tracks: list[Track] = []
        self.counts: dict[str, int] = {}
        self._next_id = 1
        self._frame = 0
        self._stamp: float | None = None
        self._K: np.ndarray | None = None
        self._lost = False
        """A track ended: look for its object on the next frame."""
        self._views = ObjectViews()
        """Each object's measurements over the last `view_window` frames, in the camera's fixed frame."""
        self._recall_due: dict[int, int] = {}
        """The frame from which an object not found where its views put it is looked for there again."""
        self._observed: set[int] = set()
        """Objects posed elsewhere (`observe`) since the last recall: their next recall starts a track whatever its
        contour's agreement, as the AGM's pose of a detection starts one on the frame it is posed."""
        self._challengers: dict[int, Challenger] = {}
        """Per track id, a pose of its object away from the track's (the AGM's: `challenge`, `_check`), followed
        beside the track on the next frame."""

    def reset(self, reason: str) -> None:
        """End every track (counted as `reset_<reason>`) and forget every view."""
        if self.tracks:
            self._count(f"reset_{reason}")
        self.tracks = []
        self._frame = 0
        self._views.forget()
        self._recall_due = {}
        self._observed = set()
        self._challengers = {}

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
        out = self._follow(follow, K, stamp, camera) + self._recall(follow, K, stamp, camera, held) if follow is not None else []
        followed = {pose.track_id for pose in out}
        detecting = detect is not None and self._detection_due(following=follow is not None)
        crops = self._track_crops(K, every=detecting, skip=followed)
        if detecting:
            crops = self._with_detections(crops, detect(), [tr for tr in self.tracks if tr.id in followed], K)
            self._count("localiser_runs")
        crops = self._unfound_dropped(crops)
        measurements = _measurements(crops, estimate)
        if follow is not None:
            self._count("frames_estimated" if crops else "frames_followed")
        for crop, m in zip(crops, measurements, strict=True):
            if crop.checks is None:
                out.append(self._measure(crop, m, K, stamp))
            else:
                self._check(crop.checks, m, camera)
        cropped = {c.track for c in crops} | followed
        quiet = [tr for tr in self.tracks if tr.id not in cropped and not tr.measured and not tr.lost and tr.last is not None]
        out += [self._predicted(tr, K) for tr in quiet]
        self._end_tracks()
        poses = self._over_views([pose for pose in out if pose is not None], camera)
        self._frame += 1
        return poses

    def observe(self, camera: np.ndarray, posed: Sequence[tuple[Detected, Measurement]]) -> int:
        """Poses made elsewhere on an earlier frame whose camera pose (4x4, camera to fixed) was `camera` (the
        localiser and the AGM in a process of their own): each joins its object's views, from where the next `step`
        follows an object no track holds (at once, however recently it was not found there; the tracks away from
        them are challenged once the search's poses are all in: `challenge`). Returns how many joined (none without
        `view_window`, a finite camera pose, or an `ok` pose)."""
        camera = np.asarray(camera, float)
        posed = self._placeable(camera, posed)
        for d, m in posed:
            self._add_view(camera, d.obj_id, m, d.box, d.score, self._frame - 1)
            self._recall_due.pop(d.obj_id, None)
            self._observed.add(d.obj_id)
        self._count("views_observed", len(posed))
        return len(posed)

    def challenge(self, camera: np.ndarray, posed: Sequence[tuple[Detected, Measurement]]) -> None:
        """Every pose one search made elsewhere (`observe`; the camera's pose at its frame, 4x4, camera to fixed): a
        track whose object it posed beyond `view_gate` of the track's pose (once: two poses of it may be two
        instances) is challenged: the next frame follows that pose beside the track's, and the one whose contour
        agrees more goes on (`_settle`), so a track stuck on a wrong pose its contour half agrees with is put right
        by the AGM's next pose of its object."""
        camera = np.asarray(camera, float)
        found: dict[int, list[Challenger]] = {}
        for d, m in self._placeable(camera, posed):
            found.setdefault(d.obj_id, []).append(Challenger.posed(m, camera))
        for tr in self.tracks:
            mine = found.get(tr.obj_id, [])
            if (
                tr.fixed is not None
                and len(mine) == 1
                and apart(self.config.view_gate, tr.fixed, (mine[0].R, mine[0].t), float(tr.filter.t[2]))
            ):
                self._challengers[tr.id] = mine[0]

    def _placeable(self, camera: np.ndarray, posed: Sequence[tuple[Detected, Measurement]]) -> list[tuple[Detected, Measurement]]:
        """The `ok` poses that can join the views from this camera pose: none without views kept or a finite 4x4
        pose."""
        if self.config.view_window <= 0 or camera.shape != (4, 4) or not np.all(np.isfinite(camera)):
            return []
        return [(d, m) for d, m in posed if m.ok]

    def _check(self, track_id: int, m: Measurement, camera: np.ndarray | None) -> None:
        """The AGM's pose of a localiser's box that found a followed track (`_with_detections`): beyond `view_gate`
        of the track's pose it challenges the track on the next frame (`_settle`), as a pose found elsewhere does -
        a track its contour holds at a wrong pose is otherwise never posed by the AGM again."""
        tr = self._track(track_id)
        if tr is None or not m.ok or not apart(self.config.view_gate, (tr.filter.R, tr.filter.t), (m.R, m.t), float(tr.filter.t[2])):
            return
        self._count("tracks_checked_apart")
        self._challengers[tr.id] = Challenger.posed(m, camera)

    def _over_views(self, poses: list[TrackedPose], camera: np.ndarray | None) -> list[TrackedPose]:
        """Each measured track's pose fused from its object's views in the camera's fixed frame that agree with
        its measurement (`view_window`, `view_gate`); none without a camera pose (the views are forgotten: the
        next pose may be in another fixed frame)."""
        if self.config.view_window <= 0:
            return poses
        if camera is None:
            self._views.forget()
            for tr in self.tracks:
                tr.fixed = None
            return poses
        self._views.age(self._frame, self.config.view_window)
        out = []
        for pose in poses:
            if not pose.measured:
                out.append(pose)
                continue
            R, t, gated = self._add_view(camera, pose.obj_id, pose.measurement, pose.box, pose.score, self._frame)
            self._count("views_gated", int(gated > 0))
            if (tr := self._track(pose.track_id)) is not None:
                tr.fixed = (R, t)
            R, t = in_camera(camera, R, t)
            out.append(replace(pose, R=R, t=t))
        return out

    def _add_view(
        self, camera: np.ndarray, obj_id: int, m: Measurement, box: Box, score: float, frame: int
    ) -> tuple[np.ndarray, np.ndarray, int]:
        """A measurement made on `frame` from `camera` into its object's views in the fixed frame: the fused pose
        there (R, t), and how many of the object's views the gate left out."""
        R, t, information = in_fixed_frame(camera, m.R, m.t, self._noise(m)[:3, :3])
        return self._views.add(obj_id, View(R, t, information, float(m.t[2]), frame, m, tuple(box), score), self.config.view_gate)

    def _recall(self, follow: Follower, K: np.ndarray, stamp: float, camera: np.ndarray | None, held: set[int]) -> list[TrackedPose]:
        """The objects no track holds (nor `held` at the frame's start: one just lost is not looked for where it
        was lost), followed from where their views put them: one whose contour holds there starts a track
        (`tracks_recalled`), so an object back in view is posed before the localiser finds it; so does one posed
        elsewhere since the last recall (`observe`) whose contour does not agree (`recalled_unconfirmed`: partly
        hidden, say): its track ends when its contour is lost, as one the AGM started would."""
        observed, self._observed = self._observed, set()
        if self.config.view_window <= 0 or camera is None:
            return []
        remembered = self._views.remembered(camera, self._frame, held | {tr.obj_id for tr in self.tracks}, self.config.view_gate)
        due = [(r, _remembered_box(r, K)) for r in remembered if self._recall_due.get(r.obj_id, 0) <= self._frame]
        due = [(r, box) for r, box in due if _in_view(K, box)]
        if not due:
            return []
        results = follow([r.latest.measurement for r, _ in due], [(r.R, r.t, r.covariance) for r, _ in due])
        out = []
        for (r, box), m in zip(due, results, strict=True):
            if m.ok and (self._holds(m) or r.obj_id in observed):
                self._recall_due.pop(r.obj_id, None)
                self._count("recalled_unconfirmed", int(not self._holds(m)))
                out.append(self._recalled(r, box, m, K, stamp))
            elif _unseen(m):  # too little of its contour in view to tell (at the border): looked for again next frame
                self._recall_due[r.obj_id] = self._frame + 1
            else:  # not there: looked for there again after a localiser's period
                self._recall_due[r.obj_id] = self._frame + max(1, self.config.redetect_period)
        return out

    def _recalled(self, r: Remembered, box: Box, m: Measurement, K: np.ndarray, stamp: float) -> TrackedPose:
        """A track started by the contour found where the object's views put it (in `box`)."""
        tr = self._start_track(Crop(r.obj_id, box, r.latest.score), m, self._noise(m), stamp)
        self._count("tracks_recalled")
        return self._output(tr, m, True, K, box)

    def _follow(self, follow: Follower, K: np.ndarray, stamp: float, camera: np.ndarray | None = None) -> list[TrackedPose]:
        """Every track followed by its contour from its prediction (`_predicted_pose`): a pose whose contour held is
        the track's measurement; a track whose contour was lost after holding for a localiser's period gets a crop
        for the AGM on this frame, one lost sooner ends, unless no contour held on this frame (frames far apart, or
        a camera that jumped: every lost track is posed again). A track that missed its last frame is not followed
        (its pose is stale): it stays lost until a detection finds it."""
        for tr in self.tracks:
            tr.lost = tr.misses > 0
        tracks = [tr for tr in self.tracks if tr.last is not None and not tr.lost]
        challengers, self._challengers = self._challengers, {}
        if not tracks:
            return []
        challenged = [tr for tr in tracks if tr.id in challengers and (camera is not None or not challengers[tr.id].fixed)]
        lasts = [tr.last for tr in tracks] + [challengers[tr.id].m for tr in challenged]
        predicted = [self._predicted_pose(tr, camera) for tr in tracks]
        predicted += [(*challengers[tr.id].in_camera(camera), self._noise(challengers[tr.id].m)) for tr in challenged]
        results = list(follow(lasts, predicted))
        if len(results) != len(lasts):
            raise ValueError(f"the follower gave {len(results)} poses for {len(lasts)} tracks")
        results = self._settle(tracks, results[: len(tracks)], dict(zip([tr.id for tr in challenged], results[len(tracks) :], strict=True)))
        out, unfollowable = [], set()
        holding = [m.ok and self._holds(m) for m in results]
        jumped = not any(holding)  # frames far apart, or the camera jumped
        for tr, m, holds in zip(tracks, results, holding, strict=True):
            if holds:
                tr.held += 1
                out.append(self._measure(Crop(tr.obj_id, self._predicted_box(tr, K), tr.score, tr.id), m, K, stamp))
                self._count("followed")
            elif tr.held < self.config.redetect_period and not jumped:
                unfollowable.add(tr.id)
            else:
                tr.lost = True
                self._count("contour_lost")
        self._end("unfollowable", lambda tr: tr.id in unfollowable, look=False)
        return [pose for pose in out if pose is not None]

    def _settle(self, tracks: list[Track], own: list[Measurement], challengers: dict[int, Measurement]) -> list[Measurement]:
        """Each track's pose on this frame: its own, or its challenger's where that holds and agrees more with the
        image (then the track starts again there, `tracks_corrected`, and is judged by its contour as a new one)."""
        out = []
        for tr, m in zip(tracks, own, strict=True):
            other = challengers.get(tr.id)
            if other is not None and self._holds(other) and _agreement(other, np.nan) > _agreement(m, -np.inf):
                tr.filter = PoseFilter.start(self.config.filter, other.R, other.t, self._noise(other))
                tr.held, tr.fixed, m = 0, None, other
                self._count("tracks_corrected")
            out.append(m)
        return out

    def _predicted_pose(self, tr: Track, camera: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Where a track is looked for on this frame (R, t, covariance): its pose in the fixed frame brought into the
        camera where views are kept and the camera's pose is known, else its filter's prediction."""
        if tr.fixed is None or self.config.view_window <= 0 or camera is None:
            return tr.filter.R, tr.filter.t, tr.filter.covariance
        return *in_camera(camera, *tr.fixed), tr.filter.covariance

    def _start_frame(self, stamp: float, K: np.ndarray) -> None:
        if self._stamp is not None and stamp < self._stamp:
            self.reset("stamps_backwards")
        if self._K is not None and not np.allclose(K, self._K):
            self.reset("camera_changed")
        self._stamp, self._K = stamp, np.array(K, float)
        self._end("timeout", lambda tr: stamp - tr.updated > self.config.track_timeout)
        for tr in self.tracks:
            tr.filter.predict(stamp - tr.stamp)
            tr.stamp, tr.measured, tr.lost = stamp, False, False
        self._end("behind", lambda tr: tr.filter.t[2] <= MIN_DEPTH)  # a filter run off behind the camera

    def _predicted_box(self, tr: Track, K: np.ndarray) -> Box:
        offset, z = tr.anchor
        scale = z / tr.filter.t[2] if tr.filter.t[2] > 0 else 1.0
        cx, cy = _project(K, tr.filter.t) + offset * scale
        w, h = tr.box[2] * scale, tr.box[3] * scale
        return (cx - w / 2, cy - h / 2, w, h)

    def _track_crops(self, K: np.ndarray, every: bool, skip: set[int]) -> list[Crop]:
        """The crops of the tracks whose turn it is (`measure_every`), or of `every` track, but those followed
        (`skip`): a track its contour lost, every time."""
        n = max(1, self.config.measure_every)
        due = [tr for tr in self.tracks if tr.id not in skip and (every or tr.lost or (self._frame + tr.id) % n == 0)]
        return [Crop(tr.obj_id, self._predicted_box(tr, K), tr.score, tr.id, (tr.filter.R, tr.filter.t)) for tr in due]

    def _predicted(self, tr: Track, K: np.ndarray) -> TrackedPose:
        """A track not posed this frame: its filter's prediction, in the box it would be cropped from."""
        f = tr.filter
        return TrackedPose(tr.id, tr.obj_id, f.R.copy(), f.t.copy(), f.covariance, tr.score, tr.last, False,
                           self._predicted_box(tr, K), measured=False)  # fmt: skip

    def _detection_due(self, following: bool = False) -> bool:
        """The localiser's turn: every period, with no tracks, after a track ended, while a track misses (without
        following, where it is posed in its predicted box anyway) or where a contour was lost (following)."""
        period = max(1, self.config.redetect_period)
        missing = any(tr.lost for tr in self.tracks) if following else any(tr.misses > 0 for tr in self.tracks)
        due = self._lost or not self.tracks or self._frame % period == 0 or missing
        self._lost = False
        return due

    def _with_detections(self, crops: list[Crop], detections: Sequence[Detected], followed: list[Track], K: np.ndarray) -> list[Crop]:
        """A detection near a track its contour followed on this frame is that track's (posed only to check it:
        `_check_crops`); each other refreshes the box of the nearest track of its object (`match_iou`,
        `match_distance`) or becomes a new crop; a track no detection found is unseen once more (`max_unseen`)."""
        detections, found = list(detections), []
        for tr in followed:
            box = self._predicted_box(tr, K)
            near = [(d, j) for j, det in enumerate(detections) if det.obj_id == tr.obj_id and (d := self._match(box, det.box)) is not None]
            tr.unseen = 0 if near else tr.unseen + 1
            if near:
                found.append((tr, detections.pop(min(near)[1])))
        checks = self._check_crops(found)
        crops = list(crops)
        pairs = sorted((d, i, j) for i, c in enumerate(crops) for j, det in enumerate(detections)
                       if c.obj_id == det.obj_id and (d := self._match(c.box, det.box)) is not None)  # fmt: skip
        taken_c, taken_d = set(), set()
        for _, i, j in pairs:
            if i in taken_c or j in taken_d:
                continue
            taken_c.add(i)
            taken_d.add(j)
            d = detections[j]
            crops[i] = Crop(d.obj_id, tuple(d.box), d.score, crops[i].track, crops[i].prior, _posed(d), detected=True)
        for i, c in enumerate(crops):
            tr = self._track(c.track)
            tr.unseen = 0 if i in taken_c else tr.unseen + 1
        new = [d for j, d in enumerate(detections) if j not in taken_d]
        return crops + [Crop(d.obj_id, tuple(d.box), d.score, measurement=_posed(d), detected=True) for d in new] + checks

    def _check_crops(self, found: list[tuple[Track, Detected]]) -> list[Crop]:
        """Of the followed tracks the localiser found, with their detections, the one checked longest ago among
        those whose contour agrees less than `check_below`: its detection's crop, to be posed by the AGM (`_check`)."""
        doubtful = [(tr, d) for tr, d in found if _agreement(tr.last, -np.inf) < self.config.check_below]
        if not doubtful:
            return []
        tr, d = min(doubtful, key=lambda f: (f[0].checked, f[0].id))
        tr.checked = self._frame
        return [Crop(d.obj_id, tuple(d.box), d.score, detected=True, checks=tr.id)]

    def _unfound_dropped(self, crops: list[Crop]) -> list[Crop]:
        """The crops but those of tracks whose contour was lost and that no detection found: where the contour
        lost its object its predicted box is no place to pose it, and the track ends (the localiser's period finds
        the object again when it is back)."""
        unfound = {c.track for c in crops if (tr := self._track(c.track)) is not None and tr.lost and not c.detected}
        self._end("unfound", lambda tr: tr.id in unfound, look=False)
        return [c for c in crops if c.track not in unfound]

    def _match(self, a: Box, b: Box) -> float | None:
        """How far detection box `b` is from track box `a` (centre distance over the larger diagonal); None when
        they do not match."""
        diag = max(np.hypot(a[2], a[3]), np.hypot(b[2], b[3]), 1e-9)
        dist = float(np.hypot(a[0] + a[2] / 2 - b[0] - b[2] / 2, a[1] + a[3] / 2 - b[1] - b[3] / 2)) / diag
        return dist if dist <= self.config.match_distance or _iou(a, b) >= self.config.match_iou else None

    def _noise(self, m: Measurement) -> np.ndarray:
        if m.covariance is not None and np.all(np.isfinite(m.covariance)):
            return np.asarray(m.covariance, float)
        rel, rot = self.config.fallback_std
        return np.diag([(rel * m.t[2]) ** 2] * 3 + [rot**2] * 3)

    def _measure(self, crop: Crop, m: Measurement, K: np.ndarray, stamp: float) -> TrackedPose | None:
        tr = self._track(crop.track)
        if not m.ok:
            if tr is not None:
                tr.misses += 1
            return None
        cov = self._noise(m)
        tr = tr or self._nearby_track(crop.obj_id, m.t)
        if tr is None:
            tr = self._start_track(crop, m, cov, stamp)
            return self._output(tr, m, True, K, crop.box)
        if tr.lost:  # its contour lost it: the AGM's pose starts it again (the next frame's contour judges it)
            tr.lost, tr.held, tr.checked = False, 0, self._frame
            tr.filter = PoseFilter.start(self.config.filter, m.R, m.t, cov)
            tr.misses, tr.measured, tr.score, tr.last, tr.updated = 0, True, crop.score, m, stamp
            self._count("tracks_reinitialised")
            return self._output(tr, m, True, K, crop.box)
        tr.misses, tr.measured, tr.score, tr.last = 0, True, crop.score, m
        if (information := getattr(m, "contour_information", None)) is not None:  # followed from the prediction
            accepted, _ = tr.filter.update_posterior(m.R, m.t, information)
        else:
            accepted, _ = tr.filter.update(m.R, m.t, cov)
        if accepted:
            tr.rejects, tr.updated = 0, stamp
        else:
            tr.rejects += 1
            self._count("measurements_gated")
            if tr.rejects >= self.config.reinit_after:
                tr.filter = PoseFilter.start(self.config.filter, m.R, m.t, cov)
                tr.rejects, tr.updated, accepted = 0, stamp, True
                self._count("tracks_restarted")
        return self._output(tr, m, accepted, K, crop.box)

    def _track(self, track_id: int | None) -> Track | None:
        """The live track of this id (None: no id, or it ended)."""
        return next((tr for tr in self.tracks if tr.id == track_id), None) if track_id is not None else None

    def _holds(self, m: Measurement) -> bool:
        """The pose's contour agrees with the image at least `lost_agreement`; a pose that says nothing of its
        contour (no refiner, NaN) holds."""
        return not getattr(m, "contour_agreement", 1.0) < self.config.lost_agreement

    def _nearby_track(self, obj_id: int, t: np.ndarray) -> Track | None:
        near = [tr for tr in self.tracks if tr.obj_id == obj_id and not tr.measured
                and np.linalg.norm(tr.filter.t - t) < self.config.same_distance * t[2]]  # fmt: skip
        return min(near, key=lambda tr: np.linalg.norm(tr.filter.t - t), default=None)

    def _start_track(self, crop: Crop, m: Measurement, cov: np.ndarray, stamp: float) -> Track:
        tr = Track(self._next_id, crop.obj_id, PoseFilter.start(self.config.filter, m.R, m.t, cov), crop.box,
                   (np.zeros(2), 1.0), crop.score, stamp, stamp, measured=True, last=m, checked=self._frame)  # fmt: skip
        self._next_id += 1
        self.tracks.append(tr)
        self._count("tracks_started")
        return tr

    def _output(self, tr: Track, m: Measurement, accepted: bool, K: np.ndarray, box: Box) -> TrackedPose:
        """The track's pose out; the crop's box becomes the track's, anchored to the filtered pose."""
        centre = np.array([box[0] + box[2] / 2, box[1] + box[3] / 2])
        tr.box, tr.anchor = box, (centre - _project(K, tr.filter.t), float(tr.filter.t[2]))
        f = tr.filter
        return TrackedPose(tr.id, tr.obj_id, f.R.copy(), f.t.copy(), f.covariance, tr.score, m, accepted, box)

    def _end_tracks(self) -> None:
        self._end("misses", lambda tr: tr.misses >= self.config.max_misses)
        self._end("unseen", lambda tr: tr.unseen >= self.config.max_unseen, look=False)

    def _end(self, reason: str, ends: Callable[[Track], bool], look: bool = True) -> None:
        """End the tracks for which `ends` holds (counted as `ended_<reason>`); with `look`, run the localiser on the
        next frame to find their objects again (not for tracks it has just not found: that would run it on every
        frame while false detections start and end tracks)."""
        kept = [tr for tr in self.tracks if not ends(tr)]
        self._count(f"ended_{reason}", len(self.tracks) - len(kept))
        self._lost |= look and len(kept) < len(self.tracks)
        self.tracks = kept

    def _count(self, key: str, n: int = 1) -> None:
        if n:
            self.counts[key] = self.counts.get(key, 0) + n
