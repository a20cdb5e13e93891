"""The search for the objects no frame accepted (adapt/search.py): the support plane and its grid from planted
geometry, the place most frames agree on among scattered reads, and on a rendered desk recording an object left out
of every frame's candidates found where it stands, while an object the scene does not hold is not."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from axispose_core.adapt.geometry import ObjectGeometry, inverse, pose_matrix, rotation_gap_deg
from axispose_core.adapt.labels import FillConfig, label_frame
from axispose_core.adapt.pseudo import AcceptConfig, Candidate
from axispose_core.adapt.recording import read_recording
from axispose_core.adapt.run import object_geometry
from axispose_core.adapt.scene import ConsistencyConfig, Instance, agree, consistent
from axispose_core.adapt.search import (
    Discovery,
    Scene,
    SearchConfig,
    gather,
    grid,
    missing_objects,
    places,
    read_discoveries,
    search,
    support_plane,
    unoccupied,
    with_discoveries,
    write_discoveries,
)  # fmt: skip
from axispose_core.estimator import SHIPPED_ESTIMATOR, Estimator

CFG = ConsistencyConfig()


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """A camera-to-fixed 4x4 at `eye` looking at `target` (z forward, y down, `up` the fixed frame's up)."""
    z = (target - eye) / np.linalg.norm(target - eye)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    return pose_matrix(np.stack([x, np.cross(z, x), z], axis=1), eye)


def circling(n: int, up: np.ndarray, centre: np.ndarray) -> list[np.ndarray]:
    """n cameras circling `centre` at 0.8 m out and 0.5 m above it, over half a turn about `up`."""
    e1 = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    angles = np.linspace(0, np.pi, n)
    return [look_at(centre + 0.8 * (np.cos(a) * e1 + np.sin(a) * e2) + 0.5 * up, centre, up) for a in angles]


def test_the_support_plane_is_the_tables_and_its_grid_covers_the_objects():
    rng = np.random.default_rng(0)
    up = Rotation.from_rotvec([0.3, -0.2, 0.1]).apply([0.0, 0.0, 1.0])
    e1 = np.cross(up, [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    centre = np.array([0.1, -0.2, 1.0])
    centres = centre + rng.uniform(-0.15, 0.15, (5, 1)) * e1 + rng.uniform(-0.15, 0.15, (5, 1)) * e2 + rng.uniform(-0.02, 0.02, (5, 1)) * up
    cameras = circling(8, up, centre)
    for points in (centres, centres[:2]):  # five centres: their plane; two: the cameras' plane
        origin, axes = support_plane(points, cameras)
        assert np.degrees(np.arccos(axes[2] @ up)) < 8.0 and np.allclose(axes @ axes.T, np.eye(3), atol=1e-9)
    cfg = SearchConfig(step=0.03, margin=0.1)
    places_ = grid(centres, cameras, cfg)
    origin, axes = support_plane(centres, cameras)
    uv = (places_ - origin) @ axes[:2].T
    span = (centres - origin) @ axes[:2].T
    assert np.allclose((places_ - origin) @ axes[2], 0.0, atol=1e-9)
    assert (uv.min(axis=0) <= span.min(axis=0) - 0.1 + 1e-9).all() and (uv.max(axis=0) >= span.max(axis=0) + 0.1 - 0.03).all()
    nearest = np.sort(np.linalg.norm(places_[:, None] - places_[None], axis=2), axis=1)[:, 1]
    assert np.allclose(nearest, 0.03)


def test_the_place_most_frames_agree_on_wins_among_scattered_reads():
    """Eight frames each read 40 places: a place where an object stands read right (a few millimetres and degrees
    off) in six of them wins over reads scattered everywhere, fused nearer the truth than a single read; a place
    where a found object stands is no place for another."""
    rng = np.random.default_rng(1)
    up, centre = np.array([0.0, 0.0, 1.0]), np.zeros(3)
    cameras = dict(enumerate(circling(8, up, centre)))
    truth = pose_matrix(Rotation.random(random_state=rng).as_matrix(), np.array([0.05, -0.04, 0.02]))
    cands = []
    for f, C in cameras.items():
        for _ in range(40):
            T = pose_matrix(Rotation.random(random_state=rng).as_matrix(), rng.uniform(-0.3, 0.3, 3) * [1, 1, 0.1])
            local = inverse(C) @ T
            cands.append(Candidate(f, 9, local[:3, :3], local[:3, 3], 0.0, False, np.nan, np.nan, (0.0, 0.0, 1.0, 1.0)))
        if f < 6:
            local = inverse(C) @ truth
            R = Rotation.from_rotvec(np.radians(3.0) * rng.normal(size=3) / np.sqrt(3)).as_matrix() @ local[:3, :3]
            t = local[:3, 3] * (1 + 0.02 * rng.normal()) + 0.002 * rng.normal(size=3)
            cands.append(Candidate(f, 9, R, t, 0.0, False, np.nan, np.nan, (0.0, 0.0, 1.0, 1.0)))
    geometry = ObjectGeometry(0.11)
    found = places(gather(cands, cameras), cameras, geometry, CFG, SearchConfig(min_support=4))
    pose, support = found[0]
    assert support == 6 and np.linalg.norm(pose[:3, 3] - truth[:3, 3]) < 0.01
    assert rotation_gap_deg(pose[:3, :3], truth[:3, :3], geometry) < 3.0
    assert all(s < 6 for _, s in found[1:]) and all(np.linalg.norm(p[:3, 3] - truth[:3, 3]) > 0.11 for p, _ in found[1:])
    duck = Instance(9, truth)
    free = unoccupied(np.array([truth[:3, 3], truth[:3, 3] + [0.2, 0.0, 0.0]]), 0.10, [duck], {9: geometry})
    assert free.tolist() == [False, True]


@pytest.fixture(scope="module")
def desk(tmp_path_factory, lmo_dir):
    """Eight rendered frames of four LM-O objects resting on a table among clutter, the camera circling (BOP)."""
    from axispose_core.data.synth.config import CameraPathConfig, SynthConfig, recipe
    from axispose_core.data.synth.generate import generate

    out = tmp_path_factory.mktemp("desk")
    scene, randomization = recipe("desk")
    scene = dataclasses.replace(scene, table_prob=1.0, objects_per_image=(4, 4))
    cfg = SynthConfig(seed=11, scenes=1, images_per_scene=8, objects=(1, 5, 9, 12), scene=scene, randomization=randomization,
                      camera_path=CameraPathConfig(orbit_deg=5.0))  # fmt: skip
    generate(cfg, lmo_dir / "models", out, progress=False)
    return out / "000000"


@pytest.mark.slow
def test_on_a_rendered_desk_a_never_accepted_object_is_found_and_an_absent_one_is_not(desk, tmp_path):
    """Every frame's candidates are the truth but for the duck's (never accepted): the search finds the duck where
    it stands, and no cat (the scene holds none); what it found is predicted in every frame and read back whole."""
    rec = read_recording(desk)
    truth = {int(f): gs for f, gs in json.loads((desk / "scene_gt.json").read_text()).items()}
    assert {g["obj_id"] for g in truth[0]} == {1, 5, 9, 12}
    est = Estimator.load(SHIPPED_ESTIMATOR)
    est.set_precision("float32")
    geometry = object_geometry(est)
    cands, duck = {}, {}
    for f, gs in truth.items():
        poses = {g["obj_id"]: (np.asarray(g["cam_R_m2c"], float).reshape(3, 3), np.asarray(g["cam_t_m2c"], float) / 1000) for g in gs}
        cands[f] = [Candidate(f, o, R, t, 0.9, True, 1.0, 0.9, (0.0, 0.0, 1.0, 1.0)) for o, (R, t) in poses.items() if o != 9]
        duck[f] = poses[9]
    scene = consistent(cands, geometry, AcceptConfig(), CFG, {f.im_id: f.camera for f in rec.frames})
    assert missing_objects(scene, [1, 5, 6, 9, 12]) == [6, 9]
    frames = {f.im_id: f for f in rec.frames}
    cfg = SearchConfig(views=5, places=2, step=0.04, margin=0.05)
    found = {d.obj_id: d for d in search(Scene(est, frames, scene, geometry, CFG, FillConfig()), cfg, objects=(6, 9))}
    assert found[6].pose is None and found[9].pose is not None and found[9].takes >= cfg.min_share * cfg.views
    filled = with_discoveries(scene, list(found.values()))
    errors = []
    for f, (R, t) in duck.items():  # the place within the scene's gates; the labels on the contours near the truth
        assert agree(CFG, inverse(scene.cameras[f]) @ found[9].pose, pose_matrix(R, t), geometry[9])
        mine = [p for p in filled.predictions[f] if p.obj_id == 9]
        assert len(mine) == 1 and mine[0].own is None
        labels = label_frame(est.refiner, frames[f].rgb(), frames[f].K, filled.predictions[f], [], geometry, CFG, FillConfig())
        errors += [(np.linalg.norm(lab.t - t), rotation_gap_deg(lab.R, R, geometry[9])) for lab in labels if lab.obj_id == 9]
    errors = np.array(errors)
    assert len(errors) == len(duck) and errors[:, 0].max() < 0.03 and errors[:, 1].max() < 5.0
    write_discoveries(tmp_path / "search.json", list(found.values()))
    back = {d.obj_id: d for d in read_discoveries(tmp_path / "search.json")}
    assert back[6] == found[6] and np.allclose(back[9].pose, found[9].pose) and back[9].takes == found[9].takes


def test_search_settings_that_cannot_find_anything_are_refused():
    for bad in ({"min_support": 1}, {"places": 0}, {"min_share": 0.0}, {"step": 0.0}):
        with pytest.raises(ValueError, match="search"):
            SearchConfig(**bad)
    assert Discovery.from_json(Discovery(9, None, 3, 0, 12).to_json()) == Discovery(9, None, 3, 0, 12)
