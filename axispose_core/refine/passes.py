"""One correspondence pass over a frame's objects together: every object's lines placed, its colours learned, the
contour's distribution found along each line and Newton steps taken, each stage one vectorised step over all the
objects' lines (each line knows its object), so five objects cost little more than one. An object's pass reads only
its own state and the frame's occlusion at the pass's start: the objects' passes do not depend on each other.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, fields
from itertools import pairwise

import cv2
import numpy as np

from axispose_core.camera import times_jacobian
from axispose_core.refine.config import RefineConfig
from axispose_core.refine.histograms import ColourHistograms
from axispose_core.refine.region import StepFunction, contour_distributions, log_odds, place_lines, sample_posteriors
from axispose_core.refine.viewpoints import ViewpointModel

NONE_NEARER = 255
"""No object's outline covers the pixel (a frame of 255 objects or more ranks them in int32, this value among them)."""


@dataclass
class RefineState:
    """One object's refinement under way."""

    start: object
    """The `refiner.Start` it began from."""
    model: ViewpointModel
    diameter: float
    R: np.ndarray
    t: np.ndarray
    precision: np.ndarray
    """The prior's (6,6) information in (ω, δ), zero without one."""
    histograms: ColourHistograms
    schedule: tuple[tuple[float, ...], tuple[float, ...]]
    """Its passes' scales and sigmas."""
    carried: bool = False
    """The histograms came from earlier frames: the passes read them, the last blends this frame's colours in."""
    table: np.ndarray | None = None
    """The histograms' P(foreground | colour), as last learned."""
    hessian: np.ndarray = field(default_factory=lambda: np.zeros((6, 6)))
    stepped: bool = False
    """A pass learned its colours and took Newton steps (False: every pass had too few lines)."""
    occlusion: Occlusion | None = None
    """The frame's objects in depth order at its last pass."""
    rank: int = 0
    """Its place in that order (0: the nearest)."""
    valid: float = 0.0
    reason: str = ""


@dataclass(frozen=True)
class Occlusion:
    """Per pixel, the depth rank of the nearest object whose outline covers it (`NONE_NEARER` where none does): an
    object of rank r is occluded where a rank below r is."""

    nearest: np.ndarray

    @classmethod
    def of(cls, states: Sequence[RefineState], K: np.ndarray, shape: tuple[int, int]) -> Occlusion:
        """The objects' outline polygons drawn from the farthest to the nearest, each at its rank, and each state
        told its rank."""
        order = sorted(range(len(states)), key=lambda i: states[i].t[2])
        nearest = np.full(shape, NONE_NEARER, dtype=np.uint8 if len(states) < NONE_NEARER else np.int32)
        for rank, i in reversed(list(enumerate(order))):
            s = states[i]
            s.rank = rank
            v = s.model.closest_view(s.R, s.t)
            p = s.model.points[v][s.model.outline[v]] * s.start.scale @ s.R.T + s.t
            if len(p) >= 3 and np.all(p[:, 2] > 1e-6):
                uv = p @ K.T
                poly = np.round(uv[:, :2] / uv[:, 2:] * 4).astype(np.int32)
                cv2.fillPoly(nearest, [poly], rank, lineType=cv2.LINE_8, shift=2)
        return cls(nearest)

    def occluded(self, x: np.ndarray, y: np.ndarray, rank: np.ndarray | int) -> np.ndarray:
        """Whether pixels (x, y) (in the image) are covered by an object nearer than `rank` (per pixel or one)."""
        return self.nearest[y, x] < rank


@dataclass
class _Batch:
    """The valid lines of the objects in a pass, object after object (`owner`: each line's object)."""

    owner: np.ndarray
    X: np.ndarray
    centres: np.ndarray
    normals: np.ndarray
    inside: np.ndarray
    outside: np.ndarray
    scale: np.ndarray
    mean: np.ndarray | None = None
    """Where each line's contour lies (segments), its variance and the line's weight: set once found."""
    variance: np.ndarray | None = None
    weight: np.ndarray | None = None

    def of(self, lines: np.ndarray) -> _Batch:
        """The batch's `lines` (a mask or indices)."""
        return _Batch(**{f.name: None if (v := getattr(self, f.name)) is None else v[lines] for f in fields(self)})

    def blocks(self) -> list[tuple[int, slice]]:
        """Each object with lines here and where its lines lie (they come object after object)."""
        bounds = np.flatnonzero(np.r_[True, self.owner[1:] != self.owner[:-1], True])
        return [(int(self.owner[a]), slice(a, b)) for a, b in pairwise(bounds)]


