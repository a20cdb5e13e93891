"""Image degradations for stress evaluation: what a robot camera gives in a dim room or while moving.

Each takes an RGB uint8 frame and a seeded generator and returns a degraded RGB uint8 frame of the same shape,
so a stress run is reproducible (`axispose eval --perturb ...`).
"""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np


def low_light(rgb: np.ndarray, rng: np.random.Generator, gain: tuple[float, float] = (0.12, 0.3), read_noise: float = 2.0) -> np.ndarray:
    """An under-exposed frame: intensity scaled by a gain in `gain`, then shot noise (Poisson, in 8-bit units
    of the dimmed signal) and Gaussian read noise of `read_noise` levels, quantised back to uint8."""
    signal = rgb.astype(np.float64) * rng.uniform(*gain)
    noisy = rng.poisson(signal) + rng.normal(0.0, read_noise, rgb.shape)
    return np.clip(np.round(noisy), 0, 255).astype(np.uint8)


def motion_blur(rgb: np.ndarray, rng: np.random.Generator, length: tuple[int, int] = (9, 21)) -> np.ndarray:
    """Linear motion blur: a straight streak of `length` pixels (drawn per frame) at a random angle."""
    n = int(rng.integers(length[0], length[1] + 1)) | 1  # odd, so the kernel has a centre
    angle = rng.uniform(0.0, np.pi)
    kernel = np.zeros((n, n), np.float32)
    c, r = n // 2, (n - 1) / 2
    dx, dy = r * np.cos(angle), r * np.sin(angle)
    cv2.line(kernel, (round(c - dx), round(c - dy)), (round(c + dx), round(c + dy)), 1.0, 1, cv2.LINE_AA)
    kernel /= kernel.sum()
    return cv2.filter2D(rgb, -1, kernel, borderType=cv2.BORDER_REFLECT)


PERTURBATIONS: dict[str, Callable[[np.ndarray, np.random.Generator], np.ndarray]] = {
    "low_light": low_light,
    "motion_blur": motion_blur,
}
