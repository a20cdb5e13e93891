"""The search beside the frames: the node's process (the newest frame offered, what it found handed back once, failures
counted) and the offline lock-step one."""

import time

import numpy as np
import pytest

from axispose_core.estimator import EstimateOptions
from axispose_core.lmo import LMO_K
from axispose_core.tracking.background import BackgroundFinder, LockStepFinder, Search, Searcher


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    """The tiny estimator with an untrained localiser of ape and can: at threshold 0 it finds both."""
    from conftest import save_tiny_estimator

    from axispose_core.estimator import Estimator
    from axispose_core.localiser.model import Localiser, LocaliserConfig
    from axispose_core.trunks.residual import ResidualBNConfig

    path = save_tiny_estimator(tmp_path_factory.mktemp("bg") / "tiny.safetensors")
    localiser = Localiser(LocaliserConfig(obj_ids=(1, 5), input_size=(160, 128), trunk=ResidualBNConfig(widths=(8, 16, 24, 32))))
    Estimator.load(path).with_localiser(localiser).save(path)
    return path


def _search(stamp: float, K=LMO_K) -> Search:
    rgb = np.random.default_rng(0).integers(0, 255, (480, 640, 3), dtype=np.uint8)
    return Search(stamp, np.asarray(K, float), np.eye(4), rgb, 0.0, EstimateOptions(steps=1), (1, 5))


def _wait(condition, timeout: float = 60.0) -> bool:
    end = time.monotonic() + timeout
    while not condition() and time.monotonic() < end:
        time.sleep(0.01)
    return condition()


def test_the_background_searches_the_newest_frame_offered_and_hands_back_what_it_found(checkpoint):
    """While a search runs, frames offered replace each other (the newest is searched next); `collect` hands over
    what each search found once, a detection at a time, the localiser's likeliest first, then the search's end
    (None); a search that fails goes to `on_error` and the process goes on; `stop` ends it."""
    errors = []
    finder = BackgroundFinder(Searcher(str(checkpoint)), errors.append)
    try:
        for stamp in (1.0, 2.0, 3.0):  # 2.0 waits while 1.0 runs, and 3.0 replaces it
            finder.offer(_search(stamp))
        assert not finder.idle()
        assert _wait(finder.idle)
        done = finder.collect()
        assert [s.stamp for s, found in done if found is None] == [1.0, 3.0] and errors == [] and done[-1][1] is None
        for stamp in (1.0, 3.0):
            each = [found for s, found in done if s.stamp == stamp]
            assert each[-1] is None and all(len(f.detections) + f.dropped == 1 == len(f.poses) for f in each[:-1])
            assert {d.obj_id for f in each[:-1] for d in f.detections} == {1, 5}
            scores = [f.detections[0].score for f in each[:-1]]
            assert scores == sorted(scores, reverse=True)
        assert finder.collect() == []
        finder.offer(_search(4.0, K=np.zeros((3, 3))))  # no intrinsics: the estimator refuses the frame
        assert _wait(finder.idle) and len(errors) == 1 and finder.alive()
        assert [(s.stamp, found) for s, found in finder.collect()] == [(4.0, None)]  # it ends, having found nothing
    finally:
        finder.stop()
    assert not finder.alive()


def test_a_search_process_that_cannot_load_or_ended_is_counted_not_a_crash(checkpoint, tmp_path):
    """A checkpoint the process cannot load answers every search with that error; a process that ended is started
    again on the next search (its end an error too)."""
    errors: list[Exception] = []
    finder = BackgroundFinder(Searcher(str(tmp_path / "missing.safetensors")), errors.append)
    try:
        finder.offer(_search(1.0))
        assert _wait(finder.idle) and len(errors) == 1 and "did not load" in str(errors[0])
    finally:
        finder.stop()
    errors.clear()
    finder = BackgroundFinder(Searcher(str(checkpoint)), errors.append)
    try:
        finder._process.kill()
        finder._process.join(10)
        finder.offer(_search(1.0))
        assert _wait(finder.idle) and [s.stamp for s, found in finder.collect() if found is None] == [1.0]
        assert len(errors) == 1 and "ended" in str(errors[0]) and finder.alive()
    finally:
        finder.stop()


def test_a_search_looks_for_the_untracked_objects_and_one_tracked_object_in_turn():
    """Posing the boxes found is most of a search: it looks for the objects no track holds, and for one tracked
    object each time, the one looked for longest ago (its track checked against a fresh pose)."""
    from types import SimpleNamespace

    from axispose_core.tracking.poser import FramePoser

    poser = FramePoser(None, {1: "ape", 5: "can", 6: "cat", 8: "driller"}, lambda key, n: None)
    poser.tracker.tracks = [SimpleNamespace(obj_id=1), SimpleNamespace(obj_id=5)]
    looked = [poser._searched_objects((1, 5, 6, 8)) for _ in range(4)]
    assert looked == [(1, 6, 8), (5, 6, 8), (1, 6, 8), (5, 6, 8)]
    poser.tracker.tracks = [SimpleNamespace(obj_id=5), SimpleNamespace(obj_id=8)]  # 1 lost, 8 found
    assert poser._searched_objects((1, 5, 6, 8)) == (1, 6, 8)  # 8 never looked for since it is tracked
    poser.tracker.tracks = []
    assert poser._searched_objects((1, 5, 6, 8)) == (1, 5, 6, 8)


