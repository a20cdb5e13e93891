"""The desk recipe's scene options: objects rest on a textured table top, cast shadows on it and on each other,
among pybullet_data distractor meshes; each is there when asked for and absent when not, the same seed gives the
same frame, and the annotations still agree with the pixels."""

from dataclasses import replace

import numpy as np
import pytest
from conftest import within_a_pixel

from axispose_core.camera import project
from axispose_core.data.bop_models import load_models_info, model_path
from axispose_core.data.meshes import load_ply, load_render_mesh
from axispose_core.data.synth import clutter, generate
from axispose_core.data.synth.config import BackgroundConfig, LightConfig, RandomizationConfig, SceneConfig, SynthConfig
from axispose_core.data.synth.generate import render_image
from axispose_core.data.synth.raster import Light, RenderMesh, ShadowMap, render, vertex_normals
from axispose_core.data.synth.table import Table, shade_table, table_frame, table_pixels

OBJECTS = (1, 5, 6, 8, 9)
DESK = SynthConfig(
    seed=5,
    objects=OBJECTS,
    scene=SceneConfig(table_prob=1.0, distractor_meshes=1.0, distractors_per_image=(2, 4)),
    randomization=RandomizationConfig(light=LightConfig(shadows=1.0)),
)
K = np.array([[600.0, 0.0, 320.0], [0.0, 600.0, 240.0], [0.0, 0.0, 1.0]])


@pytest.fixture(scope="module")
def models(lmo_dir, tmp_path_factory):
    cache = tmp_path_factory.mktemp("mesh_cache")
    infos = load_models_info(lmo_dir / "models" / "models_info.json")
    return {i: load_render_mesh(lmo_dir / "models", i, cache) for i in OBJECTS}, {i: infos[i].diameter for i in OBJECTS}


@pytest.fixture(scope="module")
def frames(models):
    return [render_image(DESK, *models, 0, k) for k in range(3)]


def test_the_same_seed_gives_the_same_frame(models, frames):
    again = render_image(DESK, *models, 0, 1)
    np.testing.assert_array_equal(again.rgb, frames[1].rgb)
    assert not np.array_equal(frames[0].rgb, frames[1].rgb)


def test_objects_rest_on_a_table_below_the_camera(models, frames):
    meshes = models[0]
    for f in frames:
        assert f.table is not None and f.gt
        height = f.table.centre @ f.table.normal
        assert height < 0  # the camera (origin) is on the side the normal points to: above the table
        for g in f.gt:
            lowest = ((meshes[g.obj_id].vertices @ g.R.T + g.t) @ f.table.normal).min()
            assert lowest == pytest.approx(height, abs=1e-9)


def test_visible_model_points_lie_in_the_visible_mask(lmo_dir, frames):
    pts = {i: load_ply(model_path(lmo_dir / "models_eval", i)).vertices for i in OBJECTS}
    inside = total = 0
    for f in frames:
        for g, vis, full in zip(f.gt, f.masks_visib, f.masks, strict=True):
            assert not (vis & ~full).any()
            cam = pts[g.obj_id] @ g.R.T + g.t
            uv = np.floor(project(K_of(DESK), cam) + 0.5).astype(int)
            ok = (uv[:, 0] >= 0) & (uv[:, 0] < DESK.width) & (uv[:, 1] >= 0) & (uv[:, 1] < DESK.height)
            uv, cam = uv[ok], cam[ok]
            seen = cam[:, 2] <= f.depth[uv[:, 1], uv[:, 0]] + 0.005  # not behind anything drawn there
            inside += within_a_pixel(vis)[uv[seen, 1], uv[seen, 0]].sum()
            total += seen.sum()
    assert total > 500
    assert inside / total >= 0.98, inside / total


def K_of(cfg: SynthConfig) -> np.ndarray:
    return np.asarray(cfg.K).reshape(3, 3)


def _box(half: tuple[float, float, float]) -> RenderMesh:
    v, f = clutter.unit_mesh(clutter.library("all")[clutter.EVERYDAY.index("cube.obj")])
    v = v / np.abs(v).max(axis=0) * half
    return RenderMesh(v, f, np.full((len(v), 3), 0.8), vertex_normals(v, f))


