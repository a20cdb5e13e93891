"""The node's inference thread: a latest-frame-wins slot and the one thread that empties it, so the executor
never blocks and a frame that waited while another was in inference is replaced (and counted) instead of queued."""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Generic, TypeVar

import torch

from axispose_core.agm.sampler import Cancelled

F = TypeVar("F")


class InferenceWorker(Generic[F]):
    """Runs `process(frame)` on its own thread for the latest `submit`ted frame. `warm_up()` runs first, before
    `start` returns; an exception from `process` goes to `on_error` and the thread goes on; `Cancelled` (raised
    by sampling once `cancelled()` is true, i.e. on `stop`) ends it. The thread has its own OpenMP team of
    `threads`: the caller's thread should not run a team of several beside it (libgomp then stops spinning)."""

    def __init__(
        self,
        process: Callable[[F], None],
        warm_up: Callable[[], None],
        on_error: Callable[[Exception], None],
        threads: int,
        name: str = "axispose_inference",
    ) -> None:
        self._process, self._warm_up, self._on_error, self._threads = process, warm_up, on_error, threads
        self._slot: F | None = None
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._stopped = threading.Event()
        self._ready = threading.Event()
        self.busy = False
        """A frame is in `process` now."""
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)

    def start(self) -> None:
        """Start the thread and wait until it has warmed up."""
        self._thread.start()
        self._ready.wait()

    def submit(self, frame: F) -> bool:
        """Put `frame` into the slot; True when it replaced a frame that had not been taken yet (a stale one)."""
        with self._lock:
            stale, self._slot = self._slot is not None, frame
        self._wake.set()
        return stale

    def cancelled(self) -> bool:
        """Whether `stop` was called: what sampling asks between DDIM steps."""
        return self._stopped.is_set()

    def idle(self) -> bool:
        """No frame waits in the slot or is in `process`."""
        with self._lock:
            return self._slot is None and not self.busy

    def alive(self) -> bool:
        return self._thread.is_alive()

    def stop(self, timeout: float = 10.0) -> None:
        """Cancel the frame in progress (at its next DDIM step) and end the thread."""
        self._stopped.set()
        self._wake.set()
        if self._thread.is_alive():
            self._thread.join(timeout=timeout)

    def _run(self) -> None:
        torch.set_num_threads(self._threads)
        try:
            self._warm_up()
        finally:
            self._ready.set()
        while not self._stopped.is_set():
            if not self._wake.wait(timeout=0.1):
                continue
            with self._lock:
                frame, self._slot = self._slot, None
                self._wake.clear()
                self.busy = frame is not None
            if frame is None:
                continue
            try:
                self._process(frame)
            except Cancelled:  # stopping mid-frame: the frame is abandoned, not dropped
                return
            except Exception as err:
                self._on_error(err)
            finally:
                with self._lock:
                    self.busy = False
