"""From a frame to the poses the node publishes: the boxes of fresh ROIs, else, in the frame's `mode`
(`mode.py`), what the localiser finds (`stills`: each posed on its own, rescored by the checkpoint's verifier
where it has one: `Estimator.find`) or every object followed by a `Tracker` (`video`: crops from predicted poses, the
localiser only where due, filtered poses with their filter's covariance and a track id, tracks followed by their
contours; `video_odometry`: the camera's pose fusing each object's views, the localiser and the AGM in a process of
their own and the frames only followed: `background.py`). The node and `axispose validate` both pose frames
through it, so what is validated is what runs on the robot."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from axispose_core.camera import hull_points, project_model
from axispose_core.estimator import SHIPPED_ESTIMATOR, EstimateOptions, Estimator
from axispose_core.localiser.decode import Detection
from axispose_core.pose_estimate import Found, PoseEstimate
from axispose_core.tracking.background import BackgroundFinder, Search, Searcher
from axispose_core.tracking.config import TrackingConfig
from axispose_core.tracking.mode import Choice, Mode, ModeChooser
from axispose_core.tracking.tracker import Tracker
from axispose_core.tracking.tracks import Crop, Sighting

Box = tuple[float, float, float, float]


@dataclass(frozen=True)
class PoserSettings:
    """What `FramePoser` reads of a frame's settings: the node's parameters of these names (`NodeSettings.poser`),
    its defaults the node's, with λ_O resolved per object id (`scales`)."""

    mode: str = "auto"
    ddim_steps: int = 3
    hypotheses: int = 1
    guidance_scale: float | None = 0.0
    """Run-time guidance (None: the checkpoint's)."""
    scales: Mapping[int, float] = field(default_factory=dict)
    """λ_O (m) by object id where it overrides the checkpoint's."""
    batch_boxes: int | None = 8
    """Most boxes in one AGM batch (None: all of a frame's in one)."""
    refine: bool = True
    follow_passes: int = 0
    score_threshold: float = 0.3
    redetect_period: int = 5
    measure_every: int = 1
    track_timeout: float = 1.0
    view_window: int = 160
    checkpoint: str = str(SHIPPED_ESTIMATOR)
    """What the search process of `video_odometry` loads (the estimator's own checkpoint)."""
    num_threads: int = 2
    """The frame's threads: the search process takes one fewer."""

    def options(self) -> EstimateOptions:
        """The estimator's options for this frame."""
        return EstimateOptions(steps=self.ddim_steps, guidance_scale=self.guidance_scale, scales=self.scales,
                               hypotheses=self.hypotheses, max_boxes=self.batch_boxes, refine=self.refine,
                               follow_passes=self.follow_passes)  # fmt: skip


class Finder(Protocol):
    """What `FramePoser` asks of a search beside the frames (`BackgroundFinder`, offline `LockStepFinder`)."""

    def offer(self, search: Search) -> None: ...
    def idle(self) -> bool: ...
    def collect(self) -> list[tuple[Search, Found | None]]: ...
    def wait_ready(self, timeout: float) -> bool: ...
    def stop(self) -> None: ...


@dataclass(frozen=True)
class Posed:
    """One frame's poses, one entry per box: the estimate (refused ones included), its score, its box (a tracked
    pose's: its model's projection), its track (0: untracked)."""

    estimates: list[PoseEstimate]
    scores: list[float]
    boxes: list[Box]
    track_ids: list[int]


