"""The localiser and the AGM in a process of their own, for tracking with the camera's pose: a frame that only follows
its objects by their contours (a few ms each) is not held up by the AGM's 100-300 ms, so the node keeps up with a
camera stream. A process, not a thread: the search's Python and NumPy work (decoding, the TBM, refining what it
found) would otherwise take turns with the following's for the interpreter's lock. It runs at a lower CPU priority,
so the frames come first and the search takes the time left. What it finds on a frame comes back with that frame's
camera pose and joins the objects' views in the fixed frame (`Tracker.observe`), from where the tracker follows them
on the frame at hand. Offline (`axispose validate`, benches), `LockStepFinder` searches in the caller's process
instead, each search handed over a set number of frames later: the same run every time."""

from __future__ import annotations

import multiprocessing
import os
import signal
import time
from collections.abc import Callable
from dataclasses import dataclass
from multiprocessing.connection import Connection

import numpy as np

from axispose_core.estimator import EstimateOptions, Estimator
from axispose_core.pose_estimate import Found

READY = "ready"
"""What the process sends once its checkpoint is loaded (or failed to load)."""
DONE = "done"
"""What the process sends after a search's last detection."""


@dataclass(frozen=True)
class Search:
    """One frame to search: its stamp, intrinsics, camera pose (4x4, camera to fixed) and image, and how (the least
    published score, the estimate options, the objects to look for)."""

    stamp: float
    K: np.ndarray
    camera: np.ndarray
    rgb: np.ndarray
    threshold: float
    options: EstimateOptions
    objects: tuple[int, ...]


@dataclass(frozen=True)
class Searcher:
    """What the search process loads (checkpoint, device, the AGM's precision) and how it runs: OpenMP `threads`, and
    `nice` added to its CPU niceness."""

    checkpoint: str
    device: str = "cpu"
    precision: str = "float32"
    threads: int = 1
    nice: int = 10


class BackgroundFinder:
    """`Searcher`'s process, fed one `Search` at a time: one offered while another runs waits (the newest replaces
    an older one waiting), and `collect` hands over what each found, a detection at a time as it is posed (the
    localiser's likeliest first), then the search with None once it is done (every search offered ends so). A
    search that fails, or a process that ended (it is started again on the next search), goes to `on_error`."""

    def __init__(self, searcher: Searcher, on_error: Callable[[Exception], None]) -> None:
        self._searcher, self._on_error = searcher, on_error
        self._process: multiprocessing.process.BaseProcess | None = None
        self._conn: Connection | None = None
        self._running: Search | None = None
        """Sent to the process, not answered yet."""
        self._waiting: Search | None = None
        self._done: list[tuple[Search, Found | None]] = []
        self._ready = False
        self._start()

    def offer(self, search: Search) -> None:
        """Search this frame as soon as the process is free (replacing one offered that has not started)."""
        self._poll()
        if self._running is None:
            self._send(search)
        else:
            self._waiting = search

    def idle(self) -> bool:
        """No search runs or waits."""
        self._poll()
        return self._running is None and self._waiting is None

    def collect(self) -> list[tuple[Search, Found | None]]:
        """What the searches found since the last call, in the order found: (search, one detection's `Found`), and
        (search, None) where the search is done."""
        self._poll()
        done, self._done = self._done, []
        return done

    def alive(self) -> bool:
        return self._process is not None and self._process.is_alive()

    def wait_ready(self, timeout: float) -> bool:
        """Wait up to `timeout` s for the process to have loaded its checkpoint (or failed to); whether it has."""
        end = time.monotonic() + timeout
        while True:
            self._poll()
            if self._ready or time.monotonic() >= end:
                return self._ready
            time.sleep(0.01)

    def stop(self, timeout: float = 5.0) -> None:
        """End the process (after the search it runs, within `timeout` s; then it is terminated)."""
        if self._process is None:
            return
        try:
            self._conn.send(None)
        except (OSError, ValueError):  # the process has gone already
            pass
        self._process.join(timeout)
        if self._process.is_alive():
            self._process.terminate()
            self._process.join(timeout)
        self._conn.close()
        self._process, self._running, self._waiting = None, None, None

    def _start(self) -> None:
        context = multiprocessing.get_context("spawn")  # never fork a process with ROS and OpenMP threads running
        self._conn, theirs = context.Pipe()
        self._process = context.Process(target=_serve, args=(theirs, self._searcher), name="axispose_background", daemon=True)
        self._process.start()
        theirs.close()

    def _send(self, search: Search) -> None:
        if not self.alive():
            self._on_error(RuntimeError("the background search process had ended: started again"))
            self._conn.close()
            self._ready = False
            self._start()
        try:
            self._conn.send(search)
        except (OSError, ValueError) as err:  # it ended just now: the next search starts it again
            self._on_error(RuntimeError(f"background search: {err}"))
            return
        self._running = search

    def _poll(self) -> None:
        """Take what the process sent (that it is ready; the running search's answer), and send the waiting search."""
        try:
            while self._conn.poll():
                self._answer(self._conn.recv())
            if self._running is not None and not self.alive():
                raise EOFError("the background search process ended")
        except (EOFError, OSError) as err:
            if self._running is not None:
                self._answer(RuntimeError(f"background search: {err}"))

    def _answer(self, answer: object) -> None:
        if answer == READY:
            self._ready = True
            return
        if isinstance(answer, Found) and self._running is not None:  # one detection: the search goes on
            self._done.append((self._running, answer))
            return
        if isinstance(answer, Exception):  # the search ends with what it found before
            self._on_error(answer)
        if self._running is not None:
            self._done.append((self._running, None))
        self._running = None
        if self._waiting is not None:
            search, self._waiting = self._waiting, None
            self._send(search)