def correspondence_pass(states: Sequence[RefineState], k: int, bins: np.ndarray, K: np.ndarray, occlusion: Occlusion,
                        config: RefineConfig, step: StepFunction) -> None:  # fmt: skip
    """Pass k of each state's schedule: lines at its pose, colours learned there, the contour's distribution along
    each line, `newton_steps` Newton steps on the lines' log-likelihood with the prior. A state with too few valid
    lines stops (`few_lines`), one whose step diverges too (`run_away`)."""
    scales = [max(1, round(s.schedule[0][k] * K[0, 0] * s.diameter / s.t[2])) for s in states]
    batch = _place(states, scales, bins.shape, K, occlusion, config)
    if batch is None:
        return
    kept = np.array([i for i, _ in batch.blocks()])
    tables = _learn(states, kept, batch, bins, occlusion, config, k)
    batch.mean, batch.variance = np.empty(len(batch.owner)), np.empty(len(batch.owner))
    n_seg = config.function_length + config.distribution_length - 1
    groups = np.unique(batch.scale)
    for scale in groups:
        lines = batch.scale == scale if len(groups) > 1 else slice(None)
        offsets = (np.arange(n_seg * scale) + 0.5) - n_seg * scale / 2
        # Sub-pixel (bilinear) where a segment is a pixel; at coarser scales the nearest pixel, a quarter of the work.
        odds = sample_posteriors(tables, bins, batch.centres[lines], batch.normals[lines], offsets, bilinear=scale == 1,
                                 rows=batch.owner[lines])  # fmt: skip
        dist = contour_distributions(odds, int(scale), step, config.distribution_length)
        batch.mean[lines], batch.variance[lines] = dist.mean, dist.variance
    sigma = np.array([states[i].schedule[1][k] for i in batch.owner])
    batch.weight = step.min_variance * batch.scale**2 / sigma**2
    _newton(states, kept, batch, K, config)


def _place(states: Sequence[RefineState], scales: list[int], shape: tuple[int, int], K: np.ndarray, occlusion: Occlusion,
           config: RefineConfig) -> _Batch | None:  # fmt: skip
    """Each state's lines at its pose, kept where usable at its scale, on the image and not occluded; a state with
    fewer than `min_lines` stops here. None where no state has enough."""
    n_seg = config.function_length + config.distribution_length - 1
    h, w = shape
    placed = place_lines([(s.model, s.R, s.t, s.start.scale) for s in states], K, config.lines)
    owner = placed.owner
    scale = np.asarray(scales, dtype=np.float64)[owner]
    c = np.round(placed.centres).astype(np.int64)
    valid = placed.usable(n_seg * scale / 2, config.min_continuous * scale, shape)
    valid &= (c[:, 0] >= 0) & (c[:, 0] < w) & (c[:, 1] >= 0) & (c[:, 1] < h)
    ranks = np.array([s.rank for s in states])
    valid[valid] &= ~occlusion.occluded(c[valid, 0], c[valid, 1], ranks[owner[valid]])
    counts = np.bincount(owner[valid], minlength=len(states))
    for s, n in zip(states, counts, strict=True):
        s.occlusion, s.valid = occlusion, n / config.lines
        if n < config.min_lines:
            s.reason = "few_lines"
    valid &= (counts >= config.min_lines)[owner]
    if not valid.any():
        return None
    return _Batch(owner[valid], placed.model_points[valid], placed.centres[valid], placed.normals[valid], placed.inside_px[valid],
                  placed.outside_px[valid], scale[valid])  # fmt: skip


def _learn(states: Sequence[RefineState], kept: np.ndarray, batch: _Batch, bins: np.ndarray, occlusion: Occlusion,
           config: RefineConfig, k: int) -> np.ndarray:  # fmt: skip
    """The colours along each line into its object's histograms (inwards foreground, outwards background, each side
    from `histogram_margin` to its silhouette run or `histogram_reach`, unoccluded); each object's posterior table
    (rows: objects). An object followed with the colours of earlier frames (`carried`) learns once a frame, at its
    last pass, as ICG updates its histograms once a tracking step; its earlier passes read the carried colours."""
    learning = [i for i in kept if not states[i].carried or k == len(states[i].schedule[0]) - 1]
    n_bins = config.histogram_bins**3
    counts = _colour_counts(states, batch.of(np.isin(batch.owner, learning)), bins, occlusion, config) if learning else None
    tables = np.full((len(states), n_bins), 0.5)
    for i in kept:
        s = states[i]
        if i in learning:
            fresh = not s.stepped and not s.carried
            rate = 1.0 if fresh else config.histogram_rate
            s.histograms.learn_counts(counts[0][i], counts[1][i], rate)
            s.table = s.histograms.posterior()
        elif s.table is None:
            s.table = s.histograms.posterior()
        tables[i] = s.table
    return log_odds(tables)


