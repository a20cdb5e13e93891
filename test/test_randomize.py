"""The camera model's lens and sensor knobs (data/synth/randomize.py): each does what it says, a crop gets what
its part of the frame gets, and a knob left at 0 changes nothing."""

from dataclasses import replace

import numpy as np
import pytest

from axispose_core.data.synth.config import SensorConfig
from axispose_core.data.synth.randomize import camera_effects

QUIET = SensorConfig(blur_prob=0.0, noise_std=(0.0, 0.0))
"""Everything off: the image goes through untouched."""
W, H = 640, 480


def _apply(cfg: SensorConfig, image: np.ndarray, seed: int = 0, **where) -> np.ndarray:
    return camera_effects(np.random.default_rng(seed), cfg, image.astype(np.float32), **where)


def test_knobs_at_zero_leave_the_image_and_the_random_stream_alone():
    image = np.random.default_rng(1).uniform(0, 1, (H, W, 3)).astype(np.float32)
    rng = np.random.default_rng(0)
    np.testing.assert_array_equal(camera_effects(rng, QUIET, image), image)
    plain = np.random.default_rng(0)
    plain.uniform(), plain.uniform(0.0, 0.0)  # the two numbers QUIET draws (blur on/off, noise std)
    assert rng.uniform() == plain.uniform()


def test_vignetting_darkens_the_corners_and_a_crop_gets_what_its_part_of_the_frame_gets():
    grey = np.full((H, W, 3), 0.5, np.float32)
    cfg = replace(QUIET, vignetting=(0.3, 0.3))
    frame = _apply(cfg, grey)
    assert frame[H // 2, W // 2, 0] == pytest.approx(0.5, abs=1e-3)
    assert frame[0, 0, 0] == pytest.approx(0.5 * 0.7, abs=5e-3)
    crop = _apply(cfg, grey[:64, 500:564], origin=(500.0, 0.0), frame=(W, H))
    np.testing.assert_allclose(crop, frame[:64, 500:564], atol=1e-6)
    half = _apply(cfg, grey[:32, 250:282], scale=0.5, origin=(500.0, 0.0), frame=(W, H))  # the same window, 2 frame px per px
    np.testing.assert_allclose(half, frame[:64:2, 500:564:2] + (frame[1:64:2, 501:564:2] - frame[:64:2, 500:564:2]) / 2, atol=2e-3)


def _centroid_x(channel: np.ndarray) -> float:
    cols = np.arange(channel.shape[1])
    return float((channel.sum(axis=0) * cols).sum() / channel.sum())


def test_chromatic_aberration_splits_red_from_blue_in_proportion_to_the_distance_from_the_centre():
    image = np.zeros((H, W, 3), np.float32)
    for x in (20, W // 2 - 4, W - 28):
        image[H // 2 - 4 : H // 2 + 4, x : x + 8] = 1.0  # white squares at the left edge, centre, right edge
    out = _apply(replace(QUIET, chromatic=0.004), image, seed=3)
    split = []
    for x in (20, W // 2 - 4, W - 28):
        patch = out[H // 2 - 12 : H // 2 + 12, x - 8 : x + 16]
        split.append(_centroid_x(patch[..., 0]) - _centroid_x(patch[..., 2]))
    left, centre, right = split
    assert abs(centre) < 0.02
    assert right == pytest.approx(-left, rel=0.1) and 0.05 < abs(right) < 2 * 0.004 * (W / 2)
    np.testing.assert_allclose(out[..., 1], image[..., 1])  # green is the reference
    np.testing.assert_array_equal(_apply(QUIET, image, seed=3), image)


def test_a_low_dynamic_range_clips_the_share_it_is_asked_to():
    ramp = np.broadcast_to(np.linspace(0, 1, W, dtype=np.float32)[None, :, None], (H, W, 3))
    out = _apply(replace(QUIET, dynamic_range=(0.2, 0.2)), ramp, seed=5)
    row = out[0, :, 0]
    clipped = np.mean((row <= 0.0) | (row >= 1.0))
    assert clipped == pytest.approx(0.2, abs=0.01)
    assert np.all(np.diff(row) >= 0)  # the tone order is kept
