"""Tracking: the SE(3) filter against known motion and noise, and the tracker's bookkeeping on scripted frames."""

from __future__ import annotations

from dataclasses import dataclass
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from axispose_core.data.bop import GTInstance
from axispose_core.tracking.config import TrackingConfig
from axispose_core.tracking.filter import FilterConfig, PoseFilter
from axispose_core.tracking.follow import follow_together
from axispose_core.tracking.motion import camera_motion, scene_motion
from axispose_core.tracking.tracker import Tracker
from axispose_core.tracking.tracks import Crop, Sighting

K = np.array([[572.4, 0.0, 325.3], [0.0, 573.6, 242.0], [0.0, 0.0, 1.0]])
SIGMA_T, SIGMA_R = 0.01, np.deg2rad(5.0)
COV = np.diag([SIGMA_T**2] * 3 + [SIGMA_R**2] * 3)


def _rot_deg(A: np.ndarray, B: np.ndarray) -> float:
    return float(np.rad2deg(np.linalg.norm(Rotation.from_matrix(A @ B.T).as_rotvec())))


def _noisy(rng: np.random.Generator, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return Rotation.from_rotvec(rng.normal(0, SIGMA_R, 3)).as_matrix() @ R, t + rng.normal(0, SIGMA_T, 3)


def test_a_static_pose_is_averaged_down():
    rng = np.random.default_rng(0)
    R0, t0 = Rotation.from_euler("xyz", [20, -30, 45], degrees=True).as_matrix(), np.array([0.05, -0.02, 0.8])
    f = PoseFilter.start(FilterConfig(accel_std=0.01, angular_accel_std=0.01), *_noisy(rng, R0, t0), COV)
    raw_t, raw_r = [], []
    for _ in range(60):
        f.predict(1 / 30)
        R, t = _noisy(rng, R0, t0)
        raw_t.append(np.linalg.norm(t - t0))
        raw_r.append(_rot_deg(R, R0))
        assert f.update(R, t, COV)[0]
    assert np.linalg.norm(f.t - t0) < 0.4 * np.median(raw_t)
    assert _rot_deg(f.R, R0) < 0.4 * np.median(raw_r)
    assert np.sqrt(f.covariance[2, 2]) < 0.5 * SIGMA_T  # it knows it has averaged


def test_constant_motion_is_followed_without_lag():
    """A pose moving at constant linear and angular velocity: after a while the filter sits on it, and its
    velocities are the true ones."""
    rng = np.random.default_rng(1)
    v, w, dt = np.array([0.1, 0.0, -0.05]), np.array([0.0, 0.5, 0.2]), 1 / 15
    R0, t0 = np.eye(3), np.array([0.0, 0.0, 1.0])

    def truth(k: int) -> tuple[np.ndarray, np.ndarray]:
        return Rotation.from_rotvec(w * dt * k).as_matrix() @ R0, t0 + v * dt * k

    f = PoseFilter.start(FilterConfig(accel_std=0.05, angular_accel_std=0.3), *truth(0), COV)
    for k in range(1, 90):
        f.predict(dt)
        assert f.update(*_noisy(rng, *truth(k)), COV)[0]
    R, t = truth(89)
    assert np.linalg.norm(f.t - t) < 2 * SIGMA_T
    assert _rot_deg(f.R, R) < 2 * np.rad2deg(SIGMA_R)
    # velocities within 3 sigma of the filter's own uncertainty, which is well below the speeds
    sd_v, sd_w = np.sqrt(np.diag(f.P)[3:6]), np.sqrt(np.diag(f.P)[9:12])
    assert np.all(np.abs(f.v - v) < 3 * sd_v) and sd_v.max() < 0.5 * np.abs(v).max()
    assert np.all(np.abs(f.w - w) < 3 * sd_w) and sd_w.max() < 0.5 * np.abs(w).max()


def test_process_noise_is_split_across_and_along_the_line_of_sight():
    """Over dt the position's process noise is dt³/3 times the acceleration density: `accel_std`² across the ray
    through the object, `depth_accel_std`² along it."""
    t0, dt = np.array([0.3, -0.2, 0.9]), 0.1
    f = PoseFilter.start(FilterConfig(accel_std=0.6, depth_accel_std=0.05), np.eye(3), t0, np.zeros((6, 6)))
    f.P[:] = 0.0
    f.predict(dt)
    ray = t0 / np.linalg.norm(t0)
    across = np.cross(ray, [0.0, 0.0, 1.0])
    across /= np.linalg.norm(across)
    P = f.P[0:3, 0:3]
    assert ray @ P @ ray == pytest.approx(dt**3 / 3 * 0.05**2)
    assert across @ P @ across == pytest.approx(dt**3 / 3 * 0.6**2)
    assert across @ P @ ray == pytest.approx(0.0, abs=1e-15)


def test_a_camera_that_turns_is_followed_sideways_while_depth_is_averaged():
    """The object steps sideways at random (a shaking camera) at a constant depth; the measured depth is noisier
    than the sideways position. With depth's own process noise the filter follows the steps and averages depth
    down; isotropic noise as strong as the steps need would follow the depth noise as well."""
    rng = np.random.default_rng(3)
    cov = np.diag([0.003**2, 0.003**2, 0.03**2] + [SIGMA_R**2] * 3)
    errors = {}
    configs = {"split": FilterConfig(accel_std=0.5, depth_accel_std=0.02), "isotropic": FilterConfig(accel_std=0.5, depth_accel_std=None)}
    for name, cfg in configs.items():
        t = np.array([0.0, 0.0, 1.0])
        f = PoseFilter.start(cfg, np.eye(3), t, cov)
        lateral, depth = [], []
        for k in range(120):
            t = t + np.array([*rng.normal(0, 0.005, 2), 0.0])
            f.predict(1 / 15)
            f.update(np.eye(3), t + rng.normal(0, np.sqrt(np.diag(cov)[:3])), cov)
            if k >= 20:
                lateral.append(np.linalg.norm(f.t[:2] - t[:2]))
                depth.append(abs(f.t[2] - t[2]))
        errors[name] = (np.median(lateral), np.median(depth))
    assert errors["split"][0] < 0.006  # the sideways steps are followed
    assert errors["split"][1] < 0.5 * errors["isotropic"][1]


def test_a_flip_is_refused_at_the_gate():
    rng = np.random.default_rng(2)
    R0, t0 = np.eye(3), np.array([0.0, 0.0, 1.0])
    f = PoseFilter.start(FilterConfig(), R0, t0, COV)
    for _ in range(10):
        f.predict(1 / 15)
        f.update(*_noisy(rng, R0, t0), COV)
    before = (f.R.copy(), f.t.copy(), f.P.copy())
    flipped = Rotation.from_euler("z", 180, degrees=True).as_matrix() @ R0
    accepted, d2 = f.update(flipped, t0, COV)
    assert not accepted and d2 > FilterConfig().gate_d2
    assert np.array_equal(f.R, before[0]) and np.array_equal(f.t, before[1]) and np.array_equal(f.P, before[2])


def test_the_state_covariance_stays_symmetric_positive():
    rng = np.random.default_rng(3)
    f = PoseFilter.start(FilterConfig(), np.eye(3), np.array([0, 0, 1.0]), COV)
    for _ in range(200):
        f.predict(rng.uniform(0.01, 0.3))
        f.update(*_noisy(rng, np.eye(3), np.array([0, 0, 1.0])), COV)
    assert np.allclose(f.P, f.P.T)
    assert np.linalg.eigvalsh(f.P).min() > 0


@dataclass
class Pose:
    ok: bool
    R: np.ndarray
    t: np.ndarray
    covariance: np.ndarray | None


@dataclass
class Det:
    obj_id: int
    score: float
    box: tuple[float, float, float, float]


class Scene:
    """Scripted frames: objects at known poses, a localiser that returns their boxes, an estimator whose poses
    are the truth plus noise (or a flip, or nothing), and a log of what each frame asked for."""

    def __init__(self, poses: dict[int, tuple[np.ndarray, np.ndarray]], seed: int = 0) -> None:
        self.poses, self.rng = poses, np.random.default_rng(seed)
        self.detect_calls, self.crops = 0, []
        self.flip: set[int] = set()
        self.refuse: set[int] = set()
        self.hidden: set[int] = set()

    def box(self, obj_id: int) -> tuple[float, float, float, float]:
        p = K @ self.poses[obj_id][1]
        cx, cy, side = p[0] / p[2], p[1] / p[2], 60.0 / self.poses[obj_id][1][2]
        return (cx - side / 2, cy - side / 2, side, side)

    def detect(self) -> list[Det]:
        self.detect_calls += 1
        return [Det(o, 0.9, self.box(o)) for o in self.poses if o not in self.hidden]

    def estimate(self, crops: list[Crop]) -> list[Pose]:
        self.crops.append(crops)
        out = []
        for c in crops:
            R, t = _noisy(self.rng, *self.poses[c.obj_id])
            if c.obj_id in self.flip:
                R = Rotation.from_euler("z", 180, degrees=True).as_matrix() @ R
            out.append(Pose(c.obj_id not in self.refuse, R, t, COV))
        return out


def _run(tracker: Tracker, scene: Scene, stamps) -> list:
    return [tracker.step(s, K, scene.detect, scene.estimate) for s in stamps]


def _scene() -> Scene:
    tilted = Rotation.from_euler("x", 40, degrees=True).as_matrix()
    return Scene({1: (np.eye(3), np.array([0.05, 0.0, 0.9])), 5: (tilted, np.array([-0.1, 0.05, 1.1]))})


def test_a_sighting_brings_its_pose_and_is_not_posed_again():
    """Detections their caller has posed (a verifier's `Estimator.find`) are their crops' measurements: the
    estimator poses only the tracks no detection refreshed, once."""
    scene, tracker = _scene(), Tracker(TrackingConfig(redetect_period=2))
    given: dict[int, Pose] = {}

    def sightings() -> list[Sighting]:
        dets = scene.detect()
        given.clear()
        given.update({d.obj_id: Pose(True, *_noisy(scene.rng, *scene.poses[d.obj_id]), COV) for d in dets})
        return [Sighting(d.obj_id, d.score, d.box, given[d.obj_id]) for d in dets]

    first = tracker.step(0.0, K, sightings, scene.estimate)
    assert scene.crops == [] and len(first) == 2
    assert all(p.measurement is given[p.obj_id] for p in first)
    tracker.step(1 / 15, K, sightings, scene.estimate)  # no localiser: the tracks' crops are posed
    assert [sorted(c.obj_id for c in crops) for crops in scene.crops] == [[1, 5]]
    scene.hidden = {5}
    third = tracker.step(2 / 15, K, sightings, scene.estimate)  # the localiser finds object 1 only
    assert [c.obj_id for c in scene.crops[-1]] == [5] and scene.crops[-1][0].track is not None
    assert {p.obj_id: p.measurement is given.get(p.obj_id) for p in third} == {1: True, 5: False}
    assert {p.track_id for p in first} == {p.track_id for p in third}


def test_tracks_keep_their_ids_and_the_localiser_runs_every_period():
    scene, tracker = _scene(), Tracker(TrackingConfig(redetect_period=5))
    frames = _run(tracker, scene, np.arange(20) / 15)
    ids = [{(p.obj_id, p.track_id) for p in poses} for poses in frames]
    assert all(i == ids[0] for i in ids) and len(ids[0]) == 2
    assert scene.detect_calls == 4  # frames 0, 5, 10, 15
    tracked = scene.crops[1]
    assert all(c.track is not None for c in tracked)
    for c in tracked:  # a tracked object's crop is where it is
        x, y, w, h = scene.box(c.obj_id)
        assert np.hypot(c.box[0] + c.box[2] / 2 - (x + w / 2), c.box[1] + c.box[3] / 2 - (y + h / 2)) < 5
        assert abs(c.box[2] / w - 1) < 0.1


def test_tracks_take_turns_between_localiser_runs_and_every_track_is_published_every_frame():
    """measure_every 3: between localiser runs each frame poses about a third of the tracks, the others publish
    their filters' predictions (flagged as such, with their latest measurement); every track stays on every frame."""
    poses = {o: (np.eye(3), np.array([0.1 * (i - 3), 0.0, 1.0 + 0.05 * i])) for i, o in enumerate((1, 5, 6, 8, 9, 10))}
    scene, tracker = Scene(poses), Tracker(TrackingConfig(redetect_period=6, measure_every=3))
    frames = _run(tracker, scene, np.arange(12) / 15)
    assert all(len(f) == 6 and len({p.track_id for p in f}) == 6 for f in frames)
    assert [len(c) for c in scene.crops] == [6, 2, 2, 2, 2, 2, 6, 2, 2, 2, 2, 2]  # frames 0 and 6: the localiser's
    for f, crops in zip(frames, scene.crops, strict=True):
        posed = {c.track for c in crops}
        assert sum(p.measured for p in f) == len(crops)
        assert None in posed or all(p.measured == (p.track_id in posed) for p in f)  # None: frame 0's new tracks
        for p in f:
            if not p.measured:  # the prediction of a static object stays on it
                assert p.measurement is not None and not p.accepted
                R, t = scene.poses[p.obj_id]
                assert np.linalg.norm(p.t - t) < 3 * SIGMA_T * np.sqrt(3) and _rot_deg(p.R, R) < np.rad2deg(3 * SIGMA_R * np.sqrt(3))
    turns = [{c.track for c in crops} for crops in scene.crops[1:4]]
    assert set().union(*turns) == {p.track_id for p in frames[0]}  # three frames: every track once
    # a track the estimator refused is posed again on the next frame, whatever its turn
    scene.refuse.add(1)
    _run(tracker, scene, [12 / 15])
    scene.refuse.clear()
    _run(tracker, scene, [13 / 15])
    assert 1 in {c.obj_id for c in scene.crops[-1]}


def test_a_flip_is_gated_then_followed_if_it_persists():
    scene, tracker = _scene(), Tracker(TrackingConfig(reinit_after=3))
    _run(tracker, scene, np.arange(10) / 15)
    R_before = next(tr.filter.R for tr in tracker.tracks if tr.obj_id == 5)
    scene.flip.add(5)
    frames = _run(tracker, scene, (10 + np.arange(2)) / 15)
    assert [next(p.accepted for p in f if p.obj_id == 5) for f in frames] == [False, False]
    assert _rot_deg(next(p.R for p in frames[-1] if p.obj_id == 5), R_before) < 10  # not followed
    frames = _run(tracker, scene, [12 / 15])
    assert next(p.accepted for p in frames[0] if p.obj_id == 5)
    assert tracker.counts["measurements_gated"] == 3 and tracker.counts["tracks_restarted"] == 1


def test_resets_on_stamps_backwards_camera_change_and_timeout():
    scene, tracker = _scene(), Tracker(TrackingConfig(track_timeout=0.5))
    first = _run(tracker, scene, [0.0, 0.1])[-1]
    old_ids = {p.track_id for p in first}
    poses = tracker.step(0.05, K, scene.detect, scene.estimate)  # a looped bag
    assert tracker.counts["reset_stamps_backwards"] == 1 and not old_ids & {p.track_id for p in poses}
    K2 = K.copy()
    K2[0, 0] *= 1.1
    tracker.step(0.2, K2, scene.detect, scene.estimate)
    assert tracker.counts["reset_camera_changed"] == 1
    scene.refuse = {1, 5}
    tracker.step(0.3, K2, scene.detect, scene.estimate)  # no poses: the tracks miss but live on
    assert len(tracker.tracks) == 2
    scene.refuse = set()
    scene.hidden = {1, 5}
    tracker.step(0.3 + 0.6, K2, scene.detect, scene.estimate)  # past the timeout since the last accepted pose
    assert tracker.counts["ended_timeout"] == 2


def test_an_object_that_leaves_ends_its_track_and_a_return_starts_a_new_one():
    scene, tracker = _scene(), Tracker(TrackingConfig(max_misses=3, track_timeout=10.0))
    _run(tracker, scene, np.arange(3) / 15)
    id1 = next(tr.id for tr in tracker.tracks if tr.obj_id == 1)
    scene.refuse, scene.hidden = {1}, {1}
    _run(tracker, scene, (3 + np.arange(3)) / 15)
    assert all(tr.obj_id != 1 for tr in tracker.tracks) and tracker.counts["ended_misses"] == 1
    scene.refuse, scene.hidden = set(), set()
    poses = _run(tracker, scene, [6 / 15])[0]
    assert next(p.track_id for p in poses if p.obj_id == 1) != id1


@pytest.mark.parametrize("period", [1, 3])
def test_a_redetection_refreshes_a_track_instead_of_duplicating_it(period):
    scene, tracker = _scene(), Tracker(TrackingConfig(redetect_period=period))
    _run(tracker, scene, np.arange(7) / 15)
    assert len(tracker.tracks) == 2 and tracker.counts["tracks_started"] == 2


def test_recovery_counts_frames_from_an_objects_return_to_its_first_right_pose():
    """Object 1 is hidden on frames 10-19 and first posed right 3 frames after it is back; object 2 is out of view
    (not annotated) on frames 15-29 and posed right on its return; object 3 never leaves. Drift compares the
    first and last windows."""
    from axispose_core.tracking.stream_scores import Seen, drift, recovery

    rows = [Seen(k, 1, 0.0 if 10 <= k < 20 else 1.0, float(k < 20), float(k < 10 or k >= 23)) for k in range(40)]
    rows += [Seen(k, 2, 1.0, 0.0, 1.0) for k in range(40) if not 15 <= k < 30]
    rows += [Seen(k, 3, 1.0, 1.0, 1.0) for k in range(40)]
    out = recovery(rows)
    assert out["returns"] == 2 and out["recovery_median"] == pytest.approx(1.5) and out["recovered_in_5"] == 1.0
    never = [r if r.obj_id != 1 or r.frame < 20 else Seen(r.frame, 1, 1.0, 0.0, 0.0) for r in rows]
    assert sorted(recovery(never, away=5).values()) == sorted([2, 10.0, 0.5])  # 20 frames left: waits 0 and 20
    scores = drift(rows, window=10)
    assert scores["add_first"] == pytest.approx(20 / 30) and scores["add_last"] == pytest.approx(10 / 30)


def test_visibility_counts_the_part_of_an_object_outside_the_image_as_unseen():
    """A cube whose centre projects onto the right border is half seen; one inside is seen as its mask says; one
    just past the border or behind the camera not at all."""
    from axispose_core.tracking.stream_scores import visibility

    grid = np.stack(np.meshgrid(*[np.linspace(-0.05, 0.05, 11)] * 3), -1).reshape(-1, 3)
    K, size, eye = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]]), (480, 640), np.eye(3)
    at = lambda u: np.array([(u - 320) / 500, 0.0, 1.0])  # noqa: E731 - the centre projected to column u at 1 m
    assert visibility(0.8, K, eye, at(320), grid, size) == pytest.approx(0.8)
    assert visibility(1.0, K, eye, at(640), grid, size) == pytest.approx(0.5, abs=0.05)
    assert visibility(1.0, K, eye, at(700), grid, size) == 0.0
    assert visibility(1.0, K, eye, np.array([0.0, 0.0, -1.0]), grid, size) == 0.0


