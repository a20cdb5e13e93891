"""Appearance randomisation of finished images, for every trainer: the frames the localiser reads and the crops the
AGM reads go through the same `photometric` chain, and the crops' objects through `surface` before compositing.

A real object differs from its vertex-coloured render in how it looks (highlights, fine detail, the camera's colour
response and processing), not where it is; a network that reads renders only must learn to ignore the surface's
look. The chain is the one the methods trained on renders alone use on LM-O (GDRNPP's: strong photometric ops in
random order), plus camera processing (demosaicing, sharpening). Images are float32 RGB in [0, 1]; lengths are given
in frame pixels and `scale` (image pixels per frame pixel) brings them to the image, so a crop is blurred and
dropped out as the frame it was cut from would be. A config whose probabilities are 0 draws no random number.
"""

from __future__ import annotations

import cv2
import numpy as np

from axispose_core.data.synth.config import PhotometricConfig, SurfaceConfig

_LUMA = np.array([0.299, 0.587, 0.114], np.float32)
_SMOOTH = np.array([[1, 1, 1], [1, 5, 1], [1, 1, 1]], np.float32) / 13  # PIL's ImageFilter.SMOOTH


def _grey(image: np.ndarray) -> np.ndarray:
    return (image @ _LUMA)[..., None]


def _dropout(rng: np.random.Generator, image: np.ndarray, share: float, cell: float) -> tuple[np.ndarray, np.ndarray]:
    """Coarse dropout: cells of `cell` image pixels set to black with probability `share`; (image, dropped mask)."""
    h, w = image.shape[:2]
    grid = rng.uniform(size=(max(1, int(np.ceil(h / cell))), max(1, int(np.ceil(w / cell))))) < share
    dropped = cv2.resize(grid.astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST).astype(bool)
    return np.where(dropped[..., None], np.float32(0), image), dropped


def _enhance(image: np.ndarray, degenerate: np.ndarray | float, factor: float) -> np.ndarray:
    """PIL ImageEnhance: blend from `degenerate` (factor 0) through the image (1) and beyond."""
    return np.clip(degenerate + np.float32(factor) * (image - degenerate), 0, 1)


def _gains(rng: np.random.Generator, lo: float, hi: float, per_channel: float) -> np.ndarray:
    """One value, or with probability `per_channel` one per channel (imgaug's per_channel)."""
    return rng.uniform(lo, hi, 3 if rng.uniform() < per_channel else 1).astype(np.float32)


def _op(rng: np.random.Generator, cfg: PhotometricConfig, name: str, image: np.ndarray, scale: float) -> np.ndarray:
    if name == "blur":
        sigma = scale * rng.uniform(cfg.blur[1], cfg.blur[2])
        return cv2.GaussianBlur(image, (0, 0), sigma) if sigma > 0.1 else image
    if name == "sharpness":
        return _enhance(image, cv2.filter2D(image, -1, _SMOOTH, borderType=cv2.BORDER_REPLICATE), rng.uniform(*cfg.sharpness[1:]))
    if name == "contrast":
        return _enhance(image, float(_grey(image).mean()), rng.uniform(*cfg.contrast[1:]))
    if name == "brightness":
        return _enhance(image, 0.0, rng.uniform(*cfg.brightness[1:]))
    if name == "color":
        return _enhance(image, _grey(image), rng.uniform(*cfg.color[1:]))
    if name == "add":
        return np.clip(image + _gains(rng, -cfg.add[1], cfg.add[1], cfg.add[2]) / 255, 0, 1)
    if name == "invert":
        flip = rng.uniform(size=3) < cfg.invert[1]
        return np.where(flip, 1 - image, image).astype(np.float32)
    if name == "multiply_channels":
        return np.clip(image * _gains(rng, *cfg.multiply_channels[1:]), 0, 1)
    if name == "multiply":
        return np.clip(image * np.float32(rng.uniform(*cfg.multiply[1:])), 0, 1)
    if name == "noise":
        return np.clip(image + rng.normal(0, cfg.noise[1] / 255, image.shape).astype(np.float32), 0, 1)
    if name == "linear_contrast":
        mid = np.float32(0.5)
        return np.clip(mid + _gains(rng, *cfg.linear_contrast[1:]) * (image - mid), 0, 1)
    if name == "grayscale":
        return _enhance(image, _grey(image), 1 - rng.uniform())
    raise ValueError(f"unknown photometric op {name!r}")


