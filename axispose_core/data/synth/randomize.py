"""Appearance randomisation: backgrounds, lights, object colour, and the camera's blur, noise and occluders.

Photographs come from packages the project installs (scikit-image's sample images, matplotlib's sample data:
real photos shipped inside registry packages; nothing is downloaded); procedural backgrounds are smooth noise,
stripes, checkers and gradients, and printed markers and clutter where the configuration names them. Both
`axispose synth` (full frames) and the crop stream (object crops) draw from here. Every knob that the frame
recipe leaves off draws no random number, so turning a knob on in one recipe never changes another's frames.
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np

from axispose_core.data.synth.config import PHOTOS, SURFACES, TEXTURES, BackgroundConfig, LightConfig, RandomizationConfig, SensorConfig
from axispose_core.data.synth.raster import Light


def _photo_path(name: str) -> Path:
    """'file' is in scikit-image's data folder; 'package:relative/path' inside an installed package."""
    package, _, rel = name.rpartition(":")
    module = __import__(package or "skimage")
    return Path(module.__file__).parent / (rel if package else Path("data") / rel)


@lru_cache(maxsize=4)
def photographs(names: tuple[str, ...] = PHOTOS) -> tuple[np.ndarray, ...]:
    """The named photographs as RGB float32 in [0,1] (grey ones as three equal channels)."""
    out = []
    for name in names:
        path = _photo_path(name)
        img = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if img is None:
            raise FileNotFoundError(f"background photograph {path} is missing (is its package installed?)")
        out.append(cv2.cvtColor(img, cv2.COLOR_BGR2RGB).astype(np.float32) / 255.0)
    return tuple(out)


def _markers(rng: np.random.Generator, width: int, height: int) -> np.ndarray:
    """Printed fiducials on paper: black-bordered random bit grids (ArUco-like) on a light sheet, turned and scaled."""
    paper = rng.uniform(0.75, 1.0) * np.clip(1 + rng.normal(0, 0.03, 3), 0.9, 1.1)
    img = np.ones((height, width, 3), np.float32) * paper.astype(np.float32)
    side = rng.uniform(0.15, 0.6) * max(width, height)
    for _ in range(int(rng.integers(1, 5))):
        n = int(rng.integers(4, 7))
        bits = np.zeros((n + 2, n + 2), np.float32)
        bits[1:-1, 1:-1] = rng.integers(0, 2, (n, n))
        tile = np.pad(bits, 1, constant_values=1.0)  # white quiet zone
        A = cv2.getRotationMatrix2D(((n + 3) / 2, (n + 3) / 2), rng.uniform(0, 360), side / (n + 4))
        A[:, 2] += rng.uniform(-0.3, 1.0, 2) * (width, height)
        ink = cv2.warpAffine(tile, A, (width, height), flags=cv2.INTER_NEAREST, borderValue=-1.0)
        img[ink == 0.0] = rng.uniform(0.0, 0.15)
        img[ink == 1.0] = paper
    return img


def _clutter(rng: np.random.Generator, width: int, height: int) -> np.ndarray:
    """Dead-leaves clutter: many overlapping rectangles, ellipses and strokes of random colour and size."""
    img = np.ones((height, width, 3), np.float32) * rng.uniform(0, 1, 3).astype(np.float32)
    scale = max(width, height)
    for _ in range(int(rng.integers(15, 50))):
        colour = tuple(float(c) for c in rng.uniform(0, 1, 3))
        c = (int(rng.uniform(0, width)), int(rng.uniform(0, height)))
        r = np.maximum(1, rng.uniform(0.02, 0.3, 2) * scale).astype(int)
        kind = rng.integers(3)
        if kind == 0:
            cv2.rectangle(img, (c[0] - r[0], c[1] - r[1]), (c[0] + r[0], c[1] + r[1]), colour, -1)
        elif kind == 1:
            cv2.ellipse(img, c, (int(r[0]), int(r[1])), rng.uniform(0, 180), 0, 360, colour, -1)
        else:
            end = (int(rng.uniform(0, width)), int(rng.uniform(0, height)))
            cv2.line(img, c, end, colour, max(1, int(r[0] / 8)), cv2.LINE_AA)
    return img