def test_jitter_measures_the_error_change_not_the_motion():
    from axispose_core.tracking.jitter import PosePair, jitter

    rng = np.random.default_rng(4)
    pairs, steady = [], []
    for k in range(20):  # the object moves a lot; the prediction is off by a constant, then by a known jump
        R_gt = Rotation.from_rotvec([0.0, 0.1 * k, 0.0]).as_matrix()
        t_gt = np.array([0.02 * k, 0.0, 1.0])
        bias_t = np.array([0.01, 0.0, 0.0]) if k % 2 == 0 else np.array([0.01, 0.003, 0.0])  # 3 mm jumps
        bias_R = Rotation.from_rotvec([0.0, 0.0, np.radians(2.0 if k % 2 else 0.0)]).as_matrix()
        pairs.append(PosePair(k, 1, bias_R @ R_gt, t_gt + bias_t, R_gt, t_gt))
        steady.append(PosePair(k, 2, Rotation.from_rotvec(rng.normal(0, 0.3, 3)).as_matrix() @ R_gt, t_gt + 0.05, R_gt, t_gt))
    out = jitter(pairs)
    assert out["n"] == 19
    assert out["jitter_mm"] == pytest.approx(3.0) and out["jitter_deg"] == pytest.approx(2.0)
    constant = [PosePair(p.frame, 2, Rotation.from_rotvec([0.3, 0, 0]).as_matrix() @ p.R_gt, p.t_pred, p.R_gt, p.t_gt) for p in steady]
    assert jitter(constant)["jitter_mm"] == pytest.approx(0.0, abs=1e-9)
    assert jitter(constant)["jitter_deg"] == pytest.approx(0.0, abs=1e-4)
    gap = [p for p in pairs if p.frame != 5]  # a missing frame breaks two pairs
    assert jitter(gap)["n"] == 17