CHAIN = ("blur", "sharpness", "contrast", "brightness", "color", "add", "invert", "multiply_channels", "multiply", "noise",
         "linear_contrast", "grayscale")  # fmt: skip
"""The chain's ops besides dropout, by PhotometricConfig field: each field's first value is its probability."""


def _probability(cfg: PhotometricConfig, name: str) -> float:
    value = getattr(cfg, name)
    return float(value if isinstance(value, float) else value[0])


def photometric(
    rng: np.random.Generator, cfg: PhotometricConfig, image: np.ndarray, scale: float = 1.0
) -> tuple[np.ndarray, np.ndarray | None]:
    """The chain on `image` (float32 RGB in [0, 1]); (new image, the pixels coarse dropout blacked out or None).
    With probability `cfg.prob` the ops run in random order, each with its own probability; camera processing
    (demosaicing, sharpening) follows with theirs."""
    dropped = None
    if cfg.prob > 0 and rng.uniform() < cfg.prob:
        steps = ["dropout", *CHAIN]
        for k in rng.permutation(len(steps)):
            name = steps[k]
            if rng.uniform() >= _probability(cfg, name):
                continue
            if name == "dropout":
                image, dropped = _dropout(rng, image, cfg.dropout[1], max(1.0, cfg.dropout[2] * scale))
            else:
                image = _op(rng, cfg, name, image, scale)
    if cfg.demosaic > 0 and rng.uniform() < cfg.demosaic:
        image = demosaic(image)
    if cfg.sharpen[0] > 0 and rng.uniform() < cfg.sharpen[0]:
        amount = np.float32(rng.uniform(cfg.sharpen[1], cfg.sharpen[2]))
        image = np.clip(image + amount * (image - cv2.GaussianBlur(image, (0, 0), max(0.3, scale))), 0, 1)
    return image.astype(np.float32, copy=False), dropped


def demosaic(image: np.ndarray) -> np.ndarray:
    """The image sampled through an RGGB Bayer mosaic and interpolated back, as a single-sensor camera does: colour
    fringes and zipper artefacts along edges."""
    h, w = image.shape[:2]
    u8 = (np.clip(image, 0, 1) * 255 + 0.5).astype(np.uint8)
    bayer = np.empty((h, w), np.uint8)
    bayer[0::2, 0::2] = u8[0::2, 0::2, 0]
    bayer[0::2, 1::2] = u8[0::2, 1::2, 1]
    bayer[1::2, 0::2] = u8[1::2, 0::2, 1]
    bayer[1::2, 1::2] = u8[1::2, 1::2, 2]
    # OpenCV names Bayer patterns by the second row's first two pixels: RGGB is its BayerBG.
    return cv2.cvtColor(bayer, cv2.COLOR_BayerBG2RGB).astype(np.float32) / 255


def surface(rng: np.random.Generator, cfg: SurfaceConfig, image: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """The object's pixels (`mask`) with fine multiplicative detail and a per-channel colour response."""
    if cfg.detail_prob > 0 and rng.uniform() < cfg.detail_prob:
        h, w = mask.shape
        cell = rng.uniform(1.0, 3.0)
        small = rng.normal(0, 1, (max(2, round(h / cell)), max(2, round(w / cell)))).astype(np.float32)
        field = cv2.resize(small, (w, h), interpolation=cv2.INTER_LINEAR)
        gain = np.exp(np.float32(rng.uniform(*cfg.detail_std)) * field)[..., None]
        image = np.where(mask[..., None], np.clip(image * gain, 0, 1), image)
    if cfg.response_prob > 0 and rng.uniform() < cfg.response_prob:
        gamma = rng.uniform(*cfg.response_gamma, 3).astype(np.float32)
        image = np.where(mask[..., None], np.clip(image, 0, 1) ** gamma, image)
    return image.astype(np.float32, copy=False)
