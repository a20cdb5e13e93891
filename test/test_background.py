"""The node's background search thread: the newest frame offered, what it found handed back once, failures counted."""

import threading
import time

import numpy as np

from axispose_core.estimator import Found
from axispose_ros.background import BackgroundFinder, Search


def _wait(condition, timeout: float = 5.0) -> bool:
    end = time.monotonic() + timeout
    while not condition() and time.monotonic() < end:
        time.sleep(0.005)
    return condition()


def test_the_background_searches_the_newest_frame_offered_and_hands_back_what_it_found():
    """While a search runs, frames offered replace each other (the newest is searched next); `collect` hands over
    each finished search once, oldest first; a search that fails goes to `on_error` and the thread goes on; `stop`
    ends it."""
    release, started, errors = threading.Event(), [], []

    def search(stamp: float, fail: bool = False) -> Search:
        def find(cancelled) -> Found:
            started.append(stamp)
            if stamp == 0.0:
                release.wait(5.0)
            if fail:
                raise RuntimeError("localiser failed")
            return Found([], [])

        return Search(stamp, np.eye(3), np.eye(4), find)

    finder = BackgroundFinder(1, errors.append)
    try:
        finder.offer(search(0.0))
        assert _wait(lambda: started == [0.0])
        finder.offer(search(1.0))
        finder.offer(search(2.0))  # replaces 1.0, which had not started
        assert not finder.idle() and finder.collect() == []
        release.set()
        assert _wait(finder.idle)
        assert [s.stamp for s, _ in finder.collect()] == [0.0, 2.0] and started == [0.0, 2.0]
        assert finder.collect() == []
        finder.offer(search(3.0, fail=True))
        assert _wait(lambda: len(errors) == 1 and finder.idle())
        assert isinstance(errors[0], RuntimeError) and finder.collect() == [] and finder.alive()
    finally:
        finder.stop()
    assert not finder.alive()
