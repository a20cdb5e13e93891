"""The axis image: the object's three model axes drawn as 2D segments, one per colour channel.

Convention (docs/axis_convention.md): the segments start at the projected model-frame origin and end at the
projections of ``L_X e_x``, ``L_Y e_y`` and ``L_Z e_z`` with ``(L_X, L_Y, L_Z) = λ_O (1, r_B, r_C)`` metres.
Channel 0/1/2 (R/G/B) holds axis X/Y/Z. Values lie in [0, 1] (1 on the line); channels are independent, so
crossing axes never hide each other.

Two renderers share one line profile so that what the network learns (NumPy targets) is what guidance
differentiates (torch): intensity ``clip(w/2 + 1/2 - d, 0, 1)`` of the distance ``d`` from the pixel centre to
the segment, a box-filtered line of width ``w``; the torch version swaps the clip for a sigmoid of the same
argument so that gradients reach keypoints even off the line.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch

from axispose_core.camera import transform

DEFAULT_LINE_WIDTH = 3.0
"""Line width in pixels of the axis image, at every image size."""


@dataclass(frozen=True)
class AxisSpec:
    """Drawn axis lengths of one object: λ_O (metres) and the paper's ratios r_B, r_C."""

    scale: float
    ratio_b: float = 1.0
    ratio_c: float = 1.0

    def __post_init__(self) -> None:
        if not (np.isfinite(self.scale) and self.scale > 0):
            raise ValueError(f"object scale λ_O must be a positive length in metres, got {self.scale}")
        if not (self.ratio_b > 0 and self.ratio_c > 0):
            raise ValueError(f"length ratios must be positive, got r_B={self.ratio_b}, r_C={self.ratio_c}")

    @property
    def lengths(self) -> np.ndarray:
        """(L_X, L_Y, L_Z) in metres."""
        return self.scale * np.array([1.0, self.ratio_b, self.ratio_c])

    @classmethod
    def from_diameter(cls, diameter: float, ratio_b: float = 1.0, ratio_c: float = 1.0) -> AxisSpec:
        """The default λ_O: half the model diameter, so the axes reach about the object's silhouette."""
        return cls(0.5 * diameter, ratio_b, ratio_c)


def axis_points(lengths: np.ndarray) -> np.ndarray:
    """Model-frame origin and the three axis endpoints, (4,3) in metres."""
    pts = np.zeros((4, 3))
    pts[1:] = np.diag(np.asarray(lengths, dtype=np.float64))
    return pts