def test_jitter_of_a_symmetric_object_ignores_a_flip_between_equivalent_poses():
    from axispose_core.tracking.jitter import PosePair, jitter

    flip = Rotation.from_euler("z", 180, degrees=True).as_matrix()
    syms = {3: [(np.eye(3), np.zeros(3)), (flip, np.zeros(3))]}
    R_gt, t_gt = Rotation.from_euler("x", 30, degrees=True).as_matrix(), np.array([0.0, 0.0, 0.8])
    pairs = [PosePair(k, 3, R_gt @ (flip if k % 2 else np.eye(3)), t_gt, R_gt, t_gt) for k in range(6)]
    assert jitter(pairs, syms)["jitter_deg"] == pytest.approx(0.0, abs=1e-4)
    assert jitter(pairs)["jitter_deg"] == pytest.approx(180.0, abs=1e-4)


def test_half_turn_symmetries_of_the_lmo_models():
    from axispose_core.data.meshes import load_ply
    from axispose_core.lmo import LMO_DIAMETERS, SHARED_LMO
    from axispose_core.metrics import half_turn_symmetries

    models = SHARED_LMO / "models_eval"
    if not models.is_dir():
        pytest.skip("needs ../shared/data/lmo")
    found = {}
    for obj_id, diameter in LMO_DIAMETERS.items():
        syms = half_turn_symmetries(load_ply(models / f"obj_{obj_id:06d}.ply").vertices, diameter)
        found[obj_id] = [float(np.degrees(np.linalg.norm(Rotation.from_matrix(R).as_rotvec()))) for R, _ in syms]
    assert found[10] == pytest.approx([0.0, 180.0]) and found[11] == pytest.approx([0.0, 180.0])  # eggbox, glue: about z
    assert all(v == [0.0] for k, v in found.items() if k not in (10, 11))


