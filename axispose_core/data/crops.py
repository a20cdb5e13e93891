"""Training pairs for the AGM: an object crop with its patch intrinsics and the axis image the GT pose draws in it.

The crop is the square around the instance's box that a detector would give (optionally jittered in centre
and scale); its intrinsics K' come from `camera.crop_intrinsics`, so the target axis image, rendered from the
saved GT pose through K', lines up with the object in the crop by construction.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from axispose_core.axis_image import DEFAULT_LINE_WIDTH, render_axis_image
from axispose_core.camera import crop_image, crop_intrinsics, square_around_box


@dataclass(frozen=True)
class CropJitter:
    """Detector-like noise on the crop: centre shift as a fraction of the side, and a scale range of the pad."""

    shift: float = 0.1
    pad: tuple[float, float] = (1.1, 1.5)


@dataclass(frozen=True)
class InstanceCrop:
    patch: np.ndarray
    K_patch: np.ndarray
    center: tuple[float, float]
    side: float


def instance_crop(
    image: np.ndarray,
    K: np.ndarray,
    box_xywh: tuple[float, float, float, float],
    size: int,
    rng: np.random.Generator | None = None,
    jitter: CropJitter = CropJitter(),
    pad: float = 1.25,
) -> InstanceCrop:
    """Cut the size x size crop around a box; with `rng`, jitter it as `jitter` says (else `pad`, centred)."""
    if rng is None:
        center, side = square_around_box(box_xywh, pad=pad)
    else:
        center, side = square_around_box(box_xywh, pad=float(rng.uniform(*jitter.pad)))
        center = (center[0] + rng.uniform(-jitter.shift, jitter.shift) * side, center[1] + rng.uniform(-jitter.shift, jitter.shift) * side)
    return InstanceCrop(crop_image(image, center, side, size), crop_intrinsics(K, center, side, size), center, side)


def axis_target(
    crop: InstanceCrop, R: np.ndarray, t: np.ndarray, lengths: np.ndarray, size: int, line_width: float = DEFAULT_LINE_WIDTH
) -> np.ndarray:
    """The axis image (size x size x 3 in [0,1]) of the GT pose in this crop."""
    return render_axis_image(crop.K_patch, R, t, lengths, size, line_width)
