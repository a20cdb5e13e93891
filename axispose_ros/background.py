"""The localiser and the AGM on a thread of their own, for tracking with the camera's pose: a frame that only follows
its objects by their contours (a few ms each) is not held up by the AGM's 100-200 ms, so the node keeps up with a
camera stream. What they find on a frame comes back with that frame's camera pose, and joins the objects' views in
the fixed frame (`Tracker.observe`), from where the tracker follows them on the frame at hand."""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from axispose_core.estimator import Found
from axispose_ros.worker import InferenceWorker


@dataclass(frozen=True)
class Search:
    """One frame for the background: its stamp, intrinsics and camera pose (4x4, camera to fixed), and the call that
    finds and poses its objects (given the thread's `cancelled`)."""

    stamp: float
    K: np.ndarray
    camera: np.ndarray
    find: Callable[[Callable[[], bool]], Found]


class BackgroundFinder:
    """Runs `Search.find` on a thread of its own (an `InferenceWorker`, `threads` OpenMP threads) for the newest
    search offered; `collect` hands over what the finished ones found. A search that fails goes to `on_error`."""

    def __init__(self, threads: int, on_error: Callable[[Exception], None]) -> None:
        self._done: list[tuple[Search, Found]] = []
        self._lock = threading.Lock()
        self._worker: InferenceWorker[Search] = InferenceWorker(self._run, lambda: None, on_error, threads, name="axispose_background")
        self._worker.start()

    def offer(self, search: Search) -> None:
        """Search this frame next (replacing one offered that has not started)."""
        self._worker.submit(search)

    def idle(self) -> bool:
        """No search waits or runs."""
        return self._worker.idle()

    def alive(self) -> bool:
        return self._worker.alive()

    def collect(self) -> list[tuple[Search, Found]]:
        """The searches finished since the last call, oldest first, with what they found."""
        with self._lock:
            done, self._done = self._done, []
        return done

    def stop(self) -> None:
        """Cancel the search in progress (at its next DDIM step) and end the thread."""
        self._worker.stop()

    def _run(self, search: Search) -> None:
        found = search.find(self._worker.cancelled)
        with self._lock:
            self._done.append((search, found))
