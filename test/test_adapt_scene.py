"""Static-scene consistency (adapt/scene.py) on planted scenes: cameras recovered without odometry, a flip and a
misplaced pose rejected, a missed object filled, a moved object found, symmetric objects' equivalent poses agreeing."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from axispose_core.adapt.geometry import ObjectGeometry, inverse, pose_matrix, rotation_gap_deg
from axispose_core.adapt.pseudo import AcceptConfig, Candidate
from axispose_core.adapt.report import round_counts
from axispose_core.adapt.scene import ConsistencyConfig, consistent
from axispose_core.objects import lmo_objects

ACCEPT = AcceptConfig(min_score=0.5, min_agreement=0.75)
CFG = ConsistencyConfig()
HALF_TURN_Z = (Rotation.from_euler("z", 180, degrees=True).as_matrix(), np.zeros(3))
GEOMETRY = {1: ObjectGeometry(0.10), 5: ObjectGeometry(0.20), 6: ObjectGeometry(0.15), 9: ObjectGeometry(0.11),
            10: ObjectGeometry(0.16, ((np.eye(3), np.zeros(3)), HALF_TURN_Z))}  # fmt: skip


def look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """A camera-to-fixed 4x4 at `eye` looking at `target` (z forward, y down)."""
    z = (target - eye) / np.linalg.norm(target - eye)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    return pose_matrix(np.stack([x, np.cross(z, x), z], axis=1), eye)


def planted_scene(seed: int = 0, frames: int = 12):
    """Five objects on a table (fixed frame: z up), a camera circling them at 0.9 m, and every frame's poses with a
    single view's errors (depth 3 %, 2 px across, 3 degrees)."""
    rng = np.random.default_rng(seed)
    objects = {o: pose_matrix(Rotation.random(random_state=rng).as_matrix(), np.r_[rng.uniform(-0.15, 0.15, 2), 0.0]) for o in GEOMETRY}
    cameras = {}
    for f in range(frames):
        a = 2 * np.pi * f / (2 * frames)
        cameras[f] = look_at(np.array([0.8 * np.cos(a), 0.8 * np.sin(a), 0.4]), np.zeros(3))
    cands = {f: [candidate(f, o, inverse(cameras[f]) @ T, rng) for o, T in objects.items()] for f in cameras}
    return objects, cameras, cands


def candidate(f: int, obj_id: int, T: np.ndarray, rng: np.random.Generator, score: float = 0.9) -> Candidate:
    R = Rotation.from_rotvec(np.radians(3.0) * rng.normal(size=3) / np.sqrt(3)).as_matrix() @ T[:3, :3]
    t = T[:3, 3] * (1 + 0.03 * rng.normal()) + 0.003 * np.r_[rng.normal(size=2), 0.0]
    return Candidate(f, obj_id, R, t, score, True, 0.9, 0.85, (0.0, 0.0, 10.0, 10.0))


def test_cameras_are_recovered_without_odometry_and_the_scene_predicts_every_object():
    """The cameras within a few degrees and centimetres (a frame's depth is its objects' depths: ~1 cm here), and the
    scene's predictions nearer the truth than the frames' own poses."""
    objects, cameras, cands = planted_scene()
    out = consistent(cands, GEOMETRY, ACCEPT, CFG)
    assert sorted(out.cameras) == sorted(cameras) and not out.rejected and not out.moved_objects
    assert round_counts(cands, ACCEPT, out, [], {}, lmo_objects())["moved"] == []  # frame ids are not object ids
    anchor = next(f for f, T in out.cameras.items() if np.allclose(T, np.eye(4)))
    for f, T in out.cameras.items():  # relative to the anchor camera, as the truth
        truth = inverse(cameras[anchor]) @ cameras[f]
        assert np.linalg.norm(T[:3, 3] - truth[:3, 3]) < 0.07 and rotation_gap_deg(T[:3, :3], truth[:3, :3], GEOMETRY[1]) < 6.0
    errors, own = [], []
    for f, preds in out.predictions.items():
        assert sorted(p.obj_id for p in preds) == sorted(objects)
        for p in preds:
            truth = inverse(cameras[f]) @ objects[p.obj_id]
            errors.append((np.linalg.norm(p.t - truth[:3, 3]), rotation_gap_deg(p.R, truth[:3, :3], GEOMETRY[p.obj_id])))
            own.append((np.linalg.norm(p.own.t - truth[:3, 3]), rotation_gap_deg(p.own.R, truth[:3, :3], GEOMETRY[p.obj_id])))
    errors, own = np.array(errors), np.array(own)
    assert (np.median(errors, axis=0) < np.median(own, axis=0)).all() and errors[:, 0].max() < 0.04 and errors[:, 1].max() < 5.0


