"""What the estimator returns: a box's pose with its uncertainty and the refiner's verdict (`PoseEstimate`), and a
frame's objects found by the localiser with their poses (`Found`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from axispose_core.localiser.decode import Detection
from axispose_core.refine.histograms import ColourHistograms


@dataclass
class PoseEstimate:
    """One box's pose (model to camera, metres) and what the estimator knows of it."""

    obj_id: int
    R: np.ndarray
    t: np.ndarray
    ok: bool
    reason: str
    axis_image: np.ndarray
    """The generated axis image (S,S,3) in [0,1], for debug overlays."""
    K_patch: np.ndarray
    center: tuple[float, float]
    side: float
    samples: int = 1
    """AGM samples drawn for this box (`hypotheses`)."""
    samples_ok: int = 1
    """Samples that gave a pose; with two or more, the spread is filled in."""
    spread_deg: float = float("nan")
    spread_m: float = float("nan")
    covariance: np.ndarray | None = None
    """(6, 6) pose covariance (x, y, z, rx, ry, rz; camera frame; m², rad²): the dense fusion's (`FusedPose`) plus
    the samples' scatter about their consensus (consensus.py); without the fusion the scatter alone, with a floor
    (None for a single sample)."""
    fit_covariance: np.ndarray | None = None
    """(6, 6) the dense fusion's own covariance, without the samples' scatter: how well the crop's dense points fit
    the object's model, alike at any number of samples (what the detection verifier reads; None without the
    fusion)."""
    head_depth: float = float("nan")
    """The encoder's depth for this crop (m, linear in λ_O); t already fuses it with the TBM's (head_depth_weight)
    and with the dense points (dense_fusion)."""
    refined: bool = False
    """The contour refiner moved this pose (R, t and covariance are its); False where it did not run or kept the
    pose (`refine_kept`)."""
    refine_kept: str = ""
    """Why the refiner kept the unrefined pose (`refine.refiner.KEPT_REASONS`); empty where it refined or did not
    run."""
    contour_lines: float = float("nan")
    """Fraction of the object's contour lines the refiner could use at the end (NaN where it did not run)."""
    contour_agreement: float = float("nan")
    """How well the refined contour separates the object's colours from its surroundings' (0.5: not at all, 1:
    fully; NaN where the refiner did not refine): evidence for a detection verifier."""
    unrefined: tuple[np.ndarray, np.ndarray] | None = None
    """(R, t) as the fusion gave it, where the refiner saw this pose: what `axispose eval` scores the refinement
    against."""
    colours: ColourHistograms | None = None
    """The object's and its surroundings' colours the refiner learned here: what a tracker carries to the next
    frame (`follow`)."""
    contour_information: np.ndarray | None = None
    """(6,6) what the contour alone says of a followed pose (`Refinement.information`): its tracker, whose
    prediction was the refiner's prior, folds the pose in as that evidence, not the prior twice."""


@dataclass(frozen=True)
class Found:
    """A frame's objects found by the localiser (`Estimator.find`), each with its pose: `detections` carry the
    published score (the verifier's probability where the checkpoint has one, else the localiser's); `dropped`
    counts the detections posed and then refused by the verifier."""

    detections: list[Detection]
    poses: list[PoseEstimate]
    dropped: int = 0