def test_a_searchs_detections_join_the_views_as_they_come_and_challenge_tracks_once_it_is_done():
    """Each detection the search hands over joins the views at once (`observe`); the tracks are challenged once,
    with all of the search's poses, when it is done (two poses of one object in a search are two instances); a
    search from before a reset (a later stamp than the frame's) joins nothing."""
    from types import SimpleNamespace

    from axispose_core.pose_estimate import Found
    from axispose_core.tracking.poser import FramePoser

    def found(obj_id: int, ok: bool = True) -> Found:
        return Found([SimpleNamespace(obj_id=obj_id)], [SimpleNamespace(ok=ok, refined=False, refine_kept=None)])

    early, late = _search(1.0), _search(9.0)
    batches = [[(early, found(1)), (early, found(5, ok=False))], [(early, found(1)), (early, None), (late, found(5)), (late, None)]]
    finder = SimpleNamespace(collect=lambda: batches.pop(0))
    poser = FramePoser(None, {1: "ape", 5: "can"}, lambda key, n: None, finder=finder)
    calls = []
    poser.tracker.observe = lambda camera, posed: calls.append(("observe", [d.obj_id for d, _ in posed]))
    poser.tracker.challenge = lambda camera, posed: calls.append(("challenge", [d.obj_id for d, _ in posed]))
    poser._take_found(_search(2.0))
    assert calls == [("observe", [1]), ("observe", [])]
    poser._take_found(_search(2.0))
    assert calls[2:] == [("observe", [1]), ("challenge", [1, 1])]  # the search at 9.0 is from before a reset


def test_the_lock_step_search_hands_each_detection_over_its_delay_in_frames_later():
    """Offline, the search runs at once in the caller's process: its k-th detection comes with the delay(k)-th
    `collect` after it, its end with its last (default: all on the next frame), the same every run."""
    from types import SimpleNamespace

    from axispose_core.pose_estimate import Found

    found = [Found([SimpleNamespace(obj_id=i)], [SimpleNamespace(ok=True)]) for i in (1, 5)]
    estimator = SimpleNamespace(find_each=lambda *args, **kwargs: iter(found))
    finder = LockStepFinder(estimator, delay=lambda boxes: boxes)
    finder.offer(_search(1.0))
    assert not finder.idle() and finder.wait_ready(0.0)
    assert [f for _, f in finder.collect()] == [found[0]]
    assert [f for _, f in finder.collect()] == [found[1], None] and finder.idle()
    finder = LockStepFinder(estimator)
    finder.offer(_search(2.0))
    assert [(s.stamp, f) for s, f in finder.collect()] == [(2.0, found[0]), (2.0, found[1]), (2.0, None)] and finder.idle()


def test_a_tracked_pose_is_boxed_by_its_models_projection_not_the_crop_it_trails():
    """A track's own box is the one it was last cropped from; the poser gives each tracked pose the box of its
    model projected at the pose (a refused pose, or a checkpoint without meshes, keeps the track's)."""
    from types import SimpleNamespace

    from axispose_core.pose_estimate import PoseEstimate
    from axispose_core.tracking.poser import FramePoser

    K = np.array([[600.0, 0, 320], [0, 600, 240], [0, 0, 1]])
    cube = np.array([[x, y, z] for x in (-0.05, 0.05) for y in (-0.05, 0.05) for z in (-0.05, 0.05)])

    def tracked(ok: bool, track_id: int) -> SimpleNamespace:
        t = np.array([0.1, -0.05, 1.0])
        pose = PoseEstimate(1, np.eye(3), t, ok, "", np.zeros((1, 1, 3)), np.eye(3), (0.0, 0.0), 1.0)
        return SimpleNamespace(measurement=pose, R=np.eye(3), t=t, covariance=None, score=0.9, box=(0.0, 0.0, 5.0, 5.0), track_id=track_id)

    tracks = [tracked(True, 1), tracked(False, 2)]
    for meshes, first in (({1: (cube, None)}, (320 + 600 * 0.05 / 1.05, 240 - 600 * 0.1 / 0.95)), (None, (0.0, 0.0))):
        poser = FramePoser(SimpleNamespace(meshes=meshes), {1: "ape"}, lambda key, n: None)
        poser.tracker.step = lambda *args: tracks
        posed = poser._tracked(0.0, K, None, None, None, 0.3)
        assert posed.boxes[0][:2] == pytest.approx(first) and posed.boxes[1] == (0.0, 0.0, 5.0, 5.0)
    assert posed.track_ids == [1, 2]
    # a body's cloud of points: the box of all of them (the poser projects their hull's only)
    cloud = np.random.default_rng(3).normal(scale=0.03, size=(500, 3))
    poser = FramePoser(SimpleNamespace(meshes={1: (cloud, None)}), {1: "ape"}, lambda key, n: None)
    poser.tracker.step = lambda *args: tracks
    uv = (cloud + tracks[0].t) @ K.T
    uv = uv[:, :2] / uv[:, 2:]
    x0, y0 = uv.min(axis=0)
    x1, y1 = uv.max(axis=0)
    assert poser._tracked(0.0, K, None, None, None, 0.3).boxes[0] == pytest.approx((x0, y0, x1 - x0, y1 - y0))
