"""Pairing Images with CameraInfos by stamp (message_filters' ApproximateTime is not installable here), and
auditing the image stamps: frames a best-effort transport lost, stamps that cannot be on the camera's timeline.

An image is paired with the CameraInfo nearest in time within `slop` seconds, whichever of the two arrives
first and in whatever order the CameraInfos come (within `reorder` seconds). Images wait (a few, bounded) for
their CameraInfo. An image is given up on, and reported, when it cannot be paired any more (a CameraInfo later
than its stamp + slop + reorder has arrived without a match), when it is pushed out of the waiting queue, when it
is older than an image already paired (the node only wants the latest), or when time jumps back (a bag that
loops, a simulator reset): a stamp more than `jump` seconds older than the newest seen clears the state.
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Generic, TypeVar

I = TypeVar("I")
C = TypeVar("C")  # camera-info type


class StampSynchronizer(Generic[I, C]):
    """Feed `add_image(stamp, image)` and `add_info(stamp, info)`; matched pairs go to `on_pair(image, info)`,
    images given up on go to `on_drop(image, reason)` (reasons: no_camera_info, out_of_order, time_jump).
    Stamps are seconds (float). Not thread-safe: call it from one callback group."""

    def __init__(
        self,
        slop: float,
        on_pair: Callable[[I, C], None],
        on_drop: Callable[[I, str], None],
        max_images: int = 5,
        max_infos: int = 30,
        reorder: float = 0.2,
        jump: float = 1.0,
    ) -> None:
        if not slop >= 0 or not reorder >= 0 or not jump > 0:
            raise ValueError(f"slop and reorder must be >= 0 and jump > 0 seconds, got {slop}, {reorder} and {jump}")
        self.slop, self.reorder, self.jump = slop, reorder, max(jump, slop + reorder)
        self.on_pair, self.on_drop = on_pair, on_drop
        self.images: deque[tuple[float, I]] = deque()
        self.infos: deque[tuple[float, C]] = deque(maxlen=max_infos)
        self.max_images = max_images
        self.newest = float("-inf")
        """The newest stamp seen on either topic."""
        self.last_paired = float("-inf")
        self.jumps = 0
        """Times the state was cleared because time went back."""

    def _clock(self, stamp: float) -> None:
        if stamp < self.newest - self.jump:
            for _, image in self.images:
                self.on_drop(image, "time_jump")
            self.images.clear()
            self.infos.clear()
            self.newest = self.last_paired = float("-inf")
            self.jumps += 1
        self.newest = max(self.newest, stamp)

    def add_info(self, stamp: float, info: C) -> None:
        self._clock(stamp)
        self.infos.append((stamp, info))
        self._flush()

    def add_image(self, stamp: float, image: I) -> None:
        self._clock(stamp)
        if stamp <= self.last_paired:
            self.on_drop(image, "out_of_order")
            return
        self.images.append((stamp, image))
        while len(self.images) > self.max_images:
            _, old = self.images.popleft()
            self.on_drop(old, "no_camera_info")
        self._flush()

    def _best(self, stamp: float) -> C | None:
        best, best_dt = None, None
        for s, info in self.infos:
            dt = abs(s - stamp)
            if dt <= self.slop and (best_dt is None or dt < best_dt):
                best, best_dt = info, dt
        return best

    def _flush(self) -> None:
        newest_info = max((s for s, _ in self.infos), default=None)
        waiting: deque[tuple[float, I]] = deque()
        for stamp, image in sorted(self.images, key=lambda e: e[0]):
            info = self._best(stamp)
            if stamp <= self.last_paired:
                self.on_drop(image, "out_of_order")
            elif info is not None:
                self.last_paired = stamp
                self.on_pair(image, info)
            elif newest_info is not None and newest_info > stamp + self.slop + self.reorder:
                self.on_drop(image, "no_camera_info")
            else:
                waiting.append((stamp, image))
        self.images = waiting


STAMP_ANOMALIES = ("zero", "backwards", "future", "discontinuity")
"""What `StampAudit` can find wrong with an image stamp (each its own `stamps_<anomaly>` counter in the node)."""


@dataclass(frozen=True)
class StampVerdict:
    lost: int = 0
    """Frames estimated lost in transport just before this one."""
    anomaly: str | None = None
    """One of STAMP_ANOMALIES, or None for a stamp on the camera's timeline."""


