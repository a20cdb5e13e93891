"""Synthetic data: annotations agree with the pixels, depth order is right, output is deterministic and resumable."""

import dataclasses
import itertools
import json
import os
import shutil

import cv2
import numpy as np
import pytest
from conftest import within_a_pixel

from axispose_core.axis_image import AxisSpec
from axispose_core.camera import instance_crop, project
from axispose_core.data.bop_models import load_models_info, model_path
from axispose_core.data.bop_scene import BopScene
from axispose_core.data.meshes import load_ply, load_render_mesh
from axispose_core.data.synth.config import SynthConfig
from axispose_core.data.synth.generate import generate, render_image
from axispose_core.data.synth.raster import Light, render
from axispose_core.train.dataset import axis_target

CFG = SynthConfig(seed=11, scenes=2, images_per_scene=3, objects=(1, 5, 6, 8, 9))


@pytest.fixture(scope="module")
def dataset(tmp_path_factory, lmo_dir):
    out = tmp_path_factory.mktemp("synth") / "data"
    assert generate(CFG, lmo_dir / "models", out, workers=1, progress=False) == 6
    return out


@pytest.fixture(scope="module")
def meshes(dataset, lmo_dir):
    return {i: load_render_mesh(lmo_dir / "models", i, dataset / ".mesh_cache") for i in CFG.objects}


def _mask(path):
    m = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert m is not None, path
    return m > 0


def _instances(dataset):
    for scene_id in range(CFG.scenes):
        scene = BopScene(dataset / f"{scene_id:06d}")
        for im_id in scene.image_ids:
            for k, (g, info) in enumerate(zip(scene.gt[im_id], scene.gt_info[im_id], strict=True)):
                yield scene_id, scene, im_id, k, g, info


def test_layout_and_config(dataset):
    assert SynthConfig.load(dataset / "synth_config.json") == CFG
    assert (dataset / "models_info.json").exists()
    scene = BopScene(dataset / "000000")
    img = cv2.imread(str(scene.rgb_path(0)))
    assert img.shape == (CFG.height, CFG.width, 3)
    assert sum(len(v) for v in scene.gt.values()) >= 3 * CFG.scene.objects_per_image[0] - 3


def test_visibility_fractions_and_boxes_match_the_masks(dataset):
    for _, scene, im_id, k, _, info in _instances(dataset):
        full = _mask(scene.root / "mask" / f"{im_id:06d}_{k:06d}.png")
        vis = _mask(scene.root / "mask_visib" / f"{im_id:06d}_{k:06d}.png")
        assert not (vis & ~full).any()
        assert 0.0 <= info.visib_fract <= 1.0
        assert info.px_count_all == full.sum() and info.px_count_visib == vis.sum()
        assert info.visib_fract == pytest.approx(vis.sum() / max(full.sum(), 1))
        if vis.any():
            x, y, w, h = info.bbox_visib
            assert 0 <= x and 0 <= y and x + w <= CFG.width and y + h <= CFG.height
            ys, xs = np.nonzero(vis)
            assert (xs.min(), ys.min(), xs.max() - xs.min() + 1, ys.max() - ys.min() + 1) == (x, y, w, h)


def test_visible_model_points_lie_in_the_visible_mask(dataset, meshes, lmo_dir):
    K = np.asarray(CFG.K).reshape(3, 3)
    infos = load_models_info(dataset / "models_info.json")
    pts = {i: load_ply(model_path(lmo_dir / "models_eval", i)).vertices for i in CFG.objects}
    inside, total = 0, 0
    for scene_id, scene, im_id, k, g, _ in _instances(dataset):
        depth = render_image(CFG, meshes, {i: infos[i].diameter for i in CFG.objects}, scene_id, im_id).depth
        vis = _mask(scene.root / "mask_visib" / f"{im_id:06d}_{k:06d}.png")
        cam = pts[g.obj_id] @ g.R.T + g.t
        uv = np.floor(project(K, cam) + 0.5).astype(int)
        ok = (uv[:, 0] >= 0) & (uv[:, 0] < CFG.width) & (uv[:, 1] >= 0) & (uv[:, 1] < CFG.height)
        uv, cam = uv[ok], cam[ok]
        seen = cam[:, 2] <= depth[uv[:, 1], uv[:, 0]] + 0.005  # not behind anything drawn there
        inside += within_a_pixel(vis)[uv[seen, 1], uv[seen, 0]].sum()
        total += seen.sum()
    assert total > 1000
    assert inside / total >= 0.98, inside / total


