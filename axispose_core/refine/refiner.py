"""Region-based refinement of a frame's poses on the image itself: each object's contour is moved until it
separates the colours the image shows inside it from those around it (after ICG's tracker, Stoiber et al. 2022).

Per frame: the colour-bin image once; then passes from coarse to fine line scales, each taking the frame's objects
together (`passes.py`): per object, colour histograms learned at its current pose, correspondence lines across the
contour of the nearest view of its viewpoint model, where along each line the contour lies, and Newton steps on
their log-likelihood with the starting pose (and its covariance) as a prior. The frame's objects mask each other's
lines in their depth order. A pose that cannot be refined (too small, off the image, too few lines, a jump its
covariance does not allow) is kept as it came, with the reason. A tracked object brings the colours it learned on
earlier frames and is followed on a short schedule from its predicted pose.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from axispose_core.refine.config import RefineConfig
from axispose_core.refine.histograms import ColourHistograms, colour_bins
from axispose_core.refine.passes import Occlusion, RefineState, correspondence_pass, rotvec
from axispose_core.refine.region import StepFunction, place_lines, sample_posteriors
from axispose_core.refine.viewpoints import ViewpointModel, viewpoint_model

KEPT_REASONS = ("invalid", "small", "few_lines", "no_contrast", "run_away")
"""Why a pose is kept unrefined: not a finite pose in front of the camera; smaller than `min_size`; fewer valid lines
than `min_lines`; a contour that separates no colours (`min_agreement`); a jump its covariance does not allow
(`max_jump`)."""
_ORDER = [3, 4, 5, 0, 1, 2]
"""(ω, δ) <-> (x, y, z, rx, ry, rz): the refiner's state and geometry_msgs' covariance order swap halves."""


@dataclass(frozen=True)
class Start:
    """A pose to refine: object, rotation, translation (m) and its (6,6) covariance in geometry_msgs' order (None:
    no prior); `scale`, the object's size against its mesh's (a run-time λ_O over the checkpoint's)."""

    obj_id: int
    R: np.ndarray
    t: np.ndarray
    covariance: np.ndarray | None = None
    scale: float = 1.0


@dataclass(frozen=True)
class Refinement:
    """A refined pose, or the starting one kept (`refined` False, `reason` one of KEPT_REASONS). `lines`: the
    fraction of the object's lines usable at the end; `agreement`: how well its contour separates the learned
    colours there (the mean over lines of P(foreground) inside and P(background) outside, 0.5 for no contrast)."""

    R: np.ndarray
    t: np.ndarray
    covariance: np.ndarray | None
    refined: bool
    reason: str = ""
    lines: float = 0.0
    agreement: float = float("nan")
    colours: ColourHistograms | None = None
    """The object's and its surroundings' colours as learned here (None where no pass ran): what a tracker carries
    to the next frame."""
    information: np.ndarray | None = None
    """(6,6) what the lines alone say of the refined pose (the inverse covariance without the prior, scaled as
    `covariance`; geometry_msgs' order): lets a tracker whose prediction was the prior fold the pose in once."""


def _finite_pose(s: Start) -> bool:
    R, t = np.asarray(s.R, dtype=float), np.asarray(s.t, dtype=float)
    return R.shape == (3, 3) and t.shape == (3,) and bool(np.all(np.isfinite(R)) and np.all(np.isfinite(t))) and t[2] > 0


def _information(covariance: np.ndarray | None) -> np.ndarray | None:
    """The covariance's inverse in (ω, δ) order, or None where it is missing or not positive definite."""
    if covariance is None:
        return None
    C = np.asarray(covariance, dtype=float)
    if C.shape != (6, 6) or not np.all(np.isfinite(C)):
        return None
    C = C[np.ix_(_ORDER, _ORDER)]
    try:
        np.linalg.cholesky(C)
        return np.linalg.inv(C)
    except np.linalg.LinAlgError:
        return None


class ContourRefiner:
    """Refines poses of the objects whose meshes it holds; viewpoint models are built on first use (or `prepare`)."""

    def __init__(self, config: RefineConfig, meshes: Mapping[int, tuple[np.ndarray, np.ndarray]]) -> None:
        self.config = config
        self.meshes = {k: (np.asarray(v, dtype=np.float64), np.asarray(f, dtype=np.int64)) for k, (v, f) in meshes.items()}
        self.diameters = {k: 2.0 * float(np.linalg.norm(v, axis=1).max()) for k, (v, _) in self.meshes.items()}
        self.step = StepFunction.of(config)
        self._models: dict[int, ViewpointModel] = {}

    def model(self, obj_id: int) -> ViewpointModel:
        if obj_id not in self._models:
            self._models[obj_id] = viewpoint_model(*self.meshes[obj_id], self.config.viewpoints)
        return self._models[obj_id]

    def prepare(self, obj_ids: Sequence[int] | None = None) -> None:
        """Build (or load from the cache) the viewpoint models of `obj_ids` (None: all) now, not on first use."""
        for obj_id in self.meshes if obj_ids is None else obj_ids:
            self.model(obj_id)

    def refine(
        self, image_rgb: np.ndarray, K: np.ndarray, starts: Sequence[Start], colours: Sequence[ColourHistograms | None] | None = None,
        passes: int = 0,
    ) -> list[Refinement]:  # fmt: skip
        """Each start refined on the image (H,W,3 uint8 RGB) seen through K; one Refinement per start, in order.
        `colours`, per start, what it learned on earlier frames (a track's, `Refinement.colours`): such a start is
        followed (`track_scales`, a short schedule from a near pose; with `passes`, its last `passes` only) and its
        colours blended with this frame's; the others take the whole schedule (`scales`)."""
        if passes < 0:
            raise ValueError(f"passes must be >= 0, got {passes}")
        cfg = self.config
        colours = list(colours) if colours is not None else [None] * len(starts)
        if len(colours) != len(starts):
            raise ValueError(f"{len(colours)} colour histograms for {len(starts)} starts")
        K = np.asarray(K, dtype=np.float64)
        shape = image_rgb.shape[:2]
        bins = colour_bins(image_rgb, cfg.histogram_bins)
        states: list[RefineState | None] = []
        kept: dict[int, str] = {}
        for i, s in enumerate(starts):
            if s.obj_id not in self.meshes:
                raise ValueError(f"the refiner has no mesh of object {s.obj_id} (it has {sorted(self.meshes)})")
            if not _finite_pose(s):
                kept[i] = "invalid"
            elif K[0, 0] * self.diameters[s.obj_id] * s.scale / s.t[2] < cfg.min_size:
                kept[i] = "small"
            states.append(None if i in kept else self._state(s, colours[i], passes))
        for k in range(max(len(cfg.scales), len(cfg.track_scales))):
            live = [s for s in states if s is not None and not s.reason and k < len(s.schedule[0])]
            if live:
                correspondence_pass(live, k, bins, K, Occlusion.of(live, K, shape), cfg, self.step)
        agreements = self._agreements([s for s in states if s is not None and s.stepped and not s.reason], bins, K)
        pairs = enumerate(zip(starts, states, strict=True))
        return [self._finish(start, s, agreements.get(id(s), 0.5), kept.get(i, "")) for i, (start, s) in pairs]

    def _state(self, s: Start, colours: ColourHistograms | None, passes: int = 0) -> RefineState:
        info = _information(s.covariance) if self.config.prior else None
        cfg = self.config
        learned = colours.copy() if colours is not None else ColourHistograms.empty(cfg.histogram_bins)
        schedule = (cfg.track_scales[-passes:], cfg.track_sigmas[-passes:]) if colours is not None else (cfg.scales, cfg.sigmas)
        return RefineState(s, self.model(s.obj_id), self.diameters[s.obj_id] * s.scale, np.asarray(s.R, float), np.asarray(s.t, float),
                      np.zeros((6, 6)) if info is None else info, learned, schedule, carried=colours is not None)  # fmt: skip

    def _finish(self, start: Start, s: RefineState | None, agreement: float, reason: str) -> Refinement:
        """The refined pose with its covariance and `agreement`, or the start kept with the reason."""
        if s is None or s.reason or not s.stepped:
            return Refinement(start.R, start.t, start.covariance, False, reason or (s.reason if s else "") or "few_lines",
                              s.valid if s else 0.0, colours=s.histograms if s and s.stepped else None)  # fmt: skip
        cfg = self.config
        H = -s.hessian + s.precision
        jump = (rotvec(s.R @ s.start.R.T), s.t - s.start.t)
        if _information(start.covariance) is not None and cfg.max_jump > 0 and not s.carried:  # a tracker gates its own
            C = np.asarray(start.covariance, dtype=float)
            d2 = (float(jump[1] @ np.linalg.solve(C[:3, :3], jump[1])), float(jump[0] @ np.linalg.solve(C[3:, 3:], jump[0])))
            if max(d2) > cfg.max_jump:
                return Refinement(start.R, start.t, start.covariance, False, "run_away", s.valid, colours=s.histograms)
        if agreement < cfg.min_agreement:
            return Refinement(start.R, start.t, start.covariance, False, "no_contrast", s.valid, agreement, s.histograms)
        d = np.sqrt(np.repeat(cfg.covariance_scale, 3))
        try:
            cov = np.linalg.inv(H + np.eye(6) * 1e-9)[np.ix_(_ORDER, _ORDER)]
            cov = (cov + cov.T) / 2 * np.outer(d, d)
        except np.linalg.LinAlgError:
            cov = start.covariance
        information = -s.hessian[np.ix_(_ORDER, _ORDER)] / np.outer(d, d)
        return Refinement(s.R, s.t, cov, True, "", s.valid, agreement, s.histograms, (information + information.T) / 2)

    def _agreements(self, states: list[RefineState], bins: np.ndarray, K: np.ndarray) -> dict[int, float]:
        """Per state (by id), the mean over its unoccluded lines at its final pose of P(foreground) in the four pixels
        inside the contour and P(background) in the four outside it, under its learned colours (0.5: no contrast,
        or no line left); the states' lines taken together."""
        if not states:
            return {}
        offsets = np.arange(-3.5, 4.0, 1.0)
        placed = place_lines([(s.model, s.R, s.t, s.start.scale) for s in states], K, self.config.lines)
        c = np.round(placed.centres).astype(np.int64)
        valid = placed.usable(4.0, 4.0, bins.shape)
        for k, s in enumerate(states):  # each against the occlusion of its own last pass
            mine = valid & (placed.owner == k)
            valid[mine] = ~s.occlusion.occluded(c[mine, 0], c[mine, 1], s.rank)
        owner = placed.owner[valid]
        tables = np.stack([s.table for s in states])
        pf = sample_posteriors(tables, bins, placed.centres[valid], placed.normals[valid], offsets, rows=owner)
        inner, outer = pf[:, offsets < 0].mean(axis=1), 1 - pf[:, offsets > 0].mean(axis=1)
        lines = np.bincount(owner, minlength=len(states))
        total = np.bincount(owner, weights=(inner + outer) / 2, minlength=len(states))
        return {id(s): float(total[k] / lines[k]) if lines[k] else 0.5 for k, s in enumerate(states)}