def test_a_track_the_localiser_stops_finding_ends():
    """A false detection starts a track; when later localiser runs do not find it again, it ends."""
    scene, tracker = _scene(), Tracker(TrackingConfig(redetect_period=1, max_unseen=2))
    real = scene.detect
    scene.poses[9], scene.hidden = (np.eye(3), np.array([0.3, -0.2, 0.9])), {9}  # posed if cropped, never detected...
    scene.detect = lambda: [*real(), Det(9, 0.5, scene.box(9))] if scene.detect_calls == 0 else real()  # ...but once
    _run(tracker, scene, [0.0])
    assert len(tracker.tracks) == 3
    _run(tracker, scene, [0.1, 0.2, 0.3])
    assert len(tracker.tracks) == 2 and tracker.counts["ended_unseen"] == 1


def test_a_track_the_localiser_did_not_find_ends_without_another_localiser_run():
    """Ending a track the localiser just failed to find does not run it again on the next frame (a track that
    ended for a refused pose does): false detections starting and ending tracks would run it on every frame."""
    scene, tracker = _scene(), Tracker(TrackingConfig(redetect_period=100, max_unseen=1))
    _run(tracker, scene, [0.0])
    scene.refuse = {1}
    _run(tracker, scene, [0.1])  # object 1's pose refused: the localiser runs on the next frame...
    scene.refuse, scene.hidden = set(), {5}
    _run(tracker, scene, [0.2])  # ...and does not find object 5, whose track ends
    assert scene.detect_calls == 2 and tracker.counts["ended_unseen"] == 1 and [tr.obj_id for tr in tracker.tracks] == [1]
    _run(tracker, scene, [0.3, 0.4])
    assert scene.detect_calls == 2
    scene.refuse = {1}
    _run(tracker, scene, [0.5, 0.6, 0.7])  # three refusals end object 1's track (max_misses): then it is looked for
    assert tracker.counts["ended_misses"] == 1 and scene.detect_calls >= 4
    scene.refuse = set()
    _run(tracker, scene, [0.8])
    assert [tr.obj_id for tr in tracker.tracks] == [1]


def test_a_fast_object_keeps_its_track_when_its_box_moved_far():
    scene, tracker = _scene(), Tracker(TrackingConfig(redetect_period=1))
    _run(tracker, scene, [0.0, 0.1])
    ids = {tr.obj_id: tr.id for tr in tracker.tracks}
    R, t = scene.poses[1]
    scene.poses[1] = (R, t + np.array([0.04, 0.0, 0.0]))  # 25 px at once: no overlap with the predicted box
    poses = _run(tracker, scene, [0.2])[0]
    assert {p.obj_id: p.track_id for p in poses} == ids and tracker.counts["tracks_started"] == 2


def test_a_track_run_off_behind_the_camera_ends():
    scene, tracker = _scene(), Tracker(TrackingConfig(redetect_period=100, track_timeout=100.0))
    _run(tracker, scene, [0.0])
    tr = next(t for t in tracker.tracks if t.obj_id == 1)
    tr.filter.v = np.array([0.0, 0.0, -20.0])  # 20 m/s towards the camera: behind it within a frame
    scene.refuse = {1}
    _run(tracker, scene, [0.1])
    assert all(t.obj_id != 1 for t in tracker.tracks) and tracker.counts["ended_behind"] == 1


def test_the_cameras_motion_between_frames_is_the_one_most_objects_agree_on():
    """Five objects seen from a camera that turns 20° about a point 0.8 m ahead: the motion comes back exactly, with
    every object on it; the one object moved 5 cm between the frames is the one off it, by 5 cm."""
    world = [(Rotation.random(random_state=k).as_matrix(), np.array([0.1 * k - 0.2, 0.05 * k, 0.8])) for k in range(5)]
    turn = Rotation.from_euler("y", 20, degrees=True).as_matrix()
    pivot = np.array([0.0, 0.0, 0.8])
    before = [GTInstance(k + 1, R, t) for k, (R, t) in enumerate(world)]
    after = [GTInstance(k + 1, turn @ R, turn @ (t - pivot) + pivot) for k, (R, t) in enumerate(world)]
    after[2] = GTInstance(3, after[2].R, after[2].t + np.array([0.05, 0.0, 0.0]))
    motion, off = camera_motion(before, after, tol=0.02)
    np.testing.assert_allclose(motion[:3, :3], turn, atol=1e-9)
    np.testing.assert_allclose(motion[:3, 3], pivot - turn @ pivot, atol=1e-9)
    assert off[2] == pytest.approx(0.05) and max(off[:2] + off[3:]) < 1e-9
    assert camera_motion(before, [], tol=0.02) is None


def test_a_scene_counts_each_objects_moves_against_the_rest():
    """Three still frames of four objects, the camera turning; object 3 moved 5 cm between the second and third: one
    move of object 3, none of the others, one step of the six moved."""
    world = [(Rotation.random(random_state=k).as_matrix(), np.array([0.1 * k - 0.2, 0.05 * k, 0.8])) for k in range(4)]
    pivot = np.array([0.0, 0.0, 0.8])
    frames = {}
    for i in range(3):
        turn = Rotation.from_euler("y", 10 * i, degrees=True).as_matrix()
        shift = [np.array([0.05, 0.0, 0.0]) if i == 2 and k == 2 else np.zeros(3) for k in range(4)]
        frames[i] = [GTInstance(k + 1, turn @ R, turn @ (t + shift[k] - pivot) + pivot) for k, (R, t) in enumerate(world)]
    K = np.array([[572.0, 0.0, 320.0], [0.0, 572.0, 240.0], [0.0, 0.0, 1.0]])
    scene = SimpleNamespace(gt=frames, cameras={i: K for i in frames}, root="three frames")
    m = scene_motion(scene, tol=0.02)
    assert m["moves"] == {1: 0, 2: 0, 3: 1, 4: 0} and m["objects_moved_share"] == pytest.approx(1 / 8)


