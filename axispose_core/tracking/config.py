"""A tracker's settings (`TrackingConfig`), a module of their own so that each part of the tracker (tracks,
following, views, search) reads them without importing the others."""

from __future__ import annotations

from dataclasses import dataclass, field

from axispose_core.tracking.filter import FilterConfig


@dataclass(frozen=True)
class TrackingConfig:
    """When the localiser runs, when tracks end, and the filter's model."""

    redetect_period: int = 5
    """Run the localiser on every n-th frame (1: on every frame)."""
    measure_every: int = 1
    """Crop and pose each track on every n-th frame, the tracks taking turns (by id), and every track where the
    localiser runs; in between a track's pose is its filter's prediction. Bounds the estimator's work per frame
    when many objects are tracked (1: every track on every frame)."""
    track_timeout: float = 1.0
    """Seconds without an accepted measurement after which a track ends."""
    max_misses: int = 3
    """Frames in a row without a pose (the estimator refused the crop) after which a track ends."""
    reinit_after: int = 3
    """Measurements in a row refused at the gate after which the track restarts at the latest one: the object
    really moved (or the filter had locked onto a wrong pose)."""
    match_iou: float = 0.3
    """A detection refreshes the track of its object whose predicted box it overlaps at least this much..."""
    match_distance: float = 0.5
    """...or whose predicted box's centre lies within this fraction of the larger box's diagonal of its own: a
    prediction that lags a fast camera still finds its object."""
    max_unseen: int = 4
    """Localiser runs in a row that do not find a track's object near it, after which the track ends: a track
    started by a false detection, or one whose object left."""
    same_distance: float = 0.1
    """A new detection's pose this close to an unmeasured track of its object (a fraction of the depth) is that
    track's measurement, not a new track: its predicted box had drifted off the detection's."""
    fallback_std: tuple[float, float] = (0.05, 0.35)
    """Measurement noise where the estimator gives no covariance: translation as a fraction of the depth, and
    rotation (rad)."""
    lost_agreement: float = 0.7
    """With contour following: a followed contour that separates the object's colours from its surroundings' less
    than this (0.5: not at all), or that the refiner kept, has lost its object: the AGM poses it from the
    localiser's box on the same frame where its contour had held for `redetect_period` frames, else it ends."""
    check_below: float = 0.85
    """With contour following: a followed track whose contour agrees less than this may hold a wrong pose (a
    contour held at the wrong side of an object): where the localiser finds it, the AGM poses that box too, one
    such track a frame, to check its pose (`follow.Following.check`)."""
    view_window: int = 0
    """With the camera's pose in a fixed frame (`Tracker.step(..., camera=...)`, e.g. from odometry): a track's published
    pose is fused from its object's measurements in that frame over the last n frames (by any of its tracks: an
    object found again brings its views back), brought to the current camera: positions weighted by their
    information (each view's covariance turned into the fixed frame: precise across its line of sight, loose along
    it, so views from other directions pin the depth), rotations by their chordal mean. Objects at rest under a
    moving camera are seen from other views, and a single view's error (depth most of all) differs from view to
    view. With following, an object no track holds is looked for where its views put it (where its contour is not
    found, again after `redetect_period` frames) (0: off)."""
    view_gate: tuple[float, float] = (0.05, 15.0)
    """A view this far from the track's measurement on this frame (translation as a fraction of its depth, rotation
    in degrees) is left out: another instance of the object, the object moved, a symmetric twin, a wrong pose."""
    filter: FilterConfig = field(default_factory=FilterConfig)