def test_nearer_object_owns_the_overlap(dataset, meshes):
    K = np.asarray(CFG.K).reshape(3, 3)
    light = Light(np.array([0.0, 0.0, 1.0]), np.ones(3), 0.5)
    overlaps = agree = 0
    for scene_id in range(CFG.scenes):
        scene = BopScene(dataset / f"{scene_id:06d}")
        for im_id in scene.image_ids:
            gts = scene.gt[im_id]
            alone = [render([(meshes[g.obj_id], g.R, g.t)], K, CFG.width, CFG.height, light).depth for g in gts]
            visib = [_mask(scene.root / "mask_visib" / f"{im_id:06d}_{k:06d}.png") for k in range(len(gts))]
            for i in range(len(gts)):
                for j in range(i + 1, len(gts)):
                    both = np.isfinite(alone[i]) & np.isfinite(alone[j]) & (visib[i] | visib[j])
                    overlaps += both.sum()
                    nearer_i = alone[i][both] < alone[j][both]
                    agree += (nearer_i == visib[i][both]).sum()
    assert overlaps > 100, "the test scenes should contain occlusions between objects"
    assert agree / overlaps >= 0.99


def test_axis_targets_line_up_with_the_object_in_the_crop(dataset):
    infos = load_models_info(dataset / "models_info.json")
    hits = n = 0
    for _, scene, im_id, k, g, info in _instances(dataset):
        if info.visib_fract < 0.5:
            continue
        full = _mask(scene.root / "mask" / f"{im_id:06d}_{k:06d}.png").astype(np.uint8)
        rgb = cv2.imread(str(scene.rgb_path(im_id)))
        crop = instance_crop(rgb, scene.cameras[im_id], info.bbox_obj, 64, rng=np.random.default_rng(k))
        target = axis_target(crop, g.R, g.t, AxisSpec.from_diameter(infos[g.obj_id].diameter).lengths, 64)
        mask_crop = instance_crop(full, scene.cameras[im_id], info.bbox_obj, 64, rng=np.random.default_rng(k)).patch
        origin = target.max(axis=2) > 0.5  # all three axes start at the origin
        assert origin.any()
        uv = crop.K_patch @ g.t
        u, v = round(uv[0] / uv[2]), round(uv[1] / uv[2])
        assert min(target[v, u]) > 0.5  # the origin pixel is lit in every channel
        n += 1
        hits += 0 <= u < 64 and 0 <= v < 64 and mask_crop[v, u] > 0
    assert n >= 5
    assert hits / n >= 0.8  # BOP models are centred: the origin projects onto the object


@pytest.mark.slow
def test_same_seed_same_bytes_whatever_the_workers(dataset, lmo_dir, tmp_path):
    small = SynthConfig(seed=11, scenes=2, images_per_scene=3, objects=CFG.objects)
    other = tmp_path / "again"
    generate(small, lmo_dir / "models", other, workers=2, progress=False)
    for scene in ("000000", "000001"):
        for name in ("scene_gt.json", "scene_camera.json", "scene_gt_info.json"):
            assert (other / scene / name).read_bytes() == (dataset / scene / name).read_bytes()
        for f in sorted((dataset / scene / "rgb").iterdir()):
            assert (other / scene / "rgb" / f.name).read_bytes() == f.read_bytes()


def test_resume_redoes_only_incomplete_scenes(dataset, lmo_dir, tmp_path):
    copy = tmp_path / "copy"
    shutil.copytree(dataset, copy)
    (copy / "000001" / "scene_gt_info.json").unlink()
    os.remove(copy / "000001" / "rgb" / "000002.jpg")
    assert generate(CFG, lmo_dir / "models", copy, progress=False) == CFG.images_per_scene
    assert (copy / "000001" / "rgb" / "000002.jpg").read_bytes() == (dataset / "000001" / "rgb" / "000002.jpg").read_bytes()
    assert json.loads((copy / "000001" / "scene_gt_info.json").read_text()) == json.loads(
        (dataset / "000001" / "scene_gt_info.json").read_text()
    )


def test_other_config_into_same_folder_is_refused(dataset, lmo_dir):
    with pytest.raises(ValueError, match="different configuration"):
        generate(SynthConfig(seed=12, scenes=1, images_per_scene=1, objects=CFG.objects), lmo_dir / "models", dataset, progress=False)