def _colour_counts(states: Sequence[RefineState], batch: _Batch, bins: np.ndarray, occlusion: Occlusion,
                   config: RefineConfig) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Per object (rows), the counts of the colour bins along its lines inwards and outwards (`_learn`)."""
    m = config.histogram_margin
    steps = m + np.arange(int(np.ceil(config.histogram_reach)))
    h, w = bins.shape
    n_bins = config.histogram_bins**3
    ranks = np.array([s.rank for s in states])
    counts = []
    for sign, run in ((-1.0, batch.inside), (1.0, batch.outside)):
        along = sign * steps
        qx = np.round(batch.centres[:, :1] + along * batch.normals[:, :1]).astype(np.int64)
        qy = np.round(batch.centres[:, 1:] + along * batch.normals[:, 1:]).astype(np.int64)
        ok = (steps[None, :] <= np.minimum(run - m, config.histogram_reach)[:, None]) & (qx >= 0) & (qx < w) & (qy >= 0) & (qy < h)
        owner = np.broadcast_to(batch.owner[:, None], ok.shape)[ok]
        x, y = qx[ok], qy[ok]
        keep = ~occlusion.occluded(x, y, ranks[owner])
        counts.append(
            np.bincount(owner[keep] * n_bins + bins[y[keep], x[keep]], minlength=len(states) * n_bins).reshape(len(states), n_bins)
        )
    return counts[0], counts[1]


def _newton(states: Sequence[RefineState], kept: np.ndarray, batch: _Batch, K: np.ndarray, config: RefineConfig) -> None:
    """`newton_steps` steps of every kept state together: each line's contour offset pulled towards its
    distribution's mean with its variance, the prior towards the start; a state whose step diverges stops."""
    damping = np.diag(np.repeat(np.asarray(config.damping, dtype=float), 3))
    active = np.zeros(len(states), dtype=bool)
    active[kept] = True
    for i in kept:
        states[i].stepped = True
    for k in range(config.newton_steps):
        lines = active[batch.owner]
        if not lines.any():
            return
        R = np.stack([s.R for s in states])
        t = np.stack([s.t for s in states])
        g, H = _gradient_hessian(batch if lines.all() else batch.of(lines), R, t, K)
        moving = np.flatnonzero(active)
        prior = np.stack([states[i].precision for i in moving])
        e = np.stack([np.concatenate([rotvec(states[i].R @ states[i].start.R.T), states[i].t - states[i].start.t]) for i in moving])
        steps = np.linalg.solve(-H[moving] + prior + damping, (g[moving] - np.einsum("nij,nj->ni", prior, e))[..., None])[..., 0]
        for i, step in zip(moving, steps, strict=True):
            s = states[i]
            if k == 0:
                s.hessian = H[i]
            if not np.all(np.isfinite(step)):
                s.reason, active[i] = "run_away", False
                continue
            s.R = cv2.Rodrigues(step[:3])[0] @ s.R
            s.t = s.t + step[3:]
            if s.t[2] <= 0:
                s.reason, active[i] = "run_away", False


def _gradient_hessian(b: _Batch, R: np.ndarray, t: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per object, the log-likelihood gradient (n,6) and Gauss-Newton Hessian (n,6,6) in (ω, δ) of its lines in
    `b` at the objects' poses R (n,3,3), t (n,3)."""
    n, owner = len(R), b.owner
    blocks = b.blocks()
    p = np.empty_like(b.X)
    for i, lines in blocks:
        p[lines] = b.X[lines] @ R[i].T + t[i]
    q = p @ K.T
    z = q[:, 2]
    uv = q[:, :2] / z[:, None]
    a = times_jacobian(K, uv, z, b.normals) / b.scale[:, None]
    r = p - t[owner]  # R X: d(exp([ω]×) R X)/dω = -[R X]×, so the rotation's row is R X × a
    rx, ry, rz, ax, ay, az = r[:, 0], r[:, 1], r[:, 2], a[:, 0], a[:, 1], a[:, 2]
    J = np.column_stack([ry * az - rz * ay, rz * ax - rx * az, rx * ay - ry * ax, a])
    offset = np.einsum("ni,ni->n", uv - b.centres, b.normals) / b.scale
    g, H = np.zeros((n, 6)), np.zeros((n, 6, 6))
    pull, w = (b.weight * (b.mean - offset) / b.variance)[:, None] * J, (b.weight / b.variance)[:, None] * J
    for i, lines in blocks:
        g[i], H[i] = pull[lines].sum(axis=0), -(w[lines].T @ J[lines])
    return g, H


def rotvec(R: np.ndarray) -> np.ndarray:
    """The rotation vector of R (3,)."""
    return cv2.Rodrigues(np.ascontiguousarray(R))[0][:, 0]
