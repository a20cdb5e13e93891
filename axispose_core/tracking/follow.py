"""Tracks followed by their contours, where the estimator can (`Follower`: its contour refiner, from each track's
predicted pose with the colours the track learned).

Every track is followed on every frame and the AGM poses only new detections and the tracks whose contour was lost
(agreement below `lost_agreement`). A track whose contour held for at least `redetect_period` frames and is lost
runs the localiser on the same frame, and the AGM's pose of the detection that matches it re-initialises it; one no
detection matches ends. A track whose contour held for less ends when it is lost (the AGM's pose of it was not one
its contour can follow: the localiser's next period finds the object again, as soon as re-posing it each frame would
have paid off). A frame on which no contour holds is one too far from the last to follow (a slow camera, a bag of
stills, a jump): every lost track is posed again from the localiser's boxes, so such frames are posed as without
tracking.

A pose of a track's object away from the track's (the AGM's, made here or elsewhere) challenges it: the next frame
follows both, and the track goes on from whichever of the two its contour agrees with more.
"""

from __future__ import annotations

from collections.abc import Callable, Generator, Sequence
from dataclasses import dataclass

import numpy as np

from axispose_core.tracking.filter import PoseFilter
from axispose_core.tracking.tracks import Crop, Detected, Measurement, Track, TrackedPose, Tracks
from axispose_core.tracking.views import apart, in_camera, in_fixed_frame

Follower = Callable[[list[Measurement], list[tuple[np.ndarray, np.ndarray, np.ndarray]]], Sequence[Measurement]]
"""(each track's last measurement, its predicted (R, t, covariance)) -> each track's pose on this frame by its contour
(`Estimator.follow`): `ok` False where the contour was lost; its `contour_agreement` is read where it has one."""


FollowPart = Generator[tuple[list[Measurement], list[tuple[np.ndarray, np.ndarray, np.ndarray]]], Sequence[Measurement], list[TrackedPose]]
"""What follows objects on a frame: it yields what it follows (the `Follower`'s arguments), is sent their poses by
their contours, and returns its tracked poses; one that follows nothing returns at once."""


def follow_together(follow: Follower, *parts: FollowPart) -> list[TrackedPose]:
    """The parts' objects followed in one call of `follow` (one refinement of every object the frame follows, each
    masking the lines of those behind it, one batch); each part then takes its poses, in order. The parts' tracked
    poses, in order."""
    started = []
    for part in parts:
        try:
            started.append((part, next(part), None))
        except StopIteration as done:
            started.append((None, ([], []), done.value))
    lasts = [m for _, (mine, _), _ in started for m in mine]
    predicted = [p for _, (_, mine), _ in started for p in mine]
    results = list(follow(lasts, predicted)) if lasts else []
    if len(results) != len(lasts):
        raise ValueError(f"the follower gave {len(results)} poses for {len(lasts)} tracks")
    out, at = [], 0
    for part, (mine, _), value in started:
        if part is not None:
            try:
                part.send(results[at : at + len(mine)])
            except StopIteration as done:
                value = done.value
            else:
                raise RuntimeError("a following part yielded twice")
            at += len(mine)
        out += value
    return out


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


def unseen(m: Measurement) -> bool:
    """A follower's pose that says nothing of whether its contour agrees (too few lines in view, too small): no
    evidence that the object is not there."""
    agreement = getattr(m, "contour_agreement", None)
    return not m.ok and (agreement is None or not np.isfinite(agreement))


def agreement(m: Measurement, otherwise: float) -> float:
    """The pose's contour agreement; `otherwise` where it is lost or has none."""
    value = getattr(m, "contour_agreement", None)
    return float(value) if m.ok and value is not None and np.isfinite(value) else otherwise


def holds(m: Measurement, lost_agreement: float) -> bool:
    """The pose's contour agrees with the image at least `lost_agreement`; a pose that says nothing of its
    contour (no refiner, NaN) holds."""
    return not getattr(m, "contour_agreement", 1.0) < lost_agreement