@dataclass
class Followed(Pose):
    contour_agreement: float = 0.9


def test_followed_tracks_are_measured_by_their_contours_and_the_agm_poses_only_the_lost():
    """With a follower every track's pose on every frame is its contour's, the localiser runs every period and poses
    nothing it already follows (their contours agree: nothing to check); a contour that held for a period and loses
    its object (low agreement) runs the localiser on the same frame, and the AGM's pose of its detection starts its
    track again; a restarted track whose contour does not hold ends at once, and nothing is posed for it until the
    localiser's next period."""
    scene = _scene()
    tracker = Tracker(TrackingConfig(redetect_period=4))
    asked, agreement = [], {1: 0.9, 5: 0.9}

    def follow(last: list, predicted: list) -> list[Followed]:
        asked.append(len(last))
        assert len(predicted) == len(last)
        out = []
        for m in last:
            obj = next(o for o, (_, tg) in scene.poses.items() if np.linalg.norm(tg - m.t) < 0.05)
            R_true, t_true = scene.poses[obj]
            out.append(Followed(True, R_true, t_true + 0.001, COV, agreement[obj]))
        return out

    def step(k: int) -> list:
        return tracker.step(k / 30, K, scene.detect, scene.estimate, follow)

    first = step(0)  # nothing to follow yet: the localiser, and the AGM poses both
    assert len(first) == 2 and asked == [] and len(scene.crops) == 1
    for k in range(1, 4):
        poses = step(k)
        assert len(poses) == 2 and all(p.accepted for p in poses)
    assert asked == [2, 2, 2] and len(scene.crops) == 1  # followed: no AGM
    assert scene.detect_calls == 1 and tracker.counts["followed"] == 6
    poses = step(4)  # the localiser's period: it finds the followed objects again and poses nothing
    assert scene.detect_calls == 2 and len(scene.crops) == 1 and len(poses) == 2
    agreement[5] = 0.3  # object 5's contour, held for 4 frames, is lost: the AGM poses its detection, a new start
    poses = step(5)
    assert scene.detect_calls == 3 and [c.obj_id for c in scene.crops[-1]] == [5] and scene.crops[-1][0].detected
    assert scene.crops[-1][0].box == scene.box(5) and tracker.counts["contour_lost"] == 1
    assert tracker.counts["tracks_reinitialised"] == 1 and {p.obj_id for p in poses} == {1, 5}
    ids = {p.track_id for p in poses}
    posed = len(scene.crops)
    for k in (6, 7):  # the restart does not hold: the track ends, no localiser, no AGM, nothing published for 5
        poses = step(k)
        assert {p.obj_id for p in poses} == {1}
    assert tracker.counts["ended_unfollowable"] == 1 and scene.detect_calls == 3 and len(scene.crops) == posed
    assert {p.track_id for p in poses} < ids  # object 1 kept its track throughout
    poses = step(8)  # the localiser's period finds object 5 again: a new track
    assert scene.detect_calls == 4 and {p.obj_id for p in poses} == {1, 5} and tracker.counts["tracks_started"] == 3


def test_a_lost_track_no_detection_finds_ends_and_a_start_is_judged_by_the_next_contour():
    """A detection's pose starts a track whatever its contour's agreement (the next frame's contour judges it); a
    track whose contour held for a period, is lost, and whose object the localiser does not find ends on that
    frame: it is not posed in its predicted box and publishes nothing."""
    scene = _scene()
    tracker = Tracker(TrackingConfig(redetect_period=3))

    def estimate(crops: list[Crop]) -> list[Followed]:
        return [Followed(p.ok, p.R, p.t, p.covariance, 0.5 if c.obj_id == 5 else 0.9)
                for c, p in zip(crops, scene.estimate(crops), strict=True)]  # fmt: skip

    lost = set()

    def follow(last: list, predicted: list) -> list[Followed]:
        return [Followed(True, m.R, m.t, COV, 0.5 if m.t[0] < 0 and lost else 0.9) for m in last]  # object 5: x -0.1

    poses = tracker.step(0.0, K, scene.detect, estimate, follow)
    assert sorted(p.obj_id for p in poses) == [1, 5] and tracker.counts["tracks_started"] == 2
    for k in range(1, 4):
        poses = tracker.step(k / 30, K, scene.detect, estimate, follow)
    assert sorted(p.obj_id for p in poses) == [1, 5] and scene.detect_calls == 2  # frames 0 and 3
    lost.add(5)
    scene.hidden = {5}  # its contour is lost and the localiser no longer finds it
    posed = len(scene.crops)
    poses = tracker.step(4 / 30, K, scene.detect, estimate, follow)
    assert [p.obj_id for p in poses] == [1] and scene.detect_calls == 3 and len(scene.crops) == posed
    assert tracker.counts["ended_unfound"] == 1 and [tr.obj_id for tr in tracker.tracks] == [1]


def test_frames_on_which_no_contour_holds_are_posed_as_without_tracking():
    """A bag of stills: no contour holds from one frame to the next, even right after the AGM posed them. Each such
    frame runs the localiser and poses every object again from its box; the tracks go on (re-initialised), and
    every object is published on every frame."""
    scene, tracker = _scene(), Tracker(TrackingConfig(redetect_period=5))

    def follow(last: list, predicted: list) -> list[Followed]:
        return [Followed(True, m.R, m.t + 0.05, COV, 0.4) for m in last]

    for k in range(4):
        poses = tracker.step(k / 7.5, K, scene.detect, scene.estimate, follow)
        assert sorted(p.obj_id for p in poses) == [1, 5]
    assert scene.detect_calls == 4 and [len(c) for c in scene.crops] == [2, 2, 2, 2]
    assert all(c.detected for crops in scene.crops for c in crops)
    assert tracker.counts["tracks_reinitialised"] == 6 and "ended_unfollowable" not in tracker.counts