def test_a_planted_flip_and_a_misplaced_pose_are_rejected_and_a_miss_is_filled():
    objects, cameras, cands = planted_scene(1)
    flip = Rotation.from_euler("x", 180, degrees=True).as_matrix()
    c = cands[4][0]
    cands[4][0] = Candidate(c.im_id, c.obj_id, c.R @ flip, c.t, 0.95, True, 0.9, 0.9, c.box)  # the ape turned over
    c = cands[7][1]
    cands[7][1] = Candidate(c.im_id, c.obj_id, c.R, c.t + np.array([0.15, 0.0, 0.0]), 0.95, True, 0.9, 0.9, c.box)  # the can aside
    missed = cands[9].pop(2)  # the cat not accepted in frame 9
    out = consistent(cands, GEOMETRY, ACCEPT, CFG)
    reasons = {(c.im_id, c.obj_id): why for c, why in out.rejected}
    assert reasons == {(4, 1): "turned", (7, 5): "misplaced"}
    filled = [p for p in out.predictions[9] if p.obj_id == missed.obj_id]
    assert len(filled) == 1 and filled[0].own is None
    truth = inverse(cameras[9]) @ objects[missed.obj_id]
    assert np.linalg.norm(filled[0].t - truth[:3, 3]) < 0.05 and rotation_gap_deg(filled[0].R, truth[:3, :3], GEOMETRY[6]) < 3.0
    assert all(p.own is not None for f in out.predictions for p in out.predictions[f] if (f, p.obj_id) not in {(9, 6), (4, 1), (7, 5)})


def test_a_symmetric_objects_equivalent_poses_agree_and_low_evidence_is_not_a_seed():
    _, cameras, cands = planted_scene(2)
    S = HALF_TURN_Z[0]
    for f in (1, 3, 5, 8):  # the eggbox read at its other, indistinguishable pose
        c = next(c for c in cands[f] if c.obj_id == 10)
        cands[f][cands[f].index(c)] = Candidate(f, 10, c.R @ S, c.t, c.score, True, 0.9, 0.85, c.box)
    weak = cands[6].pop(0)
    cands[6].append(Candidate(6, weak.obj_id, weak.R, weak.t, 0.1, True, 0.9, 0.85, weak.box))  # evidence too weak alone
    out = consistent(cands, GEOMETRY, ACCEPT, CFG)
    assert not out.rejected
    eggbox = [i for i in out.instances[0] if i.obj_id == 10]
    assert len(eggbox) == 1 and eggbox[0].views == len(cameras)
    ape = next(p for p in out.predictions[6] if p.obj_id == weak.obj_id)
    assert ape.own is None  # predicted there: the label stage refines it on the frame


def test_an_object_that_moved_falls_back_to_each_frames_own_evidence():
    objects, cameras, cands = planted_scene(3, frames=14)
    moved = pose_matrix(objects[9][:3, :3], objects[9][:3, 3] + np.array([0.0, 0.25, 0.0]))
    rng = np.random.default_rng(9)
    for f in range(7, 14):  # the duck put elsewhere half way through
        cands[f] = [c for c in cands[f] if c.obj_id != 9] + [candidate(f, 9, inverse(cameras[f]) @ moved, rng)]
    out = consistent(cands, GEOMETRY, ACCEPT, CFG)
    assert out.moved_objects == {9} and sorted(out.cameras) == sorted(cameras)
    counts = round_counts(cands, ACCEPT, out, [], {}, lmo_objects())
    assert counts["moved"] == ["duck"] and counts["objects"]["duck"]["moved"] and not counts["objects"]["ape"]["moved"]
    assert not any(p.obj_id == 9 for preds in out.predictions.values() for p in preds)
    assert sorted(c.im_id for c in out.alone if c.obj_id == 9) == list(range(14))


def test_odometry_places_the_cameras_and_a_thin_scene_fills_nothing():
    _, cameras, cands = planted_scene(4, frames=6)
    cands = {f: cs[:1] for f, cs in cands.items()}  # one object a frame: no camera can be placed from the objects
    out = consistent(cands, GEOMETRY, ACCEPT, CFG)
    assert len(out.cameras) <= 1 and sorted(c.im_id for c in out.alone) == sorted(cameras)
    out = consistent(cands, GEOMETRY, ACCEPT, CFG, odometry=cameras)
    assert out.odometry and sorted(out.cameras) == sorted(cameras) and len(out.instances[0]) == 1 and not out.alone


@pytest.mark.parametrize("gate", [0.0, -1.0])
def test_config_refuses_gates_that_admit_nothing(gate):
    with pytest.raises(ValueError):
        ConsistencyConfig(depth_gate=gate)


def test_a_window_keeps_a_moved_objects_poses_consistent_on_either_side_of_the_move():
    """With `window`, each frame's scene is its neighbours': the duck put elsewhere half way through is a still object
    in the frames away from the move, and its poses there are checked by the scene's."""
    objects, cameras, cands = planted_scene(3, frames=14)
    moved = pose_matrix(objects[9][:3, :3], objects[9][:3, 3] + np.array([0.0, 0.25, 0.0]))
    rng = np.random.default_rng(9)
    for f in range(7, 14):
        cands[f] = [c for c in cands[f] if c.obj_id != 9] + [candidate(f, 9, inverse(cameras[f]) @ moved, rng)]
    out = consistent(cands, GEOMETRY, ACCEPT, ConsistencyConfig(window=3))
    far = [0, 1, 2, 3, 10, 11, 12, 13]
    assert not any(9 in out.moved.get(f, set()) for f in far) and not out.rejected
    for f in far:
        duck = [p for p in out.predictions[f] if p.obj_id == 9]
        truth = inverse(cameras[f]) @ (objects[9] if f < 7 else moved)
        assert len(duck) == 1 and duck[0].own is not None and np.linalg.norm(duck[0].t - truth[:3, 3]) < 0.04
    assert 9 in out.moved[7] or 9 in out.moved[6]  # a window across the move sees it