class Following:
    """The tracks of a `Tracks` followed by their contours on each frame (`followed`), each beside the pose that
    challenges it, if one does (`challenge`, `check`)."""

    def __init__(self, book: Tracks) -> None:
        self._book = book
        self._challengers: dict[int, Challenger] = {}
        """Per track id, a pose of its object away from the track's (the AGM's: `challenge`, `check`), followed
        beside the track on the next frame."""

    def forget(self) -> None:
        """Drop every challenger (the tracks were reset)."""
        self._challengers = {}

    def challenge(self, camera: np.ndarray, posed: list[tuple[Detected, Measurement]]) -> None:
        """The poses one search made (`ok`, from the camera pose `camera`) challenge each track whose object they
        posed once, beyond `view_gate` of the track's pose in the fixed frame (`Tracker.challenge`)."""
        found: dict[int, list[Challenger]] = {}
        for d, m in posed:
            found.setdefault(d.obj_id, []).append(Challenger.posed(m, camera))
        for tr in self._book.tracks:
            mine = found.get(tr.obj_id, [])
            if (
                tr.fixed is not None
                and len(mine) == 1
                and apart(self._book.config.view_gate, tr.fixed, (mine[0].R, mine[0].t), float(tr.filter.t[2]))
            ):
                self._challengers[tr.id] = mine[0]

    def check(self, track_id: int, m: Measurement, camera: np.ndarray | None) -> None:
        """The AGM's pose of a localiser's box that found a followed track (`search.with_detections`): beyond
        `view_gate` of the track's pose it challenges the track on the next frame (`_settle`), as a pose found
        elsewhere does - a track its contour holds at a wrong pose is otherwise never posed by the AGM again."""
        tr = self._book.track(track_id)
        gate = self._book.config.view_gate
        if tr is None or not m.ok or not apart(gate, (tr.filter.R, tr.filter.t), (m.R, m.t), float(tr.filter.t[2])):
            return
        self._book.count("tracks_checked_apart")
        self._challengers[tr.id] = Challenger.posed(m, camera)

    def followed(self, K: np.ndarray, stamp: float, camera: np.ndarray | None = None) -> FollowPart:
        """Every track followed by its contour from its prediction (`_predicted_pose`): a pose whose contour held is
        the track's measurement; a track whose contour was lost after holding for a localiser's period gets a crop
        for the AGM on this frame, one lost sooner ends, unless no contour held on this frame (frames far apart, or
        a camera that jumped: every lost track is posed again). A track that missed its last frame is not followed
        (its pose is stale): it stays lost until a detection finds it. A `FollowPart` (`follow_together`)."""
        book = self._book
        for tr in book.tracks:
            tr.lost = tr.misses > 0
        tracks = [tr for tr in book.tracks if tr.last is not None and not tr.lost]
        challengers, self._challengers = self._challengers, {}
        if not tracks:
            return []
        challenged = [tr for tr in tracks if tr.id in challengers and (camera is not None or not challengers[tr.id].fixed)]
        lasts = [tr.last for tr in tracks] + [challengers[tr.id].m for tr in challenged]
        predicted = [self._predicted_pose(tr, camera) for tr in tracks]
        predicted += [(*challengers[tr.id].in_camera(camera), book.noise(challengers[tr.id].m)) for tr in challenged]
        results = yield lasts, predicted
        results = self._settle(tracks, results[: len(tracks)], dict(zip([tr.id for tr in challenged], results[len(tracks) :], strict=True)))
        out, unfollowable = [], set()
        holding = [m.ok and holds(m, book.config.lost_agreement) for m in results]
        jumped = not any(holding)  # frames far apart, or the camera jumped
        for tr, m, contour_held in zip(tracks, results, holding, strict=True):
            if contour_held:
                tr.held += 1
                out.append(book.measure(Crop(tr.obj_id, book.predicted_box(tr, K), tr.score, tr.id), m, K, stamp))
                book.count("followed")
            elif tr.held < book.config.redetect_period and not jumped:
                unfollowable.add(tr.id)
            else:
                tr.lost = True
                book.count("contour_lost")
        book.end("unfollowable", lambda tr: tr.id in unfollowable, look=False)
        return [pose for pose in out if pose is not None]

    def _settle(self, tracks: list[Track], own: list[Measurement], challengers: dict[int, Measurement]) -> list[Measurement]:
        """Each track's pose on this frame: its own, or its challenger's where that holds and agrees more with the
        image (then the track starts again there, `tracks_corrected`, and is judged by its contour as a new one)."""
        book = self._book
        out = []
        for tr, m in zip(tracks, own, strict=True):
            other = challengers.get(tr.id)
            if other is not None and holds(other, book.config.lost_agreement) and agreement(other, np.nan) > agreement(m, -np.inf):
                tr.filter = PoseFilter.start(book.config.filter, other.R, other.t, book.noise(other))
                tr.held, tr.fixed, m = 0, None, other
                book.count("tracks_corrected")
            out.append(m)
        return out

    def _predicted_pose(self, tr: Track, camera: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Where a track is looked for on this frame (R, t, covariance): its pose in the fixed frame brought into the
        camera where views are kept and the camera's pose is known, else its filter's prediction."""
        if tr.fixed is None or self._book.config.view_window <= 0 or camera is None:
            return tr.filter.R, tr.filter.t, tr.filter.covariance
        return *in_camera(camera, *tr.fixed), tr.filter.covariance
