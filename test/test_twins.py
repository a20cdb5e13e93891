"""Rendered twins of real frames: only the annotated objects' pixels change, the annotations carry over."""

from __future__ import annotations

import json
import shutil

import cv2
import numpy as np
import pytest
from PIL import Image

from axispose_core.data.bop import bbox_from_model
from axispose_core.data.bop_scene import BopScene
from axispose_core.data.meshes import load_render_mesh
from axispose_core.data.synth.raster import Light, render
from axispose_core.data.twins import TwinPart, twin_frame, write_twins
from axispose_core.lmo import REAL_SLICE, SHARED_LMO

MODELS = SHARED_LMO / "models_eval"
pytestmark = pytest.mark.skipif(not (REAL_SLICE / "000002").is_dir() or not MODELS.is_dir(), reason="needs ../shared/data")


@pytest.fixture(scope="module")
def one_frame(tmp_path_factory):
    """The real slice's first frame as a one-frame split."""
    src = REAL_SLICE / "000002"
    im_id = BopScene(src).image_ids[0]
    dst = tmp_path_factory.mktemp("real") / "test" / "000002"
    (dst / "rgb").mkdir(parents=True)
    shutil.copy2(src / "rgb" / f"{im_id:06d}.png", dst / "rgb")
    for name in ("scene_gt.json", "scene_camera.json"):
        whole = json.loads((src / name).read_text())
        (dst / name).write_text(json.dumps({str(im_id): whole[str(im_id)]}))
    return dst.parent, im_id


def test_twins_change_only_the_objects_and_keep_the_annotations(one_frame, tmp_path):
    split, im_id = one_frame
    out = write_twins(split, MODELS, tmp_path / "twins")
    real, twin = BopScene(split / "000002"), BopScene(out / "000002")
    assert twin.image_ids == real.image_ids
    for a, b in zip(real.gt[im_id], twin.gt[im_id], strict=True):
        assert a.obj_id == b.obj_id and np.array_equal(a.R, b.R) and np.array_equal(a.t, b.t)
    assert np.array_equal(twin.cameras[im_id], real.cameras[im_id])

    frame = np.asarray(Image.open(real.rgb_path(im_id)).convert("RGB"))
    pasted = np.asarray(Image.open(twin.rgb_path(im_id)).convert("RGB"))
    assert pasted.shape == frame.shape
    inside = np.zeros(frame.shape[:2], dtype=bool)
    for g in real.gt[im_id]:
        x, y, w, h = bbox_from_model(real.cameras[im_id], g.R, g.t, load_render_mesh(MODELS, g.obj_id).vertices)
        box = (slice(max(y - 1, 0), y + h + 1), slice(max(x - 1, 0), x + w + 1))
        inside[box] = True
        assert (pasted[box] != frame[box]).any(-1).mean() > 0.05, f"object {g.obj_id} was not drawn"
    assert np.array_equal(pasted[~inside], frame[~inside]), "a pixel outside every object's box changed"


def test_a_written_scene_is_kept(one_frame, tmp_path):
    split, im_id = one_frame
    out = write_twins(split, MODELS, tmp_path / "twins")
    png = out / "000002" / "rgb" / f"{im_id:06d}.png"
    stamp = png.stat().st_mtime_ns
    write_twins(split, MODELS, tmp_path / "twins")
    assert png.stat().st_mtime_ns == stamp


def test_flat_twins_draw_each_object_in_one_colour(one_frame, tmp_path):
    """`flat`: under a white matte light every pixel of an object has the same chromaticity (its mean colour,
    shaded); the textured twins' objects do not."""
    split, im_id = one_frame
    matte = Light(np.array([0.0, 0.0, 1.0]), np.ones(3), ambient=0.5, specular=0.0)
    chroma_spread = {}
    for flat in (False, True):
        out = write_twins(split, SHARED_LMO / "models", tmp_path / f"twins_{flat}", matte, "mean" if flat else "scan")  # vertex-coloured
        pasted = np.asarray(Image.open(out / "000002" / "rgb" / f"{im_id:06d}.png").convert("RGB")).astype(float)
        real = BopScene(split / "000002")
        gts = real.gt[im_id]
        h, w = pasted.shape[:2]
        res = render([(load_render_mesh(MODELS, g.obj_id), g.R, g.t) for g in gts], real.cameras[im_id], w, h, matte)
        largest = np.bincount(res.instance[res.instance >= 0]).argmax()  # the object most seen
        px = pasted[(res.instance == largest) & (pasted.sum(-1) > 60)]
        assert len(px) > 200
        chroma_spread[flat] = (px / px.sum(-1, keepdims=True)).std(axis=0).max()
    assert chroma_spread[True] < 0.02 < chroma_spread[False]


def test_a_part_of_the_look_comes_from_the_render_and_the_rest_from_the_frame(one_frame):
    """`inside` and `edge` split each silhouette between the render and the frame, one the other's complement;
    `coarse` and `fine` split the look by frequency, so together they add up to frame plus render; outside the
    objects nothing changes."""
    split, im_id = one_frame
    scene = BopScene(split / "000002")
    gts = scene.gt[im_id]
    rgb = np.asarray(Image.open(scene.rgb_path(im_id)).convert("RGB"))
    meshes = [load_render_mesh(MODELS, g.obj_id) for g in gts]
    frames = {
        part: twin_frame(rgb, scene.cameras[im_id], gts, meshes, part=TwinPart(part, 3.0))
        for part in ("all", "inside", "edge", "coarse", "fine")
    }
    full = frames["all"]
    drawn = (full != rgb).any(-1)
    for part, frame in frames.items():
        assert np.array_equal(frame[~drawn], rgb[~drawn]), part

    rendered_inside = (frames["inside"] == full).all(-1) & drawn
    rendered_edge = (frames["edge"] == full).all(-1) & drawn
    assert not (rendered_inside & rendered_edge).any()
    assert np.array_equal(rendered_inside | rendered_edge, drawn)
    assert (frames["inside"][rendered_edge] == rgb[rendered_edge]).all()
    deep = cv2.distanceTransform(drawn.astype(np.uint8), cv2.DIST_L2, 5) > 5  # far from every silhouette's edge
    assert rendered_inside[deep].mean() > 0.9 and rendered_edge[deep].mean() < 0.05  # bands: where two objects meet
    assert 0.2 < rendered_edge.sum() / drawn.sum() < 0.8  # a 3 px band of objects some 40-150 px across

    total = frames["coarse"].astype(int) + frames["fine"].astype(int) - rgb.astype(int) - full.astype(int)
    assert np.mean(np.abs(total[drawn]) <= 2) > 0.97
    assert (frames["coarse"][drawn] != frames["fine"][drawn]).any(-1).mean() > 0.5


def test_an_unknown_part_is_refused():
    with pytest.raises(ValueError, match="part must be one of"):
        TwinPart("middle")
    with pytest.raises(ValueError, match="px must be"):
        TwinPart("edge", 0.0)
