"""Pairing Images with CameraInfos by stamp (message_filters' ApproximateTime is not installable here), and
counting the frames a best-effort transport lost.

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


class GapCounter:
    """Frames a best-effort transport lost, estimated from the image stamps: the camera's period is the median of
    the recent intervals, and an interval of n periods (n >= 2, rounded) means n - 1 frames never arrived.
    Intervals that go back or are not positive are left out (time jumps, repeated stamps)."""

    def __init__(self, window: int = 30) -> None:
        self.intervals: deque[float] = deque(maxlen=window)
        self.last: float | None = None
        self.lost = 0

    def add(self, stamp: float) -> int:
        """Record an image stamp; returns the frames estimated lost just before it."""
        lost = 0
        if self.last is not None and stamp > self.last:
            dt = stamp - self.last
            if len(self.intervals) >= 5:
                period = sorted(self.intervals)[len(self.intervals) // 2]
                lost = max(0, round(dt / period) - 1) if period > 0 else 0
            if lost == 0:
                self.intervals.append(dt)  # gaps do not teach the period
        self.last = stamp
        self.lost += lost
        return lost


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