class StampAudit:
    """Frames a best-effort transport lost, estimated from the image stamps, and the stamps that say nothing about
    it. The camera's period is the median of the recent intervals; an interval of n periods (rounded) means n - 1
    frames never arrived. A stamp is left off the timeline when it is zero or negative (`zero`: a driver that does
    not stamp) or more than `future_s` ahead of `now` (`future`); one not later than the previous is `backwards` (a
    bag that loops, a repeated stamp), and the interval after it is not read; an interval of more than `max_gap`
    missing frames is a `discontinuity` (the camera paused, its clock stepped), not loss. Whatever the stamps, the
    total lost never exceeds the frames seen: with more than half the frames lost it reads low, a lower bound."""

    def __init__(self, window: int = 30, max_gap: int = 30, future_s: float = 10.0) -> None:
        self.intervals: deque[float] = deque(maxlen=window)
        self.max_gap, self.future_s = max_gap, future_s
        self.last: float | None = None
        """The last stamp on the timeline."""
        self.seen = 0
        self.lost = 0
        self._resync = False

    def add(self, stamp: float, now: float | None = None) -> StampVerdict:
        """Record an image stamp (s); `now` is the receiver's clock in the stamps' time base (None: unknown, e.g. a
        simulated clock not yet received), against which `future` is judged."""
        self.seen += 1
        if not stamp > 0:
            return StampVerdict(anomaly="zero")
        if now is not None and stamp > now + self.future_s:
            return StampVerdict(anomaly="future")
        last, self.last = self.last, stamp
        if last is None:
            return StampVerdict()
        if stamp <= last:
            self._resync = True
            return StampVerdict(anomaly="backwards")
        dt = stamp - last
        if self._resync:  # from a stamp that stepped back: the interval tells neither period nor loss
            self._resync = False
            return StampVerdict()
        period = sorted(self.intervals)[len(self.intervals) // 2] if len(self.intervals) >= 5 else None
        ratio = dt / period if period else 1.0
        if ratio >= self.max_gap + 1.5:  # compared before rounding: a ratio of 1e18 is a clock, not a count
            return StampVerdict(anomaly="discontinuity")
        missing = round(ratio) - 1
        if missing <= 0:
            self.intervals.append(dt)  # gaps do not teach the period
            return StampVerdict()
        lost = min(missing, self.seen - self.lost)
        self.lost += lost
        return StampVerdict(lost=lost)


Box = tuple[float, float, float, float]


class RoiStore:
    """The latest box (a RegionOfInterest-like message: x_offset, y_offset, width, height) received for each
    object and when, shared between the executor that adds them and the thread that reads them."""

    def __init__(self) -> None:
        self._boxes: dict[int, tuple[Any, float]] = {}
        self._lock = threading.Lock()

    def add(self, obj_id: int, roi: Any, now: float) -> None:
        with self._lock:
            self._boxes[obj_id] = (roi, now)

    def latest(self, obj_id: int) -> Any | None:
        """The last box received for an object (None before any)."""
        with self._lock:
            entry = self._boxes.get(obj_id)
        return entry[0] if entry else None

    def fresh(self, now: float, timeout: float, width: int, height: int) -> tuple[list[tuple[int, Box]], int]:
        """The boxes at most `timeout` seconds old and not empty, as (obj_id, (x, y, w, h)), and how many fresh
        ones reached outside a `width` x `height` image (left out)."""
        with self._lock:
            entries = list(self._boxes.items())
        boxes, outside = [], 0
        for obj_id, (roi, seen) in entries:
            if now - seen > timeout or roi.width == 0 or roi.height == 0:
                continue
            if roi.x_offset + roi.width > width or roi.y_offset + roi.height > height:
                outside += 1
                continue
            boxes.append((obj_id, (roi.x_offset, roi.y_offset, roi.width, roi.height)))
        return boxes, outside