def _sheet(side: float, n: int) -> RenderMesh:
    """A square of `side` metres in the z = 0 plane facing a camera on -z, in n x n cells (triangles small
    enough for the renderer's sampling at 1 m)."""
    xs = np.linspace(-0.5 * side, 0.5 * side, n + 1)
    v = np.array([[x, y, 0.0] for y in xs for x in xs])
    i = np.arange(n * n).reshape(n, n) // n * (n + 1) + np.arange(n * n).reshape(n, n) % n
    a, b, c, d = i.ravel(), i.ravel() + 1, i.ravel() + n + 1, i.ravel() + n + 2
    faces = np.concatenate([np.stack([a, c, b], 1), np.stack([b, c, d], 1)])
    return RenderMesh(v, faces, np.full((len(v), 3), 0.8), np.tile([0.0, 0.0, -1.0], (len(v), 1)))


def test_shadows_fall_on_the_table_and_on_other_objects_where_the_light_is_blocked():
    """A camera looking straight down at a table 1 m away, a 10 cm cube 10 cm above it, a light 45 degrees off
    vertical towards +x: the cube's shadow covers x from 0 to 0.2 m on the table, clear of the cube itself."""
    up, axes = table_frame(90.0)
    table = Table(np.array([0.0, 0.0, 1.0]), up, axes, (1.0, 1.0), np.full((8, 8, 3), 0.7, np.float32), 0.01)
    light = Light(np.array([1.0, 0.0, 1.0]) / np.sqrt(2), np.ones(3), 0.3)
    cube = (_box((0.05, 0.05, 0.05)), np.eye(3), np.array([0.0, 0.0, 0.9]))
    floor = (_sheet(1.0, 20), np.eye(3), np.array([0.0, 0.0, 0.99]))  # a sheet on the table, as a mesh
    points, depth = table_pixels(table, K, 640, 480)
    res = render([cube], K, 640, 480, light, shadows=True)
    lit_table, shaded_table = shade_table(table, points, depth, light, None), shade_table(table, points, depth, light, res.shadows)
    shadow = (slice(235, 246), slice(370, 425))  # u 370-425: x 0.08-0.17 m on the table; v about the centre line
    clear = (slice(235, 246), slice(150, 250))
    assert np.all(shaded_table[shadow] < 0.6 * lit_table[shadow])
    np.testing.assert_allclose(shaded_table[shadow], 0.7 * 0.3, atol=0.02)  # the ambient part only
    np.testing.assert_array_equal(shaded_table[clear], lit_table[clear])
    with_shadows = render([cube, floor], K, 640, 480, light, shadows=True).rgb
    without = render([cube, floor], K, 640, 480, light).rgb
    assert np.all(with_shadows[shadow] < 0.6 * without[shadow])
    np.testing.assert_array_equal(with_shadows[clear], without[clear])


def test_shadows_and_the_table_are_absent_unless_asked_for(models, monkeypatch):
    def refuse(*args, **kwargs):
        raise AssertionError("a shadow map was made")

    monkeypatch.setattr(ShadowMap, "of", refuse)
    plain = render_image(replace(DESK, scene=SceneConfig(), randomization=RandomizationConfig()), *models, 0, 0)
    assert plain.table is None and plain.gt


def test_distractor_meshes_are_drawn_when_asked_and_only_then(models, monkeypatch):
    calls = []
    real = generate.distractor_mesh

    def counted(rng, radius, split, backgrounds, exclude_faces):
        calls.append(split)
        assert exclude_faces == {len(m.faces) for m in models[0].values()}
        mesh = real(rng, radius, split, backgrounds, exclude_faces)
        assert np.linalg.norm(mesh.vertices, axis=1).max() == pytest.approx(radius)
        return mesh

    monkeypatch.setattr(generate, "distractor_mesh", counted)
    render_image(DESK, *models, 1, 0)
    assert calls and set(calls) == {"train"}
    calls.clear()
    render_image(replace(DESK, scene=replace(DESK.scene, distractor_meshes=0.0)), *models, 1, 0)
    assert calls == []


def test_lookalike_distractors_wear_an_objects_own_colour_on_their_own_shape():
    rng = np.random.default_rng(3)
    mesh = clutter.distractor_mesh(rng, 0.05, "train", BackgroundConfig())
    palettes = [np.array([[0.1, 0.2, 0.9]] * 5), np.array([[0.9, 0.8, 0.1]] * 7)]
    tint = np.array([1.1, 1.0, 0.9])
    seen = set()
    for seed in range(12):
        out = clutter.lookalike(np.random.default_rng(seed), mesh, palettes, tint)
        assert out.vertices is mesh.vertices and out.faces is mesh.faces and out.normals is mesh.normals
        base = np.median(out.colors, axis=0)
        near = [float(np.abs(base - np.clip(p[0] * tint, 0, 1)).max()) for p in palettes]
        assert min(near) < 0.05  # one palette's colour, tinted, under noise
        seen.add(int(np.argmin(near)))
        assert (out.colors >= 0).all() and (out.colors <= 1).all()
        np.testing.assert_array_equal(out.colors, clutter.lookalike(np.random.default_rng(seed), mesh, palettes, tint).colors)
    assert seen == {0, 1}