def test_unknown_object_is_refused(lmo_dir, tmp_path):
    with pytest.raises(ValueError, match=r"no object\(s\) \[99\]"):
        generate(SynthConfig(objects=(99,)), lmo_dir / "models", tmp_path / "x", progress=False)


def test_memory_stays_bounded_over_1000_renders(meshes):
    """The renderer holds no state between calls: resident memory must not grow with the number of renders."""
    K = np.array([[150.0, 0, 80], [0, 150.0, 60], [0, 0, 1]])
    light = Light(np.array([0.0, 0.0, 1.0]), np.ones(3), 0.5)
    mesh = meshes[1]

    def rss_mb() -> float:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20

    rng = np.random.default_rng(0)
    t = np.array([0.0, 0.0, 0.5])
    for _ in range(50):
        render([(mesh, np.eye(3), t)], K, 160, 120, light)
    start = rss_mb()
    for _ in range(1000):
        R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
        R *= np.sign(np.linalg.det(R))
        render([(mesh, R, t)], K, 160, 120, light)
    growth = rss_mb() - start
    print(f"RSS growth over 1000 renders: {growth:.1f} MB")
    assert growth < 20.0


def test_a_camera_path_films_one_world(meshes):
    """Along a camera path every object moves by the same rigid motion between images (one world, one moving
    camera), by about the orbit's angle, and the images differ."""
    from axispose_core.data.synth.config import CameraPathConfig

    cfg = dataclasses.replace(CFG, camera_path=CameraPathConfig(orbit_deg=2.0, shake_deg=0.0, shake_m=0.0),
                              scene=dataclasses.replace(CFG.scene, table_prob=1.0))  # fmt: skip
    diameters = {i: 2 * float(np.linalg.norm(m.vertices, axis=1).max()) for i, m in meshes.items()}
    frames = [render_image(cfg, meshes, diameters, 0, k) for k in range(3)]
    assert [[g.obj_id for g in f.gt] for f in frames] == [[g.obj_id for g in frames[0].gt]] * 3
    for a, b in itertools.pairwise(frames):
        motions = [(gb.R @ ga.R.T, gb.t - gb.R @ ga.R.T @ ga.t) for ga, gb in zip(a.gt, b.gt, strict=True)]
        for R, t in motions[1:]:
            np.testing.assert_allclose(R, motions[0][0], atol=1e-9)
            np.testing.assert_allclose(t, motions[0][1], atol=1e-9)
        angle = np.degrees(np.arccos(np.clip((np.trace(motions[0][0]) - 1) / 2, -1, 1)))
        assert angle == pytest.approx(2.0, abs=1e-6)
        assert np.abs(a.rgb.astype(int) - b.rgb.astype(int)).mean() > 1.0
    # the same image again is the same bytes
    assert np.array_equal(render_image(cfg, meshes, diameters, 0, 2).rgb, frames[2].rgb)


def test_a_camera_path_scene_records_the_cameras_pose(lmo_dir, tmp_path):
    """A camera path's scene_camera.json gives each image's camera pose (BOP's cam_R_w2c, cam_t_w2c), the one the
    objects were filmed from: each object's pose brought back to the world by it is the same in every image."""
    from axispose_core.data.synth.config import CameraPathConfig

    path = CameraPathConfig(orbit_deg=3.0, sweep_deg=10.0, sweep_frames=8)
    cfg = dataclasses.replace(CFG, scenes=1, images_per_scene=4, camera_path=path)
    generate(cfg, lmo_dir / "models", tmp_path, workers=1, progress=False)
    scene = BopScene(tmp_path / "000000")
    assert sorted(scene.camera_poses) == scene.image_ids == [0, 1, 2, 3]
    np.testing.assert_allclose(scene.camera_poses[0][0], np.eye(3), atol=1e-12)  # the world is the first camera's frame
    world = {}
    for im_id in scene.image_ids:
        R, t = scene.camera_poses[im_id]
        for g in scene.gt[im_id]:
            R_w, t_w = world.setdefault(g.obj_id, (R.T @ g.R, R.T @ (g.t - t)))
            np.testing.assert_allclose(R.T @ g.R, R_w, atol=1e-6)
            np.testing.assert_allclose(R.T @ (g.t - t), t_w, atol=1e-6)  # mm on disk: float rounding only
    assert np.degrees(np.arccos((np.trace(scene.camera_poses[3][0]) - 1) / 2)) > 1.0  # the camera moved


