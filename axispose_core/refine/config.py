"""The contour refiner's settings: one dataclass, saved in the estimator's checkpoint (`EstimatorConfig.refine`)."""

from __future__ import annotations

from dataclasses import dataclass, field

from axispose_core.refine.viewpoints import ViewpointSettings


@dataclass(frozen=True)
class RefineConfig:
    """How a pose is refined on the image's colours along the object's contour (region-based, after ICG: Stoiber et
    al. 2022). The defaults of the line model (`function_*`, `distribution_length`, `min_variance_*`, histogram
    bins) are ICG's; the schedule is set relative to the object's size in the image, since LM-O's objects span
    30-300 px where ICG's tracker expects a few hundred."""

    viewpoints: ViewpointSettings = field(default_factory=ViewpointSettings)
    function_length: int = 8
    """Segments the smoothed step function spans (even)."""
    distribution_length: int = 12
    """Places along a line where the contour may lie (even), in segments."""
    function_amplitude: float = 0.43
    """The step's height: a segment inside the object is foreground with 0.5 + amplitude."""
    function_slope: float = 0.5
    """The step's width (segments)."""
    min_continuous: float = 3.0
    """Least run (segments) of foreground inwards and background outwards that a line needs along the model's
    silhouette: a line shorter than its own step sees the object's far side."""
    histogram_bins: int = 16
    """Bins per colour channel (RGB): 2, 4, 8, 16, 32 or 64."""
    histogram_margin: float = 0.5
    """Pixels either side of the contour left out of the colour histograms (the contour's own pixels mix both)."""
    histogram_reach: float = 20.0
    """Most pixels along a line, each side, that feed the histograms."""
    histogram_rate: float = 0.2
    """Weight of the colours sampled at the current pose against those already learned: at each pass of a
    refinement (the first learns them from scratch), once a frame when following (ICG's learning rate)."""
    scales: tuple[float, ...] = (0.04, 0.02, 0.01, 0.0, 0.0, 0.0, 0.0)
    """Per correspondence pass: the segment length as a fraction of the object's projected diameter (at least one
    pixel): coarse passes reach far, fine ones place the contour to the pixel."""
    sigmas: tuple[float, ...] = (15.0, 5.0, 3.5, 1.5, 1.5, 1.5, 1.5)
    """Per pass: the user-set standard deviation (px) that weighs the lines against the regularisation (ICG's)."""
    track_scales: tuple[float, ...] = (0.01, 0.0, 0.0)
    """`scales` when following a tracked object from its predicted pose, with the colours it learned on the frames
    before (`ContourRefiner.refine(..., colours=...)`): a frame apart, the pose is near."""
    track_sigmas: tuple[float, ...] = (3.5, 1.5, 1.5)
    """`sigmas` when following."""
    newton_steps: int = 2
    """Gauss-Newton steps per correspondence pass, each pulling every line's contour offset towards the mean of its
    distribution (ICG's global step; its later steps along the distributions' local slopes overshoot on sharp
    distributions when no prior holds the pose)."""
    damping: tuple[float, float] = (1.0, 30.0)
    """Tikhonov terms on each step's rotation (1/rad²) and translation (1/m²) that keep a step finite where the
    lines and the prior leave a direction open. ICG's (1000, 30000) hold a tracker between frames; from a single
    image they stop a small object's depth short of its contour."""
    prior: bool = True
    """Hold the pose to the estimate it starts from with that estimate's covariance (the dense fusion's, plus the
    samples' scatter), so evidence the contour does not give (depth of a flat silhouette, spin of a round one)
    stays the network's."""
    lines: int = 200
    """Correspondence lines per object (at most the viewpoint model's points)."""
    min_lines: int = 20
    """Fewer valid lines than this at any pass keep the unrefined pose (the object hardly visible or off the image)."""
    min_agreement: float = 0.52
    """A refined contour that separates the learned colours no better than this (0.5: not at all, a uniform image)
    keeps the unrefined pose: the image gave no evidence."""
    max_jump: float = 21.1
    """Most squared Mahalanobis length of the refined pose's change in rotation, or in translation, under the
    starting covariance (χ²(3) at 0.9999): a larger jump is a run-away, and the unrefined pose is kept. Not for a
    followed start: its tracker's filter gates what it takes."""
    covariance_scale: tuple[float, float] = (3.15, 1.77)
    """Factors on the refined pose's translation and rotation variances (the inverse of the lines' Gauss-Newton
    Hessian and the prior's information) that make its errors' median squared Mahalanobis lengths χ²(3)'s (2.37)
    on rendered frames: measured on the synthetic validation set (lmo_val, 100 frames, the shipped estimator,
    GT crops; 7.46 and 4.19 with factors 1)."""
    min_size: float = 12.0
    """Objects whose projected diameter is smaller than this (px) are not refined."""

    def __post_init__(self) -> None:
        if self.function_length < 2 or self.function_length % 2 or self.distribution_length < 2 or self.distribution_length % 2:
            raise ValueError("refine: function_length and distribution_length must be even and at least 2")
        if self.histogram_bins not in (2, 4, 8, 16, 32, 64):
            raise ValueError(f"refine.histogram_bins must be 2, 4, 8, 16, 32 or 64, got {self.histogram_bins}")
        for scales, sigmas in ((self.scales, self.sigmas), (self.track_scales, self.track_sigmas)):
            if not scales or len(sigmas) != len(scales) or min(sigmas) <= 0 or min(scales) < 0:
                raise ValueError("refine: scales and sigmas need one non-negative scale and one positive sigma per pass")
        if not 0 < self.histogram_rate <= 1 or not 0 < self.function_amplitude < 0.5 or self.function_slope < 0:
            raise ValueError("refine: histogram_rate in (0, 1], function_amplitude in (0, 0.5) and function_slope >= 0")
        if self.lines < 8 or self.lines > self.viewpoints.points or self.newton_steps < 1 or self.min_lines < 1:
            raise ValueError(f"refine: 8 <= lines <= viewpoints.points ({self.viewpoints.points}), newton_steps >= 1, min_lines >= 1")
        if len(self.damping) != 2 or min(self.damping) <= 0 or len(self.covariance_scale) != 2 or min(self.covariance_scale) <= 0:
            raise ValueError("refine: damping and covariance_scale are two positive numbers each")