def test_a_still_objects_pose_is_averaged_over_the_views_a_moving_camera_gives():
    """An object at rest, a camera circling it at a known pose (odometry); each view's pose is off by an error that
    is the view's (it comes back with the view, here a depth error cycling over 10 degrees of turn), which a filter
    cannot tell from motion. Averaged over the last views in the fixed frame (`view_window`), the published pose is nearer
    the truth than the filter's alone; without a camera pose nothing is averaged; once the object moved its old views
    are left out (`view_gate`) and the new ones averaged."""
    R_obj, p_obj = Rotation.from_euler("xyz", [10, 20, 30], degrees=True).as_matrix(), np.array([0.0, 0.0, 0.8])

    def camera(k: int) -> np.ndarray:  # camera to fixed: turning about the object, 1 degree a frame
        turn = Rotation.from_euler("y", k, degrees=True).as_matrix()
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = turn, p_obj - turn @ p_obj
        return T

    def run(window: int, odometry: bool, moved_at: int | None = None) -> tuple[list[float], list[float], Tracker]:
        tracker, errors, after = Tracker(TrackingConfig(redetect_period=1000, view_window=window)), [], []
        view_rng = np.random.default_rng(7)
        for k in range(60):
            T = camera(k)
            p_world = p_obj + (np.array([0.0, 0.3, 0.0]) if moved_at is not None and k >= moved_at else 0.0)
            R_true, t_true = T[:3, :3].T @ R_obj, T[:3, :3].T @ (p_world - T[:3, 3])
            ray = t_true / np.linalg.norm(t_true)
            error = ray * 0.01 * np.sin(2 * np.pi * k / 10) + view_rng.normal(0, 0.001, 3)

            def detect(R_true=R_true, t_true=t_true) -> list[Det]:
                p = K @ t_true
                return [Det(1, 0.9, (p[0] / p[2] - 40, p[1] / p[2] - 40, 80.0, 80.0))]

            def estimate(crops: list[Crop], R_true=R_true, t_true=t_true, error=error) -> list[Pose]:
                cov = np.diag([0.003**2, 0.003**2, 0.01**2] + [np.deg2rad(2) ** 2] * 3)
                return [Pose(True, R_true, t_true + error, cov) for _ in crops]

            poses = tracker.step(k / 30, K, detect, estimate, camera=T if odometry else None)
            if k >= 15 and (moved_at is None or k < moved_at):
                errors.append(float(np.linalg.norm(poses[0].t - t_true)))
            elif moved_at is not None and k >= moved_at + 10:
                after.append(float(np.linalg.norm(poses[0].t - t_true)))
        return errors, after, tracker

    alone, _, _ = run(0, True)
    averaged, _, _ = run(10, True)
    without, _, _ = run(10, False)
    assert np.median(averaged) < 0.6 * np.median(alone)
    assert without == alone
    _, moved, tracker = run(10, True, moved_at=40)
    assert tracker.counts["views_gated"] >= 9 and np.median(moved) < 0.6 * np.median(alone)


def test_views_from_other_directions_pin_the_depth_that_one_view_barely_sees():
    """Each view's position is off along its own line of sight only (its depth), and says so in its covariance
    (loose along the ray, tight across it). Fused by their information the views meet where the rays' lateral
    constraints cross, at the truth, where the views' plain mean keeps their average depth error."""
    p_obj = np.array([0.0, 0.0, 0.8])

    def run(lateral_sd: float) -> float:
        tracker = Tracker(TrackingConfig(redetect_period=1000, view_window=4))
        for k, error in enumerate((0.03, 0.02, 0.03, 0.025)):  # fractions of the depth, along each ray
            turn = Rotation.from_euler("y", 4 * k, degrees=True).as_matrix()
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = turn, p_obj - turn @ p_obj
            t_true = turn.T @ (p_obj - T[:3, 3])
            cov = np.diag([lateral_sd**2, lateral_sd**2, (0.01 * t_true[2]) ** 2] + [np.deg2rad(2) ** 2] * 3)
            box = (*(K @ t_true)[:2] / t_true[2] - 40, 80.0, 80.0)
            measured = Pose(True, np.eye(3), t_true * (1 + error), cov)
            poses = tracker.step(k / 30, K, lambda box=box: [Det(1, 0.9, box)], lambda crops, m=measured: [m] * len(crops), camera=T)
        return float(np.linalg.norm(poses[0].t - t_true))

    assert run(1e-5) < 0.001  # the lines of sight cross within a millimetre
    assert run(1.0) > 0.015  # as good as no lateral information: the mean depth error (2.6 % of 0.8 m) stays


def test_an_object_found_again_brings_its_views_back():
    """Views are the object's, not one track's: a track that ended (its object unposed for `max_misses` frames)
    and the new one that finds the object again fuse the same views, so the new track's first poses already have
    the depth the earlier views pinned; views older than `view_window` frames are forgotten."""
    p_obj = np.array([0.0, 0.0, 0.8])

    def run(window: int, lateral_var: float) -> tuple[tuple[float, float], float, Tracker]:
        """The depth error (m, signed), fused and raw, on the new track's first frame and (fused) on the last: views
        2 % too far before the gap, 2 % too near after."""
        tracker = Tracker(TrackingConfig(redetect_period=1000, view_window=window))
        for k in range(24):
            turn = Rotation.from_euler("y", 2 * k, degrees=True).as_matrix()
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = turn, p_obj - turn @ p_obj
            t_true = turn.T @ (p_obj - T[:3, 3])
            cov = np.diag([lateral_var, lateral_var, (0.01 * t_true[2]) ** 2] + [np.deg2rad(2) ** 2] * 3)
            seen = Pose(k not in (16, 17, 18), turn.T, t_true * (1.02 if k < 16 else 0.98), cov)  # unposed: the track ends
            box = (*(K @ t_true)[:2] / t_true[2] - 40, 80.0, 80.0)
            poses = tracker.step(k / 30, K, lambda box=box: [Det(1, 0.9, box)], lambda crops, m=seen: [m] * len(crops), camera=T)
            if k == 19:
                first = (float(poses[0].t[2] - t_true[2]), float(seen.t[2] - t_true[2]))
        return first, float(poses[0].t[2] - t_true[2]), tracker

    (found_again, raw), _, tracker = run(20, 1e-8)  # each view sees across its line of sight: the views pin the depth
    assert tracker.counts["ended_misses"] == 1 and tracker.counts["tracks_started"] == 2
    assert abs(found_again) < 0.001 < abs(raw)
    # Views as precise across as along (8 mm): the views' mean, pulled by the earlier ones, unless they are beyond the
    # window (only the new ones, all too near).
    assert run(20, 0.008**2)[1] > 0 > -0.01 > run(5, 0.008**2)[1]


def test_an_object_back_in_view_is_followed_from_where_its_views_put_it():
    """With views (the camera's pose) an object no track holds is looked for where its views put it: a contour that
    holds there starts its track (`tracks_recalled`) before the localiser's period, and the AGM poses nothing; where
    it is not found it is looked for there again only after a localiser's period."""
    scene = _scene()
    tracker = Tracker(TrackingConfig(redetect_period=10, view_window=30))
    asked: list[list[int]] = []

    def follow(last: list, predicted: list) -> list[Followed]:
        objs = [min(scene.poses, key=lambda o: np.linalg.norm(scene.poses[o][1] - t)) for _, t, _ in predicted]
        asked.append(objs)
        return [Followed(True, *scene.poses[o], COV, 0.3 if o in scene.hidden else 0.9) for o in objs]

    def step(k: int) -> list:
        return tracker.step(k / 30, K, scene.detect, scene.estimate, follow, camera=np.eye(4))

    for k in range(3):
        assert {p.obj_id for p in step(k)} == {1, 5}
    scene.hidden = {5}  # its contour loses it (held 2 frames, less than a period: the track ends)
    assert {p.obj_id for p in step(3)} == {1} and tracker.counts["ended_unfollowable"] == 1
    scene.hidden = set()
    posed = len(scene.crops)
    calls = len(asked)
    poses = step(4)  # back: followed from its views, found, no localiser, no AGM; with the track, in one batch
    assert asked[calls:] == [[1, 5]] and {p.obj_id for p in poses} == {1, 5} and tracker.counts["tracks_recalled"] == 1
    assert scene.detect_calls == 1 and len(scene.crops) == posed
    np.testing.assert_allclose(next(p.t for p in poses if p.obj_id == 5), scene.poses[5][1], atol=0.01)
    scene.hidden = {5}
    step(5)  # lost again: ends
    tries = [k for k in range(6, 10) if 5 in (step(k), asked[-1])[1]]
    assert tries == [6] and tracker.counts["tracks_recalled"] == 1  # not found at 6: not looked for there until 16


