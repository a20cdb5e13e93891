"""Pinhole camera: intrinsics checks, projection, and square crops with their exact patch intrinsics.

Pixel convention (OpenCV and BOP): the centre of pixel (col, row) is at continuous coordinate (col, row).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import ConvexHull


class IntrinsicsError(ValueError):
    """Raised for a K that cannot be a pinhole camera (non-finite, non-positive focal length, bad shape)."""


def validate_intrinsics(K: np.ndarray) -> np.ndarray:
    """Return K as a float64 3x3 array, or raise IntrinsicsError saying what is wrong with it."""
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3):
        raise IntrinsicsError(f"K must be 3x3, got shape {K.shape}")
    if not np.all(np.isfinite(K)):
        raise IntrinsicsError("K has non-finite entries")
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise IntrinsicsError(f"K has non-positive focal length (fx={K[0, 0]}, fy={K[1, 1]})")
    if not np.allclose(K[2], (0.0, 0.0, 1.0)) or K[1, 0] != 0:
        raise IntrinsicsError("K must be upper triangular with last row (0, 0, 1)")
    return K


@dataclass(frozen=True)
class Camera:
    """Intrinsics plus image size; the unit every image-space computation is checked against."""

    K: np.ndarray
    width: int
    height: int

    def __post_init__(self) -> None:
        object.__setattr__(self, "K", validate_intrinsics(self.K))
        if self.width <= 0 or self.height <= 0:
            raise IntrinsicsError(f"image size must be positive, got {self.width}x{self.height}")

    def scaled(self, width: int, height: int) -> Camera:
        """The same camera for an image resized to width x height (pixel-centre convention kept)."""
        sx, sy = width / self.width, height / self.height
        A = np.array([[sx, 0.0, 0.5 * sx - 0.5], [0.0, sy, 0.5 * sy - 0.5], [0.0, 0.0, 1.0]])
        return Camera(A @ self.K, width, height)


def transform(R: np.ndarray, t: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Model points (N,3) into the camera frame."""
    return pts @ np.asarray(R).T + np.asarray(t).reshape(1, 3)


def project(K: np.ndarray, pts_cam: np.ndarray) -> np.ndarray:
    """Camera-frame points (N,3) to pixels (N,2). Points must lie in front of the camera."""
    uvw = pts_cam @ np.asarray(K).T
    return uvw[:, :2] / uvw[:, 2:3]


def projection_jacobian(K: np.ndarray, proj: np.ndarray, z: np.ndarray) -> np.ndarray:
    """d (image point) / d (camera-frame point) (N,2,3) at image points proj (N,2) of homogeneous depth z = (K p)_z
    (N,)."""
    return (K[None, :2, :] - proj[:, :, None] * K[None, 2:3, :]) / z[:, None, None]


def jacobian_times(K: np.ndarray, proj: np.ndarray, z: np.ndarray, d: np.ndarray) -> np.ndarray:
    """`projection_jacobian(K, proj, z) @ d` per row (N,2): how the image point moves as its camera-frame point moves
    along d (N,3); without forming the (N,2,3) Jacobians."""
    return (d @ K[:2].T - proj * (d @ K[2])[:, None]) / z[:, None]


def times_jacobian(K: np.ndarray, proj: np.ndarray, z: np.ndarray, n: np.ndarray) -> np.ndarray:
    """`n @ projection_jacobian(K, proj, z)` per row (N,3): the camera-frame gradient of the image point's component
    along n (N,2); without forming the (N,2,3) Jacobians."""
    return (n @ K[:2] - np.einsum("ni,ni->n", n, proj)[:, None] * K[2]) / z[:, None]


def hull_points(points: np.ndarray) -> np.ndarray:
    """The points on their convex hull (all of them where fewer than 4): a body's extent, and the box of its
    projection, from a fraction of its vertices."""
    points = np.asarray(points)
    return points[ConvexHull(points).vertices] if len(points) >= 4 else points


def project_model(K: np.ndarray, R: np.ndarray, t: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Model points (N,3) at pose (R, t) to pixels (N,2)."""
    return project(K, transform(R, t, pts))


def crop_transform(center: tuple[float, float], side: float, size: int) -> np.ndarray:
    """3x3 affine taking image pixels to patch pixels for a square of `side` pixels around `center`, resized to size x size.

    The square's outer edges map to the patch's outer edges, so patch pixel centres sample the square evenly.
    """
    if not side > 0:
        raise ValueError(f"crop side must be positive, got {side}")
    k = size / side
    x0 = center[0] - 0.5 * side
    y0 = center[1] - 0.5 * side
    # Continuous x0 maps to the patch's left edge, which lies half a pixel left of patch pixel 0's centre.
    return np.array([[k, 0.0, -x0 * k - 0.5], [0.0, k, -y0 * k - 0.5], [0.0, 0.0, 1.0]])


def crop_intrinsics(K: np.ndarray, center: tuple[float, float], side: float, size: int) -> np.ndarray:
    """Intrinsics K' of the size x size patch: a point projects through K then the crop exactly where K' puts it."""
    return crop_transform(center, side, size) @ np.asarray(K, dtype=np.float64)


def off_axis(K_patch: np.ndarray, size: int) -> float:
    """1 / cos θ - 1 for the angle θ between the optical axis and the ray through the centre of a size x size crop
    with intrinsics K_patch: how far off the axis the crop was cut (0 on it). An object there is drawn stretched
    along the radial direction by up to 1 / cos θ, which a network that sees the crop alone cannot tell apart from
    nearness."""
    ray = np.linalg.solve(np.asarray(K_patch, dtype=np.float64), [0.5 * (size - 1), 0.5 * (size - 1), 1.0])
    return float(np.linalg.norm(ray / ray[2]) - 1.0)


def crop_image(
    image: np.ndarray,
    center: tuple[float, float],
    side: float,
    size: int,
    interpolation: int = cv2.INTER_LINEAR,
    border_value: float | tuple[float, ...] = 0,
) -> np.ndarray:
    """Cut the square patch that `crop_intrinsics` describes; outside the image is filled with border_value."""
    A = crop_transform(center, side, size)
    return cv2.warpAffine(image, A[:2], (size, size), flags=interpolation, borderMode=cv2.BORDER_CONSTANT, borderValue=border_value)


def square_around_box(box_xywh: tuple[float, float, float, float], pad: float = 1.2) -> tuple[tuple[float, float], float]:
    """Centre and side of the square that holds an (x, y, w, h) box enlarged by `pad` (the crop a detector gives)."""
    x, y, w, h = box_xywh
    # (x, y, w, h) in BOP counts pixels: the box covers pixel centres x .. x + w - 1.
    center = (x + 0.5 * (w - 1), y + 0.5 * (h - 1))
    return center, max(w, h) * pad


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
