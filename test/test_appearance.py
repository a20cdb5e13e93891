"""Appearance randomisation: seeded, off by default, each op's semantics, and its place in the crop stream."""

import dataclasses

import numpy as np
import pytest

from axispose_core.data.synth.appearance import _enhance, demosaic, photometric, surface
from axispose_core.data.synth.config import STREAM_RANDOMIZATION, PhotometricConfig, StreamConfig, SurfaceConfig
from axispose_core.data.synth.randomize import wrong_texture
from axispose_core.data.synth.stream import CropStream

STRONG = PhotometricConfig(prob=1.0, demosaic=0.5, sharpen=(0.5, 0.3, 1.5))


def _image(seed=1, shape=(48, 64, 3)):
    return np.random.default_rng(seed).uniform(0, 1, shape).astype(np.float32)


def test_off_by_default_and_draws_no_random_number():
    rng = np.random.default_rng(0)
    image = _image()
    out, dropped = photometric(rng, PhotometricConfig(), image)
    out2 = surface(rng, SurfaceConfig(), out, np.ones(image.shape[:2], bool))
    assert out2 is image and dropped is None
    assert rng.uniform() == np.random.default_rng(0).uniform()


def test_same_seed_same_image_and_values_stay_in_range():
    a = [photometric(np.random.default_rng([3, k]), STRONG, _image(), scale=0.5)[0] for k in range(20)]
    b = [photometric(np.random.default_rng([3, k]), STRONG, _image(), scale=0.5)[0] for k in range(20)]
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x, y)
        assert x.dtype == np.float32 and x.shape == (48, 64, 3) and 0 <= x.min() and x.max() <= 1
    assert len({float(x.mean()) for x in a}) == 20  # every draw differs


def test_enhance_is_pils_blend():
    image = np.full((4, 4, 3), 0.4, np.float32)
    np.testing.assert_allclose(_enhance(image, 0.0, 2.0), 0.8)  # brightness x2
    np.testing.assert_allclose(_enhance(image, 0.5, 0.0), 0.5)  # factor 0: the degenerate image
    np.testing.assert_allclose(_enhance(image, 0.0, 3.0), 1.0)  # clipped as 8-bit images are


def test_dropout_blacks_out_what_it_reports():
    cfg = dataclasses.replace(PhotometricConfig(prob=1.0), **{f: (0.0, *getattr(PhotometricConfig(), f)[1:]) for f in
                              ("blur", "sharpness", "contrast", "brightness", "color", "add", "invert", "multiply_channels",
                               "multiply", "noise", "linear_contrast")}, grayscale=0.0, dropout=(1.0, 0.3, 8.0))  # fmt: skip
    image = _image() * 0.5 + 0.25
    out, dropped = photometric(np.random.default_rng(5), cfg, image)
    assert dropped is not None and 0 < dropped.mean() < 1
    assert (out[dropped] == 0).all() and np.array_equal(out[~dropped], image[~dropped])


def test_demosaic_keeps_flat_colour_and_fringes_edges():
    flat = np.full((16, 16, 3), (0.2, 0.5, 0.8), np.float32)
    np.testing.assert_allclose(demosaic(flat), flat, atol=1 / 255)
    edge = np.zeros((16, 16, 3), np.float32)
    edge[:, 8:] = 1.0
    out = demosaic(edge)
    assert np.abs(out[:, 6:10] - edge[:, 6:10]).max() > 0.05  # an edge is interpolated across
    np.testing.assert_allclose(out[4:12, 1:5], 0.0, atol=1 / 255)


def test_surface_changes_only_the_objects_pixels():
    image = _image()
    mask = np.zeros(image.shape[:2], bool)
    mask[10:30, 20:40] = True
    out = surface(np.random.default_rng(2), SurfaceConfig(detail_prob=1.0, response_prob=1.0), image, mask)
    assert np.array_equal(out[~mask], image[~mask]) and not np.allclose(out[mask], image[mask])


@pytest.mark.slow
def test_crop_stream_with_appearance_is_seeded_and_keeps_its_targets(lmo_dir):
    rand = dataclasses.replace(STREAM_RANDOMIZATION, photometric=STRONG, surface=SurfaceConfig(detail_prob=1.0, response_prob=1.0))
    plain = StreamConfig(objects=(1, 5), seed=4)
    strong = dataclasses.replace(plain, randomization=rand)
    a, b, c = CropStream(strong, lmo_dir / "models"), CropStream(strong, lmo_dir / "models"), CropStream(plain, lmo_dir / "models")
    for i in range(4):
        sa, sb, sc = a[i], b[i], c[i]
        np.testing.assert_array_equal(sa.crop, sb.crop)
        np.testing.assert_array_equal(sa.keypoints, sc.keypoints)  # the pose and framing draw before the looks
        assert sa.mask_visib.sum() <= sa.mask.sum() and (sa.mask_visib <= sa.mask).all()
    assert not np.array_equal(a[0].crop, c[0].crop)


@pytest.mark.parametrize("scale", [0.25, 1.0, 3.0])
def test_lengths_are_in_frame_pixels(scale):
    """A blur of sigma s frame pixels is s * scale image pixels: a bigger scale smooths a noise image more."""
    cfg = dataclasses.replace(PhotometricConfig(prob=1.0), **{f: (0.0, *getattr(PhotometricConfig(), f)[1:]) for f in
                              ("dropout", "sharpness", "contrast", "brightness", "color", "add", "invert", "multiply_channels",
                               "multiply", "noise", "linear_contrast")}, grayscale=0.0, blur=(1.0, 2.0, 2.0))  # fmt: skip
    out, _ = photometric(np.random.default_rng(0), cfg, _image(shape=(64, 64, 3)), scale=scale)
    assert out.std() < _image(shape=(64, 64, 3)).std() * (1.2 / (1 + scale))


def test_wrong_textures_are_not_the_scan_and_stay_in_range():
    """Each of the three kinds (shuffled palette, colour bands, one flat colour) appears, in [0, 1], the scan's
    per-vertex colours replaced."""
    rng = np.random.default_rng(0)
    vertices, colors = rng.normal(0, 0.05, (500, 3)), rng.uniform(0.2, 0.8, (500, 3))
    kinds = set()
    for k in range(30):
        out = wrong_texture(np.random.default_rng([7, k]), colors, vertices)
        assert out.shape == colors.shape and 0 <= out.min() and out.max() <= 1 and not np.array_equal(out, colors)
        flat = np.allclose(out, out[0])
        shuffled = np.allclose(np.sort(out, axis=0), np.sort(colors, axis=0))
        kinds.add("flat" if flat else "shuffled" if shuffled else "bands")
    assert kinds == {"flat", "shuffled", "bands"}


def test_crop_stream_draws_wrong_textures_when_asked(lmo_dir):
    """texture_prob 1 changes the object's look, seeded, with its targets kept."""
    plain = StreamConfig(objects=(1, 5), seed=4)
    light = dataclasses.replace(plain.randomization.light, texture_prob=1.0)
    wrong = dataclasses.replace(plain, randomization=dataclasses.replace(plain.randomization, light=light))
    a, b, c = (CropStream(cfg, lmo_dir / "models") for cfg in (wrong, wrong, plain))
    for i in range(3):
        np.testing.assert_array_equal(a[i].crop, b[i].crop)
        np.testing.assert_array_equal(a[i].keypoints, c[i].keypoints)  # the pose and framing draw before the looks
    assert not np.array_equal(a[0].crop[a[0].mask_visib], c[0].crop[c[0].mask_visib])
