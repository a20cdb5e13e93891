"""Pairing Images with CameraInfos by stamp (message_filters' ApproximateTime is not installable here).

An image is paired with the CameraInfo nearest in time within `slop` seconds. Images wait (a few, bounded)
for their CameraInfo; an image that cannot be paired any more — a CameraInfo later than its stamp + slop has
arrived without a match, or it was pushed out of the waiting queue — is dropped and reported.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from typing import Generic, TypeVar

I = TypeVar("I")
C = TypeVar("C")  # camera-info type


class StampSynchronizer(Generic[I, C]):
    """Feed `add_image(stamp, image)` and `add_info(stamp, info)`; matched pairs go to `on_pair(image, info)`,
    images given up on go to `on_drop(image, reason)`. Stamps are seconds (float). Not thread-safe: call it
    from one callback group."""

    def __init__(
        self,
        slop: float,
        on_pair: Callable[[I, C], None],
        on_drop: Callable[[I, str], None],
        max_images: int = 5,
        max_infos: int = 30,
    ) -> None:
        if not slop >= 0:
            raise ValueError(f"slop must be >= 0 seconds, got {slop}")
        self.slop = slop
        self.on_pair, self.on_drop = on_pair, on_drop
        self.images: deque[tuple[float, I]] = deque()
        self.infos: deque[tuple[float, C]] = deque(maxlen=max_infos)
        self.max_images = max_images

    def add_info(self, stamp: float, info: C) -> None:
        self.infos.append((stamp, info))
        self._flush()

    def add_image(self, stamp: float, image: I) -> None:
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
        newest_info = self.infos[-1][0] if self.infos else None
        waiting: deque[tuple[float, I]] = deque()
        for stamp, image in self.images:
            info = self._best(stamp)
            if info is not None:
                self.on_pair(image, info)
            elif newest_info is not None and newest_info > stamp + self.slop:
                self.on_drop(image, "no_camera_info")
            else:
                waiting.append((stamp, image))
        self.images = waiting