def test_lookalikes_recolour_distractors_when_asked_and_only_then(models, monkeypatch):
    calls = []
    real = generate.lookalike

    def counted(rng, mesh, palettes, tint):
        calls.append(len(palettes))
        for palette, i in zip(palettes, OBJECTS, strict=True):
            np.testing.assert_array_equal(palette, models[0][i].colors)
        return real(rng, mesh, palettes, tint)

    distractors = []

    def drawn(make):
        def counted_distractor(*args, **kwargs):
            distractors.append(make)
            return make(*args, **kwargs)

        return counted_distractor

    monkeypatch.setattr(generate, "lookalike", counted)
    monkeypatch.setattr(generate, "distractor_mesh", drawn(generate.distractor_mesh))
    monkeypatch.setattr(generate, "primitive", drawn(generate.primitive))
    base = render_image(DESK, *models, 1, 0)
    assert calls == [] and len(distractors) >= 2
    distractors.clear()
    every = render_image(replace(DESK, scene=replace(DESK.scene, lookalike_prob=1.0)), *models, 1, 0)
    assert len(calls) == len(distractors) >= 2 and set(calls) == {len(OBJECTS)}
    for a, b in zip(every.gt, base.gt, strict=True):  # the same scene, only the distractors' colours changed
        assert a.obj_id == b.obj_id and np.array_equal(a.R, b.R) and np.array_equal(a.t, b.t)
    assert not np.array_equal(every.rgb, base.rgb)
    with pytest.raises(ValueError, match="lookalike_prob"):
        SceneConfig(lookalike_prob=1.5)


@pytest.mark.slow
def test_held_out_meshes_never_reach_the_training_split():
    train, held_out, every = (set(clutter.library(s)) for s in ("train", "held_out", "all"))
    assert train.isdisjoint(held_out) and train | held_out == every
    assert len(held_out) == len(every) // clutter.HELD_OUT_EVERY and len(every) > 1000
    units = [clutter.unit_mesh(p) for p in sorted(every)]
    assert all(u is None or (np.isfinite(u[0]).all() and u[1].max() < len(u[0])) for u in units)
    assert sum(u is None for u in units) <= 2  # random_urdfs/168 is all NaN
    with pytest.raises(ValueError, match="distractor_split"):
        SceneConfig(distractor_split="test")


def test_an_own_object_taken_from_pybullet_data_is_never_its_own_distractor(tmp_path, monkeypatch):
    from axispose_core.data.mesh_import import import_meshes

    mug = clutter._data_path() / "objects" / "mug.obj"
    models_dir = tmp_path / "models"
    import_meshes([mug], models_dir, units=1.0)
    own = len(load_render_mesh(models_dir, 1).faces)
    library = (mug, clutter.library("train")[1])
    monkeypatch.setattr(clutter, "library", lambda split: library)
    rng = np.random.default_rng(0)
    faces = {len(clutter.distractor_mesh(rng, 0.05, "train", BackgroundConfig()).faces) for _ in range(20)}
    assert own in faces  # the library's mug, unless it is the scene's own object:
    faces = {len(clutter.distractor_mesh(rng, 0.05, "train", BackgroundConfig(), frozenset({own})).faces) for _ in range(20)}
    assert faces == {len(clutter.unit_mesh(library[1])[1])}


def test_the_desk_recipes_train_and_stress_on_disjoint_meshes_and_photographs():
    from axispose_core.data.synth.config import PHOTOS, recipe

    assert recipe("plain") == (SceneConfig(), RandomizationConfig())
    (desk, looks), (stress, stress_looks) = recipe("desk"), recipe("desk-held-out")
    assert desk.table_prob > 0 and desk.distractor_meshes > 0 and looks.light.shadows > 0 and looks.sensor.vignetting[1] > 0
    assert (desk.distractor_split, stress.distractor_split) == ("train", "held_out")
    assert looks.background.photos == PHOTOS and not set(stress_looks.background.photos) & set(PHOTOS)
    assert not set(stress_looks.table_top.photos) & set(looks.table_top.photos)
    with pytest.raises(ValueError, match="unknown recipe"):
        recipe("kitchen")
