"""The region modality: correspondence lines across the object's projected contour, the probability of where the
contour lies along each (from the colour histograms' per-pixel posteriors and a smoothed step function) (ICG's region
modality, Stoiber et al. 2022; written here, vectorised over lines); the Newton steps on their log-likelihood are
`passes.py`'s.

Pose perturbations are the dense fusion's (`tbm/dense.py`): R ← exp([ω]×) R, t ← t + δ, camera frame, state (ω, δ).
Along a line, positions are in segments of `scale` pixels, 0 at the line's centre, positive outwards.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from axispose_core.camera import jacobian_times
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
    """Objects' lines at their poses, object after object (`owner` (N,): each line's object): model points (N,3),
    their camera-frame points (N,3), centres (N,2, px), unit outward normals (N,2), and how far the silhouette runs
    inwards and outwards from each (N,; px)."""

    owner: np.ndarray
    model_points: np.ndarray
    camera_points: np.ndarray
    centres: np.ndarray
    normals: np.ndarray
    inside_px: np.ndarray
    outside_px: np.ndarray

    def usable(self, reach_px: float | np.ndarray, min_run_px: float | np.ndarray, shape: tuple[int, int]) -> np.ndarray:
        """(N,) bool: in front of the camera, the whole line (`reach_px` each side) inside an image of `shape`,
        and the silhouette's runs inwards and outwards at least `min_run_px` (a shorter one sees the far side);
        both one for all lines or one per line."""
        h, w = shape
        reach = np.asarray(reach_px, dtype=np.float64).reshape(-1, 1) * np.array([-1.0, 1.0])
        x, y = self.centres[:, :1] + reach * self.normals[:, :1], self.centres[:, 1:] + reach * self.normals[:, 1:]
        on_image = np.all((x >= 0) & (x <= w - 1) & (y >= 0) & (y <= h - 1), axis=1)
        return (self.camera_points[:, 2] > 1e-6) & on_image & (np.minimum(self.inside_px, self.outside_px) >= min_run_px)


def place_lines(objects: Sequence[tuple[ViewpointModel, np.ndarray, np.ndarray, float]], K: np.ndarray, count: int) -> LinePlacement:
    """For each object (its model, pose R, t, and scale: an object of another size than its mesh), `count` contour
    points of the view nearest its pose, projected through K, with their normals' image directions. The objects
    are placed together: only the choice of view is per object."""
    parts = []
    for model, R, t, scale in objects:
        v = model.closest_view(R, t)
        pick = _picks(model.points.shape[1], count)
        X = model.points[v, pick] * scale
        parts.append((X, X @ R.T + t, model.normals[v, pick] @ R.T, model.inside[v, pick] * scale, model.outside[v, pick] * scale))
    X, p, normals, inside, outside = (np.concatenate(c) if len(parts) > 1 else c[0] for c in zip(*parts, strict=True))
    safe = np.where(p[:, 2] > 1e-6, p[:, 2], 1.0)
    q = p @ K.T
    uv = q[:, :2] / np.where(q[:, 2:] > 1e-9, q[:, 2:], 1.0)
    # The normal's image direction: the projection's Jacobian applied to the 3D normal.
    n = jacobian_times(K, uv, safe, normals)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    px_per_m = K[0, 0] / safe
    owner = np.repeat(np.arange(len(parts)), count)
    return LinePlacement(owner, X, p, uv, n, inside * px_per_m, outside * px_per_m)


@functools.lru_cache(maxsize=8)
def _picks(points: int, count: int) -> np.ndarray:
    """`count` of a view's `points` contour points, evenly spread along it."""
    pick = np.linspace(0, points, count, endpoint=False).astype(int)
    pick.setflags(write=False)
    return pick


def sample_posteriors(
    table: np.ndarray, bins: np.ndarray, centres: np.ndarray, normals: np.ndarray, offsets: np.ndarray, bilinear: bool = True,
    rows: np.ndarray | None = None,
) -> np.ndarray:  # fmt: skip
    """A per-colour `table` (P(foreground), or its log odds) looked up (N,L) at `offsets` (L,) pixels along each line
    (centres (N,2), normals (N,2)) in the `bins` image: bilinear in the pixels' values, or at the nearest pixel
    (positions clipped to the image). With `rows` (N,), `table` holds one row per object and each line reads its
    object's."""
    h, w = bins.shape
    # x and y apart: (N,L) arrays broadcast far faster than an (N,L,2) one with its innermost axis of 2
    qx, qy = centres[:, :1] + offsets * normals[:, :1], centres[:, 1:] + offsets * normals[:, 1:]
    flat = bins.reshape(-1)
    if rows is None:
        values, base = table, 0
    else:  # one flat table, each line's row its offset into it: one index array per lookup, not two
        values, base = table.reshape(-1), (rows * table.shape[1])[:, None]

    def at(k: np.ndarray) -> np.ndarray:
        return values[flat[k] + base]

    if not bilinear:
        x = np.clip(np.rint(qx), 0, w - 1).astype(np.int64)
        y = np.clip(np.rint(qy), 0, h - 1).astype(np.int64)
        return at(y * w + x)
    x = np.clip(qx, 0, w - 1.001, out=qx)
    y = np.clip(qy, 0, h - 1.001, out=qy)
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
    odds = odds.reshape(n, -1, scale).sum(axis=2) if scale > 1 else odds  # (N,S) segment log odds
    seg_f = 1 / (1 + np.exp(-odds))
    f = step.foreground
    windows = sliding_window_view(seg_f, len(f), axis=1)  # (N,D,F)
    # P(segment's colour | the step's foreground f there) = w f + (1 - w)(1 - f) = (1 - f) + w (2f - 1)
    like = windows * (2 * f - 1)
    like += 1 - f
    log_p = np.log(like, out=like).sum(axis=2)
    p = np.exp(log_p - log_p.max(axis=1, keepdims=True))
    p /= p.sum(axis=1, keepdims=True)
    places = np.arange(length, dtype=np.float64)
    mean = p @ places
    variance = np.maximum(np.einsum("nd,nd->n", p, (places[None] - mean[:, None]) ** 2), step.min_variance)
    return Distributions(mean - (length - 1) / 2, variance)
