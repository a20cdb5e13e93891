"""The tracks' views in the camera's fixed frame, where the camera's pose in it is known (odometry) and `view_window`
keeps them.

Each measured pose is published fused with its object's other views in that frame (`views.ObjectViews`), and, when
following, an object no track holds is followed from where its views put it: a contour that holds there starts its
track without the localiser or the AGM. So the localiser and the AGM can run elsewhere (a process of their own, on an
earlier frame): `observe` adds their poses to the views, and an object so posed is tracked from there on the next
frame, as a detection the AGM posed would be.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from axispose_core.tracking.follow import FollowPart, holds, unseen
from axispose_core.tracking.tracks import Box, Crop, Detected, Measurement, TrackedPose, Tracks, project
from axispose_core.tracking.views import ObjectViews, Remembered, View, in_camera, in_fixed_frame


def _remembered_box(r: Remembered, K: np.ndarray) -> Box:
    """The box an object's last track had, moved to where its views put it and scaled with the depth."""
    scale = r.latest.depth / r.t[2]
    (cx, cy), w, h = project(K, r.t), r.latest.box[2] * scale, r.latest.box[3] * scale
    return (cx - w / 2, cy - h / 2, w, h)


def _in_view(K: np.ndarray, box: Box) -> bool:
    """Part of the box lies in the image (taken as twice the principal point's size: intrinsics alone)."""
    x, y, w, h = box
    return bool(x + w > 0 and x < 2 * K[0, 2] and y + h > 0 and y < 2 * K[1, 2])


class FixedFrame:
    """The views of a `Tracks`' objects in the fixed frame: what measured poses are published fused over
    (`over_views`), what poses made elsewhere join (`observe`), and where objects no track holds are looked for
    (`recalled`)."""

    def __init__(self, book: Tracks) -> None:
        self._book = book
        self._views = ObjectViews()
        """Each object's measurements over the last `view_window` frames, in the camera's fixed frame."""
        self._recall_due: dict[int, int] = {}
        """The frame from which an object not found where its views put it is looked for there again."""
        self._observed: set[int] = set()
        """Objects posed elsewhere (`observe`) since the last recall: their next recall starts a track whatever its
        contour's agreement, as the AGM's pose of a detection starts one on the frame it is posed."""

    def forget(self) -> None:
        """Forget every view (the tracks were reset)."""
        self._views.forget()
        self._recall_due = {}
        self._observed = set()

    def observe(self, camera: np.ndarray, posed: Sequence[tuple[Detected, Measurement]]) -> int:
        """Poses made elsewhere from the camera pose `camera` into their objects' views (`Tracker.observe`): how many
        joined."""
        posed = self.placeable(camera, posed)
        for d, m in posed:
            self._add_view(camera, d.obj_id, m, d.box, d.score, self._book.frame - 1)
            self._recall_due.pop(d.obj_id, None)
            self._observed.add(d.obj_id)
        self._book.count("views_observed", len(posed))
        return len(posed)

    def placeable(self, camera: np.ndarray, posed: Sequence[tuple[Detected, Measurement]]) -> list[tuple[Detected, Measurement]]:
        """The `ok` poses that can join the views from this camera pose: none without views kept or a finite 4x4
        pose."""
        if self._book.config.view_window <= 0 or camera.shape != (4, 4) or not np.all(np.isfinite(camera)):
            return []
        return [(d, m) for d, m in posed if m.ok]

    def over_views(self, poses: list[TrackedPose], camera: np.ndarray | None) -> list[TrackedPose]:
        """Each measured track's pose fused from its object's views in the camera's fixed frame that agree with
        its measurement (`view_window`, `view_gate`); none without a camera pose (the views are forgotten: the
        next pose may be in another fixed frame)."""
        book = self._book
        if book.config.view_window <= 0:
            return poses
        if camera is None:
            self._views.forget()
            for tr in book.tracks:
                tr.fixed = None
            return poses
        self._views.age(book.frame, book.config.view_window)
        out = []
        for pose in poses:
            if not pose.measured:
                out.append(pose)
                continue
            R, t, gated = self._add_view(camera, pose.obj_id, pose.measurement, pose.box, pose.score, book.frame)
            book.count("views_gated", int(gated > 0))
            if (tr := book.track(pose.track_id)) is not None:
                tr.fixed = (R, t)
            R, t = in_camera(camera, R, t)
            out.append(replace(pose, R=R, t=t))
        return out

    def _add_view(
        self, camera: np.ndarray, obj_id: int, m: Measurement, box: Box, score: float, frame: int
    ) -> tuple[np.ndarray, np.ndarray, int]:
        """A measurement made on `frame` from `camera` into its object's views in the fixed frame: the fused pose
        there (R, t), and how many of the object's views the gate left out."""
        R, t, information = in_fixed_frame(camera, m.R, m.t, self._book.noise(m)[:3, :3])
        return self._views.add(obj_id, View(R, t, information, float(m.t[2]), frame, m, tuple(box), score), self._book.config.view_gate)

    def recalled(self, K: np.ndarray, stamp: float, camera: np.ndarray | None, held: set[int]) -> FollowPart:
        """The objects no track holds (nor `held` at the frame's start: one just lost is not looked for where it
        was lost), followed from where their views put them: one whose contour holds there starts a track
        (`tracks_recalled`), so an object back in view is posed before the localiser finds it; so does one posed
        elsewhere since the last recall (`observe`) whose contour does not agree (`recalled_unconfirmed`: partly
        hidden, say): its track ends when its contour is lost, as one the AGM started would. A `FollowPart`."""
        book, config = self._book, self._book.config
        observed, self._observed = self._observed, set()
        if config.view_window <= 0 or camera is None:
            return []
        remembered = self._views.remembered(camera, book.frame, held | {tr.obj_id for tr in book.tracks}, config.view_gate)
        due = [(r, _remembered_box(r, K)) for r in remembered if self._recall_due.get(r.obj_id, 0) <= book.frame]
        due = [(r, box) for r, box in due if _in_view(K, box)]
        if not due:
            return []
        results = yield [r.latest.measurement for r, _ in due], [(r.R, r.t, r.covariance) for r, _ in due]
        out = []
        for (r, box), m in zip(due, results, strict=True):
            if m.ok and (holds(m, config.lost_agreement) or r.obj_id in observed):
                self._recall_due.pop(r.obj_id, None)
                book.count("recalled_unconfirmed", int(not holds(m, config.lost_agreement)))
                out.append(self._start_recalled(r, box, m, K, stamp))
            elif unseen(m):  # too little of its contour in view to tell (at the border): looked for again next frame
                self._recall_due[r.obj_id] = book.frame + 1
            else:  # not there: looked for there again after a localiser's period
                self._recall_due[r.obj_id] = book.frame + max(1, config.redetect_period)
        return out

    def _start_recalled(self, r: Remembered, box: Box, m: Measurement, K: np.ndarray, stamp: float) -> TrackedPose:
        """A track started by the contour found where the object's views put it (in `box`)."""
        tr = self._book.start_track(Crop(r.obj_id, box, r.latest.score), m, self._book.noise(m), stamp)
        self._book.count("tracks_recalled")
        return self._book.output(tr, m, True, K, box)