class LockStepFinder:
    """`BackgroundFinder` in this process, counted in frames rather than time: a search offered is done at once
    (`Estimator.find_each`), its k-th detection handed over by the n-th `collect` after it (`FramePoser` collects
    once a frame), n = `delay(k)` (default: 1, the next frame), and its end with its last detection. Frames wait
    for the search, so a run repeats exactly whatever the machine's speed."""

    def __init__(self, estimator: Estimator, delay: Callable[[int], int] = lambda boxes: 1) -> None:
        self.estimator, self.delay = estimator, delay
        self._due: list[tuple[int, Search, Found | None]] = []
        """What the search hands over, each with the collect it is due at."""
        self._collects = 0

    def offer(self, search: Search) -> None:
        est = self.estimator
        found = list(est.find_each(search.rgb, search.K, search.threshold, search.options, objects=search.objects))
        self._collects = 0
        self._due = [(self.delay(k + 1), search, f) for k, f in enumerate(found)] + [(self.delay(len(found)), search, None)]

    def idle(self) -> bool:
        return not self._due

    def collect(self) -> list[tuple[Search, Found | None]]:
        self._collects += 1
        done = [(search, found) for due, search, found in self._due if due <= self._collects]
        self._due = [d for d in self._due if d[0] > self._collects]
        return done

    def wait_ready(self, timeout: float = 0.0) -> bool:
        return True

    def stop(self) -> None:
        self._due = []


def _serve(conn: Connection, searcher: Searcher) -> None:
    """The search process: load the estimator, then answer each search with what it found, a detection at a time
    and then `DONE`, or with the error that stopped it (every search with the loading error if the checkpoint did
    not load), until told to stop."""
    import torch

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the node's Ctrl-C is the node's to handle: it stops this
    try:
        os.nice(searcher.nice)
    except OSError:
        pass
    torch.set_num_threads(searcher.threads)
    estimator, failed = None, None
    try:
        estimator = Estimator.load(searcher.checkpoint, searcher.device)
        estimator.set_precision(searcher.precision)
    except Exception as err:  # answered to every search: the node counts them
        failed = RuntimeError(f"background search: the checkpoint did not load: {err}")
    if not _sent(conn, READY):
        return
    while True:
        try:
            search = conn.recv()
        except (EOFError, OSError):  # the node has gone
            return
        if search is None:
            return
        try:
            if failed is not None:
                raise failed
            for found in estimator.find_each(search.rgb, search.K, search.threshold, search.options, objects=search.objects):
                if not _sent(conn, found):
                    return
            answer = DONE
        except Exception as err:
            answer = err if isinstance(err, RuntimeError) else RuntimeError(f"background search failed: {err!r}")
        if not _sent(conn, answer):
            return


def _sent(conn: Connection, message: object) -> bool:
    """Send `message` to the node; False where the node has gone."""
    try:
        conn.send(message)
    except (OSError, ValueError):
        return False
    return True