def axis_keypoints(K: np.ndarray, R: np.ndarray, t: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """Projected origin and endpoints (4,2) in pixels; raises if any of them is not in front of the camera."""
    cam = transform(R, t, axis_points(lengths))
    if np.any(cam[:, 2] <= 1e-9):
        raise ValueError("axis origin or endpoint lies behind the camera")
    uvw = cam @ np.asarray(K).T
    return uvw[:, :2] / uvw[:, 2:3]


def _segment_distance_np(px: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    ab = b - a
    denom = float(ab @ ab)
    if denom < 1e-12:
        return np.linalg.norm(px - a, axis=-1)
    s = np.clip(((px - a) @ ab) / denom, 0.0, 1.0)
    return np.linalg.norm(px - (a + s[..., None] * ab), axis=-1)


def render_axis_keypoints(keypoints: np.ndarray, size: int | tuple[int, int], line_width: float = DEFAULT_LINE_WIDTH) -> np.ndarray:
    """Draw (origin, end X, end Y, end Z) pixel keypoints as an HxWx3 float32 axis image."""
    h, w = (size, size) if isinstance(size, int) else size
    kp = np.asarray(keypoints, dtype=np.float64)
    if kp.shape != (4, 2) or not np.all(np.isfinite(kp)):
        raise ValueError(f"keypoints must be finite (4,2), got {kp.shape}")
    img = np.zeros((h, w, 3), dtype=np.float32)
    reach = 0.5 * line_width + 0.5  # beyond this distance from the segment the profile is 0
    for c in range(3):
        a, b = kp[0], kp[c + 1]
        lo = np.maximum(np.ceil(np.minimum(a, b) - reach), 0).astype(int)
        hi = np.minimum(np.floor(np.maximum(a, b) + reach), (w - 1, h - 1)).astype(int)
        if np.any(hi < lo):
            continue
        ys, xs = np.mgrid[lo[1] : hi[1] + 1, lo[0] : hi[0] + 1].astype(np.float64)
        d = _segment_distance_np(np.stack([xs, ys], axis=-1), a, b)
        img[lo[1] : hi[1] + 1, lo[0] : hi[0] + 1, c] = np.clip(0.5 * line_width + 0.5 - d, 0.0, 1.0)
    return img


def render_axis_image(
    K: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    lengths: np.ndarray,
    size: int | tuple[int, int],
    line_width: float = DEFAULT_LINE_WIDTH,
) -> np.ndarray:
    """Axis image (HxWx3 float32 in [0,1]) of an object at pose (R, t) seen through K."""
    return render_axis_keypoints(axis_keypoints(K, R, t, lengths), size, line_width)


def axis_keypoints_torch(K: torch.Tensor, R: torch.Tensor, t: torch.Tensor, lengths: torch.Tensor) -> torch.Tensor:
    """Batched, differentiable `axis_keypoints`: K (B,3,3), R (B,3,3), t (B,3), lengths (B,3) -> (B,4,2).

    Depth is clamped to 1 mm so that a pose driven behind the camera by an optimiser yields finite values.
    """
    pts = torch.zeros(*lengths.shape[:-1], 4, 3, dtype=lengths.dtype, device=lengths.device)
    pts[..., 1:, :] = torch.diag_embed(lengths)
    cam = pts @ R.transpose(-1, -2) + t.unsqueeze(-2)
    uvw = cam @ K.transpose(-1, -2)
    return uvw[..., :2] / uvw[..., 2:3].clamp_min(1e-3)


def render_axis_keypoints_torch(
    keypoints: torch.Tensor, size: int | tuple[int, int], line_width: float = DEFAULT_LINE_WIDTH, softness: float = 0.35
) -> torch.Tensor:
    """Differentiable axis image (B,3,H,W) from keypoints (B,4,2) with a sigmoid line profile.

    `softness` (pixels) is the sigmoid's temperature; at 0.35 the profile matches the NumPy box-filtered line
    to within a few percent at every distance, while gradients still reach pixels a couple of pixels away.
    """
    h, w = (size, size) if isinstance(size, int) else size
    dev, dt = keypoints.device, keypoints.dtype
    ys = torch.arange(h, device=dev, dtype=dt).view(1, 1, h, 1)
    xs = torch.arange(w, device=dev, dtype=dt).view(1, 1, 1, w)
    a = keypoints[:, 0:1, :]  # (B,1,2)
    ab = keypoints[:, 1:4, :] - a  # (B,3,2)
    ax, ay = a[..., 0, None, None], a[..., 1, None, None]
    bx, by = ab[..., 0, None, None], ab[..., 1, None, None]
    denom = (bx * bx + by * by).clamp_min(1e-9)
    s = (((xs - ax) * bx + (ys - ay) * by) / denom).clamp(0.0, 1.0)
    dx = xs - (ax + s * bx)
    dy = ys - (ay + s * by)
    d = torch.sqrt(dx * dx + dy * dy + 1e-12)
    return torch.sigmoid((0.5 * line_width - d) / softness)


AXIS_BGR = ((0, 0, 255), (0, 255, 0), (255, 0, 0))  # X red, Y green, Z blue


def draw_axes(image_bgr: np.ndarray, K: np.ndarray, R: np.ndarray, t: np.ndarray, lengths: np.ndarray, thickness: int = 2) -> None:
    """Draw the axis convention's three segments onto a BGR image in place."""
    try:
        kp = axis_keypoints(K, R, t, lengths)
    except ValueError:
        return
    o = tuple(round(v) for v in kp[0])
    for k in range(3):
        cv2.line(image_bgr, o, tuple(round(v) for v in kp[k + 1]), AXIS_BGR[k], thickness, cv2.LINE_AA)
