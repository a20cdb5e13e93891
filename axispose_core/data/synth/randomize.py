"""Appearance randomisation: backgrounds, lights, object colour, and the camera's blur, noise and occluders.

Photographs come from scikit-image's bundled sample images (real photos shipped inside a registry package:
nothing is downloaded); procedural backgrounds are smooth noise, stripes, checkers and gradients.
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np

from axispose_core.data.synth.config import RandomizationConfig
from axispose_core.data.synth.raster import Light

PHOTOS = (
    "astronaut.png", "brick.png", "camera.png", "chelsea.png", "coffee.png", "coins.png", "color.png", "grass.png",
    "gravel.png", "hubble_deep_field.jpg", "ihc.png", "moon.png", "motorcycle_left.png", "motorcycle_right.png",
    "retina.jpg", "rocket.jpg", "text.png",
)  # fmt: skip
"""Bundled photographs used as backgrounds (not page.png: its ICC profile makes libpng warn on every read)."""


@lru_cache(maxsize=1)
def photographs() -> tuple[np.ndarray, ...]:
    """The sample photographs as RGB float32 in [0,1] (grey ones as three equal channels)."""
    import skimage  # the photos ship in its wheel; only their files are used

    folder = Path(skimage.__file__).parent / "data"
    out = []
    for name in PHOTOS:
        img = cv2.imread(str(folder / name), cv2.IMREAD_COLOR)
        if img is None:
            raise FileNotFoundError(f"background photograph {folder / name} is missing (is scikit-image installed?)")
        out.append(cv2.cvtColor(img, cv2.COLOR_BGR2RGB).astype(np.float32) / 255.0)
    return tuple(out)


def _procedural(rng: np.random.Generator, width: int, height: int) -> np.ndarray:
    kind = rng.integers(4)
    if kind == 0:  # smooth multi-scale colour noise
        img = np.zeros((height, width, 3), np.float32)
        for cells in (4, 16, 64):
            small = rng.uniform(0, 1, (max(2, cells * height // width), cells, 3)).astype(np.float32)
            img += cv2.resize(small, (width, height), interpolation=cv2.INTER_CUBIC) / 3
        return img
    ys, xs = np.mgrid[0:height, 0:width].astype(np.float32)
    a, b = rng.uniform(0, 1, 3), rng.uniform(0, 1, 3)
    angle = rng.uniform(0, np.pi)
    proj = xs * np.cos(angle) + ys * np.sin(angle)
    if kind == 1:  # stripes
        mix = 0.5 + 0.5 * np.sin(proj * 2 * np.pi / rng.uniform(8, 80))
    elif kind == 2:  # checkers
        p = rng.uniform(10, 80)
        mix = ((np.floor(xs / p) + np.floor(ys / p)) % 2).astype(np.float32)
    else:  # gradient
        mix = (proj - proj.min()) / max(float(np.ptp(proj)), 1.0)
    return (a[None, None] * mix[..., None] + b[None, None] * (1 - mix[..., None])).astype(np.float32)


def background(rng: np.random.Generator, cfg: RandomizationConfig, width: int, height: int) -> np.ndarray:
    """A width x height RGB background: a random crop of a photograph (flipped, tinted) or a procedural texture."""
    if rng.uniform() < cfg.photo_background_prob:
        photo = photographs()[rng.integers(len(PHOTOS))]
        h, w = photo.shape[:2]
        scale = rng.uniform(0.4, 1.0)
        ch, cw = max(8, int(h * scale)), max(8, int(min(w, h * width / height) * scale))
        y0, x0 = rng.integers(0, h - ch + 1), rng.integers(0, w - cw + 1)
        img = cv2.resize(photo[y0 : y0 + ch, x0 : x0 + cw], (width, height), interpolation=cv2.INTER_LINEAR)
        if rng.uniform() < 0.5:
            img = img[:, ::-1]
        img = img * rng.uniform(0.8, 1.2, 3).astype(np.float32)
    else:
        img = _procedural(rng, width, height)
    return np.clip(img, 0, 1).astype(np.float32)


def light(rng: np.random.Generator, cfg: RandomizationConfig) -> Light:
    """A directional light from the camera's hemisphere, of random intensity and tint, with random ambient."""
    d = rng.normal(size=3)
    d[2] = abs(d[2]) + 0.3  # travelling away from the camera: lights the visible side
    color = rng.uniform(*cfg.light_intensity) * np.clip(1 + rng.normal(0, cfg.light_color_jitter, 3), 0.5, 1.5)
    return Light(d / np.linalg.norm(d), color, float(rng.uniform(*cfg.ambient)))


def object_tint(rng: np.random.Generator, cfg: RandomizationConfig) -> np.ndarray:
    """Per-object RGB gain: brightness times a small colour jitter."""
    return rng.uniform(*cfg.object_brightness) * np.clip(1 + rng.normal(0, cfg.object_color_jitter, 3), 0.7, 1.3)


def cutouts(rng: np.random.Generator, cfg: RandomizationConfig, image: np.ndarray) -> np.ndarray:
    """Paint random-coloured rectangles and ellipses in front of everything; returns the occluded-pixel mask."""
    h, w = image.shape[:2]
    mask = np.zeros((h, w), np.uint8)
    if rng.uniform() >= cfg.cutout_prob:
        return mask.astype(bool)
    for _ in range(int(rng.integers(cfg.cutouts[0], cfg.cutouts[1] + 1))):
        size = rng.uniform(*cfg.cutout_size, 2) * w
        c = (int(rng.uniform(0, w)), int(rng.uniform(0, h)))
        shape = np.zeros((h, w), np.uint8)
        if rng.uniform() < 0.5:
            cv2.rectangle(
                shape, (int(c[0] - size[0] / 2), int(c[1] - size[1] / 2)), (int(c[0] + size[0] / 2), int(c[1] + size[1] / 2)), 1, -1
            )
        else:
            cv2.ellipse(shape, c, (int(size[0] / 2), int(size[1] / 2)), rng.uniform(0, 180), 0, 360, 1, -1)
        sel = shape.astype(bool)
        if rng.uniform() < 0.5:
            image[sel] = rng.uniform(0, 1, 3).astype(np.float32)
        else:  # a texture of the occluder's own box only: a full frame of it would cost ten times more
            ys, xs = np.nonzero(sel)
            y0, x0 = ys.min(), xs.min()
            patch = _procedural(rng, int(xs.max() - x0 + 1), int(ys.max() - y0 + 1))
            image[ys, xs] = patch[ys - y0, xs - x0]
        mask |= shape
    return mask.astype(bool)


def camera_effects(rng: np.random.Generator, cfg: RandomizationConfig, image: np.ndarray) -> np.ndarray:
    """Optical blur and sensor noise; JPEG artefacts come from saving with a random quality."""
    if rng.uniform() < cfg.blur_prob:
        image = cv2.GaussianBlur(image, (0, 0), rng.uniform(*cfg.blur_sigma))
    std = rng.uniform(*cfg.noise_std)
    if std > 0:
        # OpenCV's generator, seeded from ours, is several times faster than NumPy's for a full frame.
        cv2.setRNGSeed(int(rng.integers(2**31)))
        noise = np.empty(image.shape, np.float32)
        cv2.randn(noise, 0.0, float(std))
        image = image + noise
    return np.clip(image, 0, 1)