def test_a_camera_stream_sweeps_smears_passes_occluders_and_keeps_its_cameras_settings(meshes):
    """A stream as a hand-held camera films one: the view sweeps (the world turns far more than the orbit), frames
    are smeared along their motion and their exposure walks, an occluder crosses the view once (an unannotated
    mesh that hides the objects for a while), and the camera's own settings (white balance, tone) stay put."""
    from axispose_core.data.synth.config import CameraPathConfig
    from axispose_core.data.synth.generate import passers, sample_world

    path = CameraPathConfig(orbit_deg=0.5, shake_deg=0.0, shake_m=0.0, sweep_deg=20.0, sweep_frames=40, shutter=0.5, gain_walk=0.1,
                            passers=1, pass_frames=6)  # fmt: skip
    cfg = dataclasses.replace(CFG, images_per_scene=20, camera_path=path)
    diameters = {i: 2 * float(np.linalg.norm(m.vertices, axis=1).max()) for i, m in meshes.items()}
    world = sample_world(cfg, meshes, diameters, np.random.default_rng([cfg.seed, 0, 0]))
    crossing = passers(cfg, world, np.random.default_rng([cfg.seed, 0, 0, 3]))[0]
    k = crossing.start
    frames = {j: render_image(cfg, meshes, diameters, 0, j) for j in (0, k - 1, k + 2, k + 3)}
    first, later = frames[0].gt[0], frames[k + 3].gt[0]
    turned = np.degrees(np.arccos(np.clip((np.trace(later.R @ first.R.T) - 1) / 2, -1, 1)))
    assert turned > 0.5 * (k + 3) + 2.0  # the sweep on top of the orbit
    K = np.asarray(cfg.K).reshape(3, 3)
    assert crossing.pose(k - 1, 6, K, cfg.width) is None and crossing.pose(k + 2, 6, K, cfg.width) is not None
    visible = [sum(i.px_count_visib for i in frames[j].info) for j in (k - 1, k + 2)]
    assert len(frames[k + 2].gt) == len(frames[k - 1].gt) and visible[1] != visible[0]
    assert np.array_equal(render_image(cfg, meshes, diameters, 0, k + 2).rgb, frames[k + 2].rgb)  # repeatable
    balance = [frames[j].rgb.reshape(-1, 3).mean(axis=0) for j in (0, k - 1)]
    np.testing.assert_allclose(balance[0] / balance[0][1], balance[1] / balance[1][1], rtol=0.05)  # one white balance


def test_the_cli_changes_the_recipes_look_and_scenes_where_told_and_refuses_a_bad_change(lmo_dir, tmp_path, capsys):
    from axispose_core.cli import main
    from axispose_core.data.synth.config import recipe

    base = ["synth", "--models", str(lmo_dir / "models"), "--scenes", "1", "--images-per-scene", "1", "--objects", "1", "--recipe", "plain"]
    out = tmp_path / "flat"
    assert main([*base, "--out", str(out), "--randomization", "{light: {ambient: [0.15, 1.0]}}"]) == 0
    _, plain = recipe("plain")
    light = dataclasses.replace(plain.light, ambient=(0.15, 1.0))
    assert SynthConfig.load(out / "synth_config.json").randomization == dataclasses.replace(plain, light=light)
    capsys.readouterr()  # the render's progress

    alike = tmp_path / "alike"
    assert main([*base, "--out", str(alike), "--scene", "{lookalike_prob: 0.5, distractors_per_image: [2, 3]}"]) == 0
    scene, _ = recipe("plain")
    wanted = dataclasses.replace(scene, lookalike_prob=0.5, distractors_per_image=(2, 3))
    assert SynthConfig.load(alike / "synth_config.json").scene == wanted
    capsys.readouterr()

    for option, bad, message in (
        ("--randomization", "{light: {ambiant: 1}}", "ambiant"),
        ("--randomization", "[1, 2]", "expected a YAML mapping"),
        ("--scene", "{lookalike: 0.5}", "lookalike"),
        ("--scene", "{lookalike_prob: 2}", "lookalike_prob must lie in [0, 1]"),
    ):
        assert main([*base, "--out", str(tmp_path / "bad"), option, bad]) == 2
        err = capsys.readouterr().err
        assert message in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "bad").exists()