def test_an_object_its_contour_cannot_tell_yet_is_looked_for_again_next_frame():
    """A recall whose contour says nothing (too few of its lines in view: an object coming in at the border) is no
    evidence that the object is not there: it is looked for again on the next frame, not after a localiser's period
    as where its contour disagrees."""
    scene = _scene()
    tracker = Tracker(TrackingConfig(redetect_period=10, view_window=30))
    asked: list[int] = []
    verdict = {5: 0.9}

    def follow(last: list, predicted: list) -> list[Followed]:
        out = []
        for _, t, _ in predicted:
            o = min(scene.poses, key=lambda o: np.linalg.norm(scene.poses[o][1] - t))
            asked.append(o)
            seen = np.isfinite(verdict.get(o, 0.9))
            out.append(Followed(seen, *scene.poses[o], COV, verdict.get(o, 0.9)))
        return out

    def step(k: int) -> list:
        return tracker.step(k / 30, K, scene.detect, scene.estimate, follow, camera=np.eye(4))

    for k in range(3):
        step(k)
    verdict[5] = 0.3
    step(3)  # its contour lost: the track ends
    verdict[5] = float("nan")  # at the border: nothing to tell
    asked.clear()
    for k in range(4, 7):
        step(k)
    assert asked.count(5) == 3  # looked for on every frame
    verdict[5], scene.hidden = 0.3, {5}  # seen, and not there (nor does the localiser find it)
    step(7)
    asked.clear()
    for k in range(8, 12):
        step(k)
    assert asked.count(5) == 0  # not before the period


def test_poses_found_elsewhere_join_the_views_and_the_objects_are_followed_from_there():
    """The localiser and the AGM elsewhere (a process of their own): their poses of an earlier frame, at that frame's camera
    pose (`observe`), join the objects' views, and `step` without a localiser follows the objects from there on a
    frame the camera has since moved: each starts a track (`tracks_recalled`), nothing is detected or posed on this
    thread. A track whose contour is lost ends (nothing here can pose it again); observed again, its object is looked
    for at once. Nothing joins without views or a finite camera pose."""
    scene = _scene()
    tracker = Tracker(TrackingConfig(redetect_period=10, view_window=30))
    moved = np.eye(4)
    moved[:3, 3] = [0.02, 0.0, 0.0]  # the camera 2 cm to the right since the searched frame (at the identity)
    truth = {o: (R, t - moved[:3, 3]) for o, (R, t) in scene.poses.items()}

    def follow(last: list, predicted: list) -> list[Followed]:
        # the contour's basin: it finds an object from within a millimetre, unless the object is hidden
        out = []
        for _, t, _ in predicted:
            o = min(truth, key=lambda o: np.linalg.norm(truth[o][1] - t))
            found = np.linalg.norm(truth[o][1] - t) < 1e-3 and o not in scene.hidden
            out.append(Followed(True, *truth[o], COV, 0.9 if found else 0.3))
        return out

    def found(*objs: int) -> list:
        return [(Det(o, 0.9, scene.box(o)), Pose(True, *scene.poses[o], COV)) for o in objs]

    def step(k: int) -> list:
        return tracker.step(k / 30, K, None, scene.estimate, follow, camera=moved)

    assert tracker.observe(np.eye(4), found(1, 5)) == 2
    poses = step(0)
    assert {p.obj_id for p in poses} == {1, 5} and tracker.counts["tracks_recalled"] == 2
    for p in poses:
        np.testing.assert_allclose(p.t, truth[p.obj_id][1], atol=1e-6)
    scene.hidden = {5}
    assert {p.obj_id for p in step(1)} == {1} and tracker.counts["ended_unfollowable"] == 1
    assert {p.obj_id for p in step(2)} == {1}  # looked for where its views put it: not there
    scene.hidden = set()
    assert {p.obj_id for p in step(3)} == {1}  # not looked for again before a localiser's period...
    tracker.observe(np.eye(4), found(5))
    assert {p.obj_id for p in step(4)} == {1, 5} and tracker.counts["tracks_recalled"] == 3  # ...unless found again
    assert scene.detect_calls == 0 and scene.crops == []
    assert tracker.observe(np.full((4, 4), np.nan), found(1)) == 0
    assert Tracker(TrackingConfig(view_window=0)).observe(np.eye(4), found(1)) == 0


def test_an_object_posed_elsewhere_starts_its_track_once_whatever_its_contour_says():
    """A pose found elsewhere (`observe`) starts its object's track on the next frame even where the contour only
    half agrees (the object partly hidden), as the AGM's pose of a detection would; the contour then ends it, and
    the views alone (no new pose) do not start it again."""
    scene = _scene()
    tracker = Tracker(TrackingConfig(redetect_period=10, view_window=30))

    def follow(last: list, predicted: list) -> list[Followed]:
        objs = [min(scene.poses, key=lambda o: np.linalg.norm(scene.poses[o][1] - t)) for _, t, _ in predicted]
        return [Followed(True, *scene.poses[o], COV, 0.6 if o == 5 else 0.9) for o in objs]

    def step(k: int) -> set[int]:
        return {p.obj_id for p in tracker.step(k / 30, K, None, scene.estimate, follow, camera=np.eye(4))}

    tracker.observe(np.eye(4), [(Det(o, 0.9, scene.box(o)), Pose(True, *scene.poses[o], COV)) for o in (1, 5)])
    assert step(0) == {1, 5} and tracker.counts["recalled_unconfirmed"] == 1
    assert step(1) == {1} and tracker.counts["ended_unfollowable"] == 1
    assert step(2) == step(3) == {1} and tracker.counts["tracks_recalled"] == 2


def test_a_track_on_a_wrong_pose_gives_way_to_a_pose_found_elsewhere_that_agrees_more():
    """A track its contour holds at a wrong pose (flipped 180 degrees, agreement 0.75) is followed beside the pose
    a search found elsewhere for its object (`observe`, then `challenge` with all the search's poses): it goes on
    from that pose, its id kept (`tracks_corrected`), where that pose agrees more (0.9); not where it agrees less,
    nor where the search found two poses of the object (two instances)."""
    scene = _scene()
    flipped = Rotation.from_euler("z", 180, degrees=True).as_matrix()
    truth = scene.poses[1]

    def run(found: list, right: float) -> tuple[Tracker, list]:
        tracker = Tracker(TrackingConfig(redetect_period=10, view_window=30))

        def follow(last: list, predicted: list) -> list[Followed]:
            return [Followed(True, R, t, COV, right if _rot_deg(R, truth[0]) < 1 else 0.75) for R, t, _ in predicted]

        def step(k: int) -> list:
            return tracker.step(k / 30, K, None, scene.estimate, follow, camera=np.eye(4))

        tracker.observe(np.eye(4), [(Det(1, 0.9, scene.box(1)), Pose(True, flipped, truth[1], COV))])
        first = step(0)  # the wrong pose starts the track
        searched = [(Det(1, 0.9, scene.box(1)), Pose(True, *p, COV)) for p in found]
        tracker.observe(np.eye(4), searched)
        tracker.challenge(np.eye(4), searched)  # the search is done
        return tracker, first + step(1) + step(2)

    tracker, poses = run([truth], right=0.9)
    assert tracker.counts["tracks_corrected"] == 1 and len({p.track_id for p in poses}) == 1
    assert _rot_deg(poses[0].R, truth[0]) > 170 and _rot_deg(poses[-1].R, truth[0]) < 1
    for found, right in (([truth], 0.72), ([truth, (flipped, truth[1] + 0.3)], 0.9)):
        tracker, poses = run(found, right)
        assert "tracks_corrected" not in tracker.counts and _rot_deg(poses[-1].R, truth[0]) > 170


