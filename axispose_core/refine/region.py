"""The region modality: correspondence lines across the object's projected contour, the probability of where the
contour lies along each (from the colour histograms' per-pixel posteriors and a smoothed step function) (ICG's region
modality, Stoiber et al. 2022; written here, vectorised over lines); the Newton steps on their log-likelihood are
`passes.py`'s.

Pose perturbations are the dense fusion's (`tbm/dense.py`): R ← exp([ω]×) R, t ← t + δ, camera frame, state (ω, δ).
Along a line, positions are in segments of `scale` pixels, 0 at the line's centre, positive outwards.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from axispose_core.camera import projection_jacobian
from axispose_core.refine.config import RefineConfig
from axispose_core.refine.viewpoints import ViewpointModel

EPS = 1e-4
"""Per-colour posteriors are held inside [EPS, 1 - EPS]: one pixel's colour never settles a segment alone."""


@dataclass(frozen=True)
class StepFunction:
    """The smoothed step (foreground probability of the segments around a contour) and its derived constants."""

    foreground: np.ndarray
    """(F,): P(foreground) of segment i of the window, the contour between segments F/2 - 1 and F/2."""
    min_variance: float
    """Least variance (segments²) a line's contour distribution is given: what the step itself blurs."""

    @classmethod
    def of(cls, config: RefineConfig) -> StepFunction:
        x = np.arange(config.function_length) - (config.function_length - 1) / 2
        a, s = config.function_amplitude, config.function_slope
        f = 0.5 - a * (np.sign(x) if s == 0 else np.tanh(x / (2 * s)))
        laplace = 1 / (2 * np.arctanh(2 * a) ** 2)
        return cls(f, max(laplace, s))


@dataclass(frozen=True)
class LinePlacement:
    """One object's lines at one pose: model points (N,3), their camera-frame points (N,3), centres (N,2, px), unit
    outward normals (N,2), and how far the silhouette runs inwards and outwards from each (N,; px)."""

    model_points: np.ndarray
    camera_points: np.ndarray
    centres: np.ndarray
    normals: np.ndarray
    inside_px: np.ndarray
    outside_px: np.ndarray

    def usable(self, reach_px: float, min_run_px: float, shape: tuple[int, int]) -> np.ndarray:
        """(N,) bool: in front of the camera, the whole line (`reach_px` each side) inside an image of `shape`,
        and the silhouette's runs inwards and outwards at least `min_run_px` (a shorter one sees the far side)."""
        h, w = shape
        ends = self.centres[:, None, :] + np.array([-reach_px, reach_px])[None, :, None] * self.normals[:, None, :]
        on_image = np.all((ends[..., 0] >= 0) & (ends[..., 0] <= w - 1) & (ends[..., 1] >= 0) & (ends[..., 1] <= h - 1), axis=1)
        return (self.camera_points[:, 2] > 1e-6) & on_image & (np.minimum(self.inside_px, self.outside_px) >= min_run_px)


def place_lines(model: ViewpointModel, R: np.ndarray, t: np.ndarray, K: np.ndarray, count: int, scale: float = 1.0) -> LinePlacement:
    """`count` contour points of the view nearest the pose (R, t), projected through K, with their normals' image
    directions; `scale` sizes the model (an object of another size than its mesh)."""
    v = model.closest_view(R, t)
    pick = np.linspace(0, model.points.shape[1], count, endpoint=False).astype(int)
    X = model.points[v, pick] * scale
    p = X @ R.T + t
    safe = np.where(p[:, 2] > 1e-6, p[:, 2], 1.0)
    q = p @ K.T
    uv = q[:, :2] / np.where(q[:, 2:] > 1e-9, q[:, 2:], 1.0)
    # The normal's image direction: the projection's Jacobian applied to the 3D normal.
    n = np.einsum("nij,nj->ni", projection_jacobian(K, uv, safe), model.normals[v, pick] @ R.T)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    px_per_m = K[0, 0] * scale / safe
    return LinePlacement(X, p, uv, n, model.inside[v, pick] * px_per_m, model.outside[v, pick] * px_per_m)


def sample_posteriors(
    table: np.ndarray, bins: np.ndarray, centres: np.ndarray, normals: np.ndarray, offsets: np.ndarray, bilinear: bool = True,
    rows: np.ndarray | None = None,
) -> np.ndarray:  # fmt: skip
    """A per-colour `table` (P(foreground), or its log odds) looked up (N,L) at `offsets` (L,) pixels along each line
    (centres (N,2), normals (N,2)) in the `bins` image: bilinear in the pixels' values, or at the nearest pixel
    (positions clipped to the image). With `rows` (N,), `table` holds one row per object and each line reads its
    object's."""
    h, w = bins.shape
    q = centres[:, None, :] + offsets[None, :, None] * normals[:, None, :]
    flat = bins.reshape(-1)

    def at(k: np.ndarray) -> np.ndarray:
        return table[flat[k]] if rows is None else table[rows[:, None], flat[k]]

    if not bilinear:
        x = np.clip(np.rint(q[..., 0]), 0, w - 1).astype(np.int64)
        y = np.clip(np.rint(q[..., 1]), 0, h - 1).astype(np.int64)
        return at(y * w + x)
    x = np.clip(q[..., 0], 0, w - 1.001)
    y = np.clip(q[..., 1], 0, h - 1.001)
    x0, y0 = x.astype(np.int64), y.astype(np.int64)
    fx, fy = x - x0, y - y0
    i = y0 * w + x0
    return (1 - fy) * ((1 - fx) * at(i) + fx * at(i + 1)) + fy * ((1 - fx) * at(i + w) + fx * at(i + w + 1))


def log_odds(posterior: np.ndarray) -> np.ndarray:
    """log(p / (1 - p)) of P(foreground) per colour, p held inside [EPS, 1 - EPS]."""
    p = np.clip(posterior, EPS, 1 - EPS)
    return np.log(p) - np.log1p(-p)


@dataclass(frozen=True)
class Distributions:
    """Where each line's contour lies: the mean (N,) and variance (N,) of its distribution over the D places, in
    segments (0 at the line's centre)."""

    mean: np.ndarray
    variance: np.ndarray


def contour_distributions(odds: np.ndarray, scale: int, step: StepFunction, length: int) -> Distributions:
    """From the pixels' log odds of foreground (N, S·scale) along lines of S = F + D - 1 segments: each segment's
    probability of being foreground (the product of its pixels' odds), then for each of the D places the window of
    F segments around it scored against the step function (ICG's distribution and moments)."""
    n = len(odds)
    odds = odds.reshape(n, -1, scale).sum(axis=2)  # (N,S) segment log odds
    seg_f = 1 / (1 + np.exp(-odds))
    f = step.foreground
    windows = sliding_window_view(seg_f, len(f), axis=1)  # (N,D,F)
    log_p = np.log(windows * f + (1 - windows) * (1 - f)).sum(axis=2)
    log_p -= log_p.max(axis=1, keepdims=True)
    log_p -= np.log(np.exp(log_p).sum(axis=1, keepdims=True))
    p = np.exp(log_p)
    places = np.arange(length, dtype=np.float64)
    mean = p @ places
    variance = np.maximum(np.einsum("nd,nd->n", p, (places[None] - mean[:, None]) ** 2), step.min_variance)
    return Distributions(mean - (length - 1) / 2, variance)