class FramePoser:
    """The estimator's side of the node's frame: which boxes, posed how, and the tracker across frames. What it
    counts (`verifier_dropped`, `tracking_<event>`, `pose_refused` of tracked crops, `refine_refined` and
    `refine_kept_<reason>` of every pose the contour refiner saw) goes to `count(key, n)`."""

    def __init__(
        self, estimator: Estimator, published: dict[int, str], count: Callable[[str, int], None], dropped: Callable[[], int] = lambda: 0,
        finder: Finder | None = None,
    ) -> None:  # fmt: skip
        """`dropped`: the frames the node dropped so far for being busy (`dropped_stale`: under `auto`, falling behind
        the camera turns following on); `finder`: where `video_odometry` searches (None: `BackgroundFinder`'s process,
        started with the first frame that needs it)."""
        self.estimator, self.published, self.count, self._dropped = estimator, published, count, dropped
        self.tracker = Tracker(TrackingConfig())
        self.chooser = ModeChooser()
        self.choice = Choice(Mode.STILLS, "no frame yet")
        """The mode the last frame ran in, and why (`mode`; what /diagnostics says)."""
        self._reported: dict[str, int] = {}
        self._finder = finder
        self._since_search = 0
        """Frames since the background's last search was offered."""
        self._searches = 0
        self._hulls: dict[int, np.ndarray] = {}
        """Per object, its mesh's convex-hull vertices (`_pose_box`)."""
        self._checked: dict[int, int] = {}
        """Per tracked object, the search that last looked for it (`_searched_objects`)."""
        self._search_posed: list[tuple[Detection, PoseEstimate]] = []
        """What the running search has posed so far (its detections come one at a time)."""

    @staticmethod
    def uses_odometry(s: PoserSettings) -> bool:
        """Whether a frame in `s.mode` wants the camera's pose (its frame then waits briefly for camera_odom)."""
        return Mode(s.mode) in (Mode.AUTO, Mode.VIDEO_ODOMETRY) and s.view_window > 0

    def stop(self) -> None:
        """End the search process of `video_odometry`, if it has one."""
        if self._finder is not None:
            self._finder.stop()

    def pose(
        self, rgb: np.ndarray, K: np.ndarray, stamp: float, rois: Sequence[tuple[int, Box]], s: PoserSettings,
        cancelled: Callable[[], bool], camera_pose: np.ndarray | None = None,
    ) -> Posed:  # fmt: skip
        """ROIs where fresh ones came; else the localiser's boxes, each posed on its own or through the tracker (with
        `camera_pose`, the camera's pose in a fixed frame at this frame, averaged over views: `view_window`)."""
        options = s.options()

        def estimate(boxes: list[tuple[int, Box]]) -> list[PoseEstimate]:
            return self._count_refined(self.estimator.estimate(rgb, K, boxes, options=options, cancelled=cancelled))

        if rois or self.estimator.localiser is None:
            self._run_in(Choice(Mode.STILLS, "boxes from ~/roi" if rois else "no localiser in the checkpoint: boxes from ~/roi only"))
            return _each(list(rois), [1.0] * len(rois), estimate)

        def find() -> Found:
            return self._counted(self.estimator.find(rgb, K, s.score_threshold, options, cancelled, objects=self.published))

        self._run_in(self.chooser.choose(Mode(s.mode), camera_pose is not None, self._dropped()))
        if not self.choice.tracking:
            if self.tracker.tracks:
                self.tracker.reset("disabled")
            found = find()
            return Posed(found.poses, [d.score for d in found.detections], [d.box for d in found.detections], [0] * len(found.poses))

        following = self.estimator.refiner is not None and s.refine
        camera_pose = camera_pose if self.choice.odometry else None
        view_window = s.view_window if self.choice.odometry else 0
        verifier = self.estimator.config.verifier

        def dets() -> list:
            """The tracker's detections: boxes it poses itself (following, or without a verifier: down to the
            verifier's least score, the new ones verified once posed); else posed already to score them."""
            if verifier is None or following:
                least = s.score_threshold if verifier is None else verifier.min_score
                return [d for d in self.estimator.detect(rgb, least) if d.obj_id in self.published]
            found = find()
            if refused := sum(not p.ok for p in found.poses):
                self.count("pose_refused", refused)
            return [Sighting(d.obj_id, d.score, d.box, p) for d, p in zip(found.detections, found.poses, strict=True)]

        self.tracker.config = TrackingConfig(
            redetect_period=s.redetect_period, measure_every=s.measure_every, track_timeout=s.track_timeout, view_window=view_window
        )
        follow = None
        if following:  # every track followed by its contour; the AGM poses the localiser's boxes of new and lost objects (verified)

            def follow(last: list, predicted: list) -> list[PoseEstimate]:
                return self._count_refined(self.estimator.follow(rgb, K, last, predicted, options))

            if view_window > 0 and camera_pose is not None:
                search = Search(
                    stamp, np.array(K, float), np.array(camera_pose, float), rgb, s.score_threshold, options, tuple(self.published)
                )
                return self._in_background(search, s, estimate, follow)
        return self._tracked(stamp, K, dets, estimate, follow, s.score_threshold, camera_pose)

    def _run_in(self, choice: Choice) -> None:
        """This frame's mode: kept for `/diagnostics`, and counted (`mode_<mode>`: frames run in each)."""
        self.choice = choice
        self.count(f"mode_{choice.mode.value}", 1)

    def _tracked(self, stamp: float, K: np.ndarray, detect, estimate, follow, threshold: float, camera_pose=None) -> Posed:
        """The tracked objects' filtered poses on this frame (followed by their contours where `follow` is given; a
        pose of a localiser's box then verified, below `threshold` refused and counted as `verifier_dropped`); crops
        the estimator refused are counted, and what following did tells `auto` whether contours hold."""

        def measure(crops: list[Crop]) -> list[PoseEstimate]:
            out = estimate([(c.obj_id, c.box) for c in crops])
            if follow is not None:
                new = [k for k, c in enumerate(crops) if c.detected]
                checked = self.estimator.verified([crops[k].score for k in new], [out[k] for k in new], threshold)
                for k, p in zip(new, checked, strict=True):
                    if out[k].ok and not p.ok:
                        self.count("verifier_dropped", 1)
                    out[k] = p
            if refused := sum(not e.ok and e.reason != "verifier" for e in out):
                self.count("pose_refused", refused)
            return out

        tracked = self.tracker.step(stamp, K, detect, measure, follow, camera_pose)
        new = self._new_counts()
        for key, n in new.items():
            self.count(f"tracking_{key}", n)
        self.chooser.record(new.get("followed", 0), new.get("contour_lost", 0) + new.get("ended_unfollowable", 0))
        estimates = [dataclasses.replace(tp.measurement, R=tp.R, t=tp.t, covariance=tp.covariance) for tp in tracked]
        boxes = [self._pose_box(e, K) or tp.box for e, tp in zip(estimates, tracked, strict=True)]
        return Posed(estimates, [tp.score for tp in tracked], boxes, [tp.track_id for tp in tracked])

    def _pose_box(self, estimate: PoseEstimate, K: np.ndarray) -> Box | None:
        """A tracked pose's box as a localiser draws one: its model's projection at the pose (the track's own box
        is the one it was last cropped from, which trails a pose followed by its contour); None without the
        checkpoint's meshes or a pose."""
        meshes = None if self.estimator is None else self.estimator.meshes
        if meshes is None or not estimate.ok:
            return None
        if estimate.obj_id not in self._hulls:  # the box of the hull's projection is the mesh's, at a fraction of the cost
            self._hulls[estimate.obj_id] = hull_points(meshes[estimate.obj_id][0])
        uv = project_model(K, estimate.R, estimate.t, self._hulls[estimate.obj_id])
        (x0, y0), (x1, y1) = uv.min(axis=0), uv.max(axis=0)
        return float(x0), float(y0), float(x1 - x0), float(y1 - y0)

    def _in_background(self, search: Search, s: PoserSettings, estimate, follow) -> Posed:
        """Tracking with the localiser and the AGM in a process of their own (`background.py`): what they found on
        earlier frames joins the objects' views (`_take_found`), this frame is followed (its objects recalled from
        their views), and it is searched next where the last search is done and `redetect_period` frames have
        passed since one was offered, or where nothing is tracked."""
        self.start_background(s)
        self._take_found(search)
        posed = self._tracked(search.stamp, search.K, None, estimate, follow, s.score_threshold, search.camera)
        self._since_search += 1
        if self._finder.idle() and (self._since_search >= s.redetect_period or not self.tracker.tracks):
            self._finder.offer(dataclasses.replace(search, objects=self._searched_objects(search.objects)))
            self._since_search = 0
            self.count("background_searches", 1)
        return posed

    def _take_found(self, now: Search) -> None:
        """What the search process found since the last frame joins the objects' views as it comes (a search's
        detections one at a time, the likeliest first); once a search is done, all its poses challenge the tracks
        away from them (`Tracker.challenge`: two poses of an object are two instances, and challenge none). A search
        from before a reset (stamps going back, other intrinsics) is left out."""
        for earlier, found in self._finder.collect():
            current = earlier.stamp <= now.stamp and np.allclose(earlier.K, now.K)
            if found is None:
                posed, self._search_posed = self._search_posed, []
                if current:
                    self.tracker.challenge(earlier.camera, posed)
                continue
            found = self._counted(found)
            posed = [(d, p) for d, p in zip(found.detections, found.poses, strict=True) if p.ok]
            self._search_posed += posed
            if current:
                self.tracker.observe(earlier.camera, posed)

    def _searched_objects(self, objects: tuple[int, ...]) -> tuple[int, ...]:
        """What a search looks for: the objects no track holds, and of the tracked ones the one looked for longest
        ago (a fresh pose to check its track against). Posing each box found is most of a search's time: searching
        for fewer objects brings back sooner an object that comes back into view."""
        held = {tr.obj_id for tr in self.tracker.tracks}
        self._checked = {o: n for o, n in self._checked.items() if o in held}
        checked = min((o for o in objects if o in held), key=lambda o: self._checked.get(o, -1), default=None)
        self._searches += 1
        if checked is not None:
            self._checked[checked] = self._searches
        return tuple(o for o in objects if o not in held or o == checked)

    def start_background(self, s: PoserSettings, wait: float = 0.0) -> None:
        """Start the search process of `video_odometry` now (else the first frame that needs it does), and
        wait up to `wait` s for it to load its checkpoint."""
        if self._finder is None:
            precision = "bfloat16" if self.estimator.bf16 else "float32"
            searcher = Searcher(s.checkpoint, str(self.estimator.device), precision, max(1, s.num_threads - 1))
            self._finder = BackgroundFinder(searcher, lambda err: self.count("background_failed", 1))
        self._finder.wait_ready(wait)

    def _counted(self, found: Found) -> Found:
        """What the localiser found and posed, its refinements and the verifier's drops counted."""
        self._count_refined(found.poses)
        if found.dropped:
            self.count("verifier_dropped", found.dropped)
        return found

    def _count_refined(self, estimates: list[PoseEstimate]) -> list[PoseEstimate]:
        """Count what the contour refiner did with each pose it saw (`refine_refined`, `refine_kept_<reason>`)."""
        for e in estimates:
            if e.refined:
                self.count("refine_refined", 1)
            elif e.refine_kept:
                self.count(f"refine_kept_{e.refine_kept}", 1)
        return estimates

    def _new_counts(self) -> dict[str, int]:
        """The tracker's counts (`tracks_started`, `reset_stamps_backwards`, ...) added since the last call."""
        now = dict(self.tracker.counts)
        new = {k: n - self._reported.get(k, 0) for k, n in now.items() if n != self._reported.get(k, 0)}
        self._reported = now
        return new


def _each(boxes: list[tuple[int, Box]], scores: list[float], estimate: Callable[[list[tuple[int, Box]]], list[PoseEstimate]]) -> Posed:
    """Every box posed on its own."""
    estimates = estimate(boxes)
    return Posed(estimates, scores, [b for _, b in boxes], [0] * len(estimates))