@pytest.mark.parametrize("camera", [None, np.eye(4)], ids=["camera frame", "fixed frame"])
def test_a_track_on_a_wrong_pose_is_checked_by_the_agm_when_the_localiser_finds_it(camera):
    """A track its contour holds at a wrong pose (the AGM's first pose flipped 180 degrees, agreement 0.75): the
    localiser's next run finds it, the AGM poses that box (the track checked longest ago), and the next frame
    follows that pose beside the track's; the track goes on from it, its id kept (`tracks_corrected`), where it
    agrees more (0.9) - not where it agrees less, with views (the fixed frame) or without."""
    scene = _scene()
    scene.poses = {1: scene.poses[1]}
    truth = scene.poses[1]

    def run(right: float) -> tuple[Tracker, list]:
        tracker = Tracker(TrackingConfig(redetect_period=3, view_window=30 if camera is not None else 0))
        scene.flip = {1}

        def follow(last: list, predicted: list) -> list[Followed]:
            return [Followed(True, R, t, COV, right if _rot_deg(R, truth[0]) < 20 else 0.75) for R, t, _ in predicted]

        poses = []
        for k in range(6):
            poses += tracker.step(k / 30, K, scene.detect, scene.estimate, follow, camera)
            scene.flip = set()  # the AGM's later poses are right
        return tracker, poses

    tracker, poses = run(right=0.9)
    assert [c.checks for c in scene.crops[-1]] == [poses[0].track_id]  # frame 3: the followed track's box posed
    assert tracker.counts["tracks_checked_apart"] == 1 and tracker.counts["tracks_corrected"] == 1
    assert len({p.track_id for p in poses}) == 1 and tracker.counts["tracks_started"] == 1
    assert _rot_deg(poses[3].R, truth[0]) > 170 and _rot_deg(poses[-1].R, truth[0]) < 20
    tracker, poses = run(right=0.72)
    assert tracker.counts["tracks_checked_apart"] == 1 and "tracks_corrected" not in tracker.counts
    assert _rot_deg(poses[-1].R, truth[0]) > 170


def test_a_track_is_looked_for_where_the_cameras_own_motion_moved_it():
    """With views and the camera's pose a still object is followed from its pose in the fixed frame brought into the
    camera: a camera that pans back and forth (8 degrees a frame) loses no contour, where the filter's constant
    velocity, which knows nothing of the camera, looks for it 11 cm off."""
    p_obj = np.array([0.0, 0.0, 0.8])

    def run(odometry: bool) -> dict[str, int]:
        tracker = Tracker(TrackingConfig(redetect_period=100, view_window=10))
        for k in range(12):
            turn = Rotation.from_euler("y", 8 * (k % 2), degrees=True).as_matrix()
            T = np.eye(4)
            T[:3, :3] = turn
            R_true, t_true = turn.T, turn.T @ p_obj
            box = (*(K @ t_true)[:2] / t_true[2] - 40, 80.0, 80.0)
            measured = Pose(True, R_true, t_true, COV)

            def follow(last: list, predicted: list, R_true=R_true, t_true=t_true) -> list[Followed]:
                # the contour's basin: it finds the object from within a centimetre
                return [Followed(True, R_true, t_true, COV, 0.9 if np.linalg.norm(t - t_true) < 0.01 else 0.3) for _, t, _ in predicted]

            tracker.step(
                k / 30, K, lambda box=box: [Det(1, 0.9, box)], lambda crops, m=measured: [m] * len(crops), follow, T if odometry else None
            )
        return tracker.counts

    moved = run(True)
    assert moved["followed"] == 11 and "contour_lost" not in moved and "ended_unfollowable" not in moved
    assert run(False)["contour_lost"] == 11  # each frame's contour lost: the AGM poses the object again every frame


def test_a_posterior_is_folded_in_as_the_one_measurement_that_gives_it():
    """A pose refined from the filter's prediction as prior is that prior and its evidence already: folding it in
    with the evidence's information moves the state (pose and velocity) exactly as the evidence's own measurement
    would have, instead of counting the prior twice."""
    import copy

    rng = np.random.default_rng(3)
    f = PoseFilter.start(FilterConfig(), np.eye(3), np.array([0.0, 0.0, 0.8]), COV)
    f.predict(1 / 30)
    R_z = Rotation.from_rotvec([0.002, -0.001, 0.003]).as_matrix() @ f.R
    t_z = f.t + rng.normal(0, 0.002, 3)
    noise = np.diag([2e-6, 3e-6, 1e-5, 1e-4, 2e-4, 1e-4])
    by_measurement, by_posterior = copy.deepcopy(f), copy.deepcopy(f)
    assert by_measurement.update(R_z, t_z, noise)[0]
    # The posterior of that evidence given the prediction: the state the measurement update reached.
    assert by_posterior.update_posterior(by_measurement.R, by_measurement.t, np.linalg.inv(noise))[0]
    np.testing.assert_allclose(by_posterior.t, by_measurement.t, atol=1e-6)
    np.testing.assert_allclose(by_posterior.R, by_measurement.R, atol=1e-6)
    np.testing.assert_allclose(by_posterior.v, by_measurement.v, atol=1e-4)
    np.testing.assert_allclose(by_posterior.P, by_measurement.P, rtol=1e-6, atol=1e-12)


def test_parts_are_followed_in_one_call_and_each_takes_its_own_poses():
    """`follow_together`: one call of the follower for every part's objects; a part that follows nothing returns at
    once; each part gets its own poses back, in order; a follower that answers for fewer objects is an error."""
    calls = []

    def follow(last, predicted):
        calls.append(list(last))
        return [m * 10 for m in last]

    def part(mine):
        if not mine:
            return ["none"]
        got = yield mine, [None] * len(mine)
        return [("got", g) for g in got]

    assert follow_together(follow, part([1, 2]), part([]), part([3])) == [("got", 10), ("got", 20), "none", ("got", 30)]
    assert calls == [[1, 2, 3]]
    assert follow_together(follow, part([])) == ["none"] and len(calls) == 1
    with pytest.raises(ValueError, match="2 poses for 3"):
        follow_together(lambda last, predicted: last[:2], part([1, 2, 3]))