def _smooth(rng: np.random.Generator, width: int, height: int, cells: int, channels: int = 3) -> np.ndarray:
    """Uniform noise on a grid of `cells` across, interpolated up to width x height (H, W, channels)."""
    small = rng.uniform(0, 1, (max(2, cells * height // width), cells, channels)).astype(np.float32)
    return cv2.resize(small, (width, height), interpolation=cv2.INTER_CUBIC).reshape(height, width, channels)


def _surface(rng: np.random.Generator, kind: str, width: int, height: int) -> np.ndarray:
    """Materials of a table top: wood (warped grain, planks), cloth (a weave) and paper (fibres, faint shading)."""
    ys, xs = np.mgrid[0:height, 0:width].astype(np.float32)
    if kind == "wood":
        base = rng.uniform(0.3, 0.8) * np.array([1.0, rng.uniform(0.55, 0.75), rng.uniform(0.3, 0.5)], np.float32)
        plank = rng.uniform(0.15, 0.5) * width
        warp = _smooth(rng, width, height, 6, 1)[..., 0] * rng.uniform(5, 30)
        grain = 0.5 + 0.5 * np.sin(2 * np.pi * (xs + warp) / rng.uniform(3, 12))
        seams = (np.mod(xs + warp * 0.1, plank) < 1.5).astype(np.float32)
        tone = 0.8 + 0.25 * grain + 0.15 * (_smooth(rng, width, height, 3, 1)[..., 0] - 0.5) - 0.5 * seams
        return np.clip(base[None, None] * tone[..., None], 0, 1)
    if kind == "cloth":
        base = rng.uniform(0.1, 0.9, 3).astype(np.float32)
        p = rng.uniform(2.0, 6.0)
        weave = 0.5 + 0.25 * (np.sin(2 * np.pi * xs / p) + np.sin(2 * np.pi * ys / p))
        tone = 0.8 + 0.3 * weave + 0.1 * (_smooth(rng, width, height, 32, 1)[..., 0] - 0.5)
        return np.clip(base[None, None] * tone[..., None], 0, 1)
    white = rng.uniform(0.75, 1.0) * np.clip(1 + rng.normal(0, 0.03, 3), 0.9, 1.1).astype(np.float32)  # paper
    tone = 1 + 0.06 * (_smooth(rng, width, height, 64, 1)[..., 0] - 0.5) - 0.1 * _smooth(rng, width, height, 2, 1)[..., 0]
    return np.clip(white[None, None] * tone[..., None], 0, 1).astype(np.float32)


def _procedural(rng: np.random.Generator, width: int, height: int, kinds: tuple[str, ...] = TEXTURES) -> np.ndarray:
    kind = kinds[int(rng.integers(len(kinds)))]
    if kind == "markers":
        return _markers(rng, width, height)
    if kind == "clutter":
        return _clutter(rng, width, height)
    if kind in SURFACES:
        return _surface(rng, kind, width, height)
    if kind == "noise":  # smooth multi-scale colour noise
        img = np.zeros((height, width, 3), np.float32)
        for cells in (4, 16, 64):
            img += _smooth(rng, width, height, cells) / 3
        return img
    ys, xs = np.mgrid[0:height, 0:width].astype(np.float32)
    a, b = rng.uniform(0, 1, 3), rng.uniform(0, 1, 3)
    angle = rng.uniform(0, np.pi)
    proj = xs * np.cos(angle) + ys * np.sin(angle)
    if kind == "stripes":
        mix = 0.5 + 0.5 * np.sin(proj * 2 * np.pi / rng.uniform(8, 80))
    elif kind == "checkers":
        p = rng.uniform(10, 80)
        mix = ((np.floor(xs / p) + np.floor(ys / p)) % 2).astype(np.float32)
    else:  # gradient
        mix = (proj - proj.min()) / max(float(np.ptp(proj)), 1.0)
    return (a[None, None] * mix[..., None] + b[None, None] * (1 - mix[..., None])).astype(np.float32)


def background(rng: np.random.Generator, cfg: BackgroundConfig, width: int, height: int, zoom: float = 1.0) -> np.ndarray:
    """A width x height RGB background: a random crop of a photograph (flipped, tinted) or a procedural texture.
    `zoom` < 1 shows that part of a frame's background: the photograph's crop shrinks by it."""
    if rng.uniform() < cfg.photo_background_prob:
        photo = photographs(cfg.photos)[rng.integers(len(cfg.photos))]
        h, w = photo.shape[:2]
        scale = min(1.0, rng.uniform(*cfg.photo_scale) * zoom)
        ch, cw = max(8, int(h * scale)), max(8, int(min(w, h * width / height) * scale))
        y0, x0 = rng.integers(0, h - ch + 1), rng.integers(0, w - cw + 1)
        img = cv2.resize(photo[y0 : y0 + ch, x0 : x0 + cw], (width, height), interpolation=cv2.INTER_LINEAR)
        if rng.uniform() < 0.5:
            img = img[:, ::-1]
        img = img * rng.uniform(0.8, 1.2, 3).astype(np.float32)
    else:
        img = _procedural(rng, width, height, cfg.textures)
    return np.clip(img, 0, 1).astype(np.float32)


def light(rng: np.random.Generator, cfg: LightConfig) -> Light:
    """A directional light from the camera's hemisphere, of random intensity and tint, with random ambient."""
    d = rng.normal(size=3)
    d[2] = abs(d[2]) + 0.3  # travelling away from the camera: lights the visible side
    color = rng.uniform(*cfg.light_intensity) * np.clip(1 + rng.normal(0, cfg.light_color_jitter, 3), 0.5, 1.5)
    ambient = float(rng.uniform(*cfg.ambient))
    if cfg.specular[1] <= 0:
        return Light(d / np.linalg.norm(d), color, ambient)
    return Light(d / np.linalg.norm(d), color, ambient, float(rng.uniform(*cfg.specular)), float(rng.uniform(*cfg.shininess)))


def wrong_texture(rng: np.random.Generator, colors: np.ndarray, vertices: np.ndarray) -> np.ndarray:
    """Per-vertex colours (N,3) that are not the object's: its own shuffled over the vertices (speckle of its
    palette), bands of colour along a random direction (1-5 cm period, on the model's metres), or one flat colour."""
    kind = int(rng.integers(3))
    if kind == 0:
        return colors[rng.permutation(len(colors))]
    if kind == 1:
        d = rng.normal(size=3)
        along = vertices @ (d / np.linalg.norm(d)) * (2 * np.pi / rng.uniform(0.01, 0.05))
        return 0.5 + rng.uniform(0.15, 0.45) * np.sin(along[:, None] + rng.uniform(0, 2 * np.pi, 3))
    return np.broadcast_to(rng.uniform(0.05, 0.95, 3), colors.shape).copy()


def object_tint(rng: np.random.Generator, cfg: LightConfig) -> np.ndarray:
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


def camera_effects(
    rng: np.random.Generator,
    cfg: SensorConfig,
    image: np.ndarray,
    scale: float = 1.0,
    origin: tuple[float, float] = (0.0, 0.0),
    frame: tuple[int, int] | None = None,
    noise: np.random.Generator | None = None,
) -> np.ndarray:
    """The camera between scene and pixels: optical blur, lateral chromatic aberration and vignetting, motion blur,
    white balance, contrast and saturation, gamma, a low dynamic range, sensor noise (more of it in the dark where
    `noise_shot` says so); JPEG artefacts come from saving (`jpeg` for in-memory images). `scale`: image pixels per
    frame pixel, for lengths given in frame pixels; `origin`: the frame coordinates of the image's top-left
    corner and `frame` the frame's (width, height) (None: the image is the frame), for the effects that grow
    away from the frame's centre. `noise`: where the sensor noise's pattern is drawn from (None: `rng`), so that the
    frames of a video share the camera's settings and not its noise."""
    if rng.uniform() < cfg.blur_prob:
        image = cv2.GaussianBlur(image, (0, 0), max(0.05, scale * rng.uniform(*cfg.blur_sigma)))
    if cfg.chromatic > 0 or cfg.vignetting[1] > 0:
        h, w = image.shape[:2]
        fw, fh = frame or (w / scale, h / scale)
        dx = origin[0] + (np.arange(w, dtype=np.float32) + 0.5) / scale - 0.5 * fw  # frame px from its centre
        dy = origin[1] + (np.arange(h, dtype=np.float32) + 0.5) / scale - 0.5 * fh
        if cfg.chromatic > 0:
            image = _chromatic(image, rng.uniform(-cfg.chromatic, cfg.chromatic), dx, dy, scale)
        if cfg.vignetting[1] > 0:
            r2 = (dy[:, None] ** 2 + dx[None, :] ** 2) / (0.25 * (fw * fw + fh * fh))
            image = image * (1 - np.float32(rng.uniform(*cfg.vignetting)) * r2)[..., None]
    if cfg.motion_blur_prob > 0 and rng.uniform() < cfg.motion_blur_prob:
        image = motion_blur(image, scale * rng.uniform(*cfg.motion_blur_px), rng.uniform(0, 180))
    if cfg.white_balance > 0:
        image = image * np.clip(1 + rng.normal(0, cfg.white_balance, 3), 0.6, 1.4).astype(np.float32)
    if cfg.contrast > 0:
        grey = image.mean(axis=-1, keepdims=True)
        image = grey + (image - grey) * np.float32(np.clip(1 + rng.normal(0, 2 * cfg.contrast), 0.0, 2.0))
        mean = float(grey.mean())
        image = mean + (image - mean) * np.float32(np.clip(1 + rng.normal(0, cfg.contrast), 0.5, 1.5))
    if cfg.gamma[1] > 0:
        image = np.clip(image, 0, 1) ** np.float32(rng.uniform(*cfg.gamma))
    if cfg.dynamic_range[1] > 0:
        lost = rng.uniform(*cfg.dynamic_range)
        black = lost * rng.uniform()
        image = np.clip((image - np.float32(black)) / np.float32(1 - lost), 0, 1)
    std = rng.uniform(*cfg.noise_std)
    if std > 0:
        # OpenCV's generator, seeded from ours, is several times faster than NumPy's for a full frame.
        cv2.setRNGSeed(int((rng if noise is None else noise).integers(2**31)))
        noise = np.empty(image.shape, np.float32)
        cv2.randn(noise, 0.0, float(std))
        if cfg.noise_shot > 0:  # read noise plus a term that grows as the signal falls (gain in the dark)
            noise *= 1 + cfg.noise_shot * (1 - np.clip(image.mean(axis=-1, keepdims=True), 0, 1))
        image = image + noise
    return np.clip(image, 0, 1)


def _chromatic(image: np.ndarray, delta: float, dx: np.ndarray, dy: np.ndarray, scale: float) -> np.ndarray:
    """Red magnified by 1 + delta and blue by 1 - delta about the frame's centre (`dx`, `dy`: each image column's
    and row's frame offset from it): the colour fringes a lens leaves at the edges of a frame."""
    out = image.copy()
    cols, rows = np.arange(len(dx), dtype=np.float32), np.arange(len(dy), dtype=np.float32)
    for channel, m in ((0, 1 + delta), (2, 1 - delta)):
        # The channel's value at a pixel is the scene's where the lens drew it from: offsets shrunk by m.
        map_x = np.broadcast_to(cols + (dx / m - dx) * scale, (len(dy), len(dx)))
        map_y = np.broadcast_to((rows + (dy / m - dy) * scale)[:, None], (len(dy), len(dx)))
        out[..., channel] = cv2.remap(image[..., channel], np.ascontiguousarray(map_x, np.float32), np.ascontiguousarray(map_y, np.float32),
                                      cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)  # fmt: skip
    return out


def motion_blur(image: np.ndarray, length: float, angle_deg: float) -> np.ndarray:
    """Blur along a straight path of `length` pixels at `angle_deg` (a line kernel, normalised)."""
    if length < 1.0:
        return image
    k = max(3, int(np.ceil(length)) | 1)
    kernel = np.zeros((k, k), np.float32)
    c = (k - 1) / 2
    dx, dy = 0.5 * length * np.cos(np.radians(angle_deg)), 0.5 * length * np.sin(np.radians(angle_deg))
    cv2.line(kernel, (round(16 * (c - dx)), round(16 * (c - dy))), (round(16 * (c + dx)), round(16 * (c + dy))), 1.0, 1, cv2.LINE_AA, 4)
    return cv2.filter2D(image, -1, kernel / max(float(kernel.sum()), 1e-6), borderType=cv2.BORDER_REFLECT)


def jpeg(image: np.ndarray, quality: int) -> np.ndarray:
    """`image` (float RGB in [0,1]) through a JPEG encode and decode at `quality`, as a saved and reloaded frame."""
    bgr = (np.clip(image[..., ::-1], 0, 1) * 255 + 0.5).astype(np.uint8)
    ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise RuntimeError("OpenCV could not encode a JPEG")
    return cv2.imdecode(buf, cv2.IMREAD_COLOR)[..., ::-1].astype(np.float32) / 255.0
