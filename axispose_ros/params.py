"""The node's parameters: each declared once (name, default, description, range), read into one typed
`NodeSettings`, and every change checked in one place, so that the node's code never spells a parameter twice.

Parameters read at start only shape what the node builds (its checkpoint, threads, subscriptions, health rules);
changing them later is refused. The others are read again for each frame, so `ros2 param set` takes effect on the
next one. `object_scales.<name>` exist once the checkpoint's object names are known (`declare_objects`).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, fields
from typing import Any

import torch
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult
from rclpy.exceptions import ParameterUninitializedException
from rclpy.node import Node
from rclpy.parameter import Parameter

from axispose_core.checkpoint import CheckpointError
from axispose_core.estimator import SHIPPED_ESTIMATOR
from axispose_core.tracking.mode import Mode
from axispose_core.tracking.poser import PoserSettings

DEFAULT_CHECKPOINT = SHIPPED_ESTIMATOR
OBJECT_SCALES = "object_scales."
MAX_OBJECT_SCALE = 10.0
"""Largest λ_O in m that `object_scales.<name>` accepts."""


@dataclass(frozen=True)
class Spec:
    """One parameter: its default (a Parameter.Type declares it without a value), description, range, and whether
    it is read at start only."""

    name: str
    default: Any
    description: str
    ints: tuple[int, int] | None = None
    floats: tuple[float, float] | None = None
    at_start: bool = False

    def descriptor(self) -> ParameterDescriptor:
        d = ParameterDescriptor(description=self.description)
        if self.ints is not None:
            d.integer_range = [IntegerRange(from_value=self.ints[0], to_value=self.ints[1], step=1)]
        if self.floats is not None:
            d.floating_point_range = [FloatingPointRange(from_value=self.floats[0], to_value=self.floats[1], step=0.0)]
        return d


SPECS = (
    Spec("checkpoint", str(DEFAULT_CHECKPOINT), "AxisPose estimator checkpoint (.safetensors)", at_start=True),
    Spec("ddim_steps", 3, "DDIM steps per estimate", ints=(1, 1000)),
    Spec("hypotheses", 1, "AGM samples per object; >= 2: their consensus, their scatter added to the covariance", ints=(1, 64)),
    Spec("guidance_scale", 0.0, "run-time geometric guidance (0: off)", floats=(0.0, 100.0)),
    Spec("object_scale", 0.0, "λ_O in m for every object (0: checkpoint's)", floats=(0.0, MAX_OBJECT_SCALE)),
    Spec("device", "cpu", "cpu, cuda or auto", at_start=True),
    Spec(
        "precision", "auto", "the AGM's arithmetic: float32, bfloat16, or auto (bfloat16 where the device has it natively)", at_start=True
    ),
    Spec("objects", Parameter.Type.STRING_ARRAY, "object names to look for, estimate and publish (empty: all)", at_start=True),
    Spec("use_rectified", False, "use P instead of K (images already rectified)", at_start=True),
    Spec("sync_slop", 0.02, "largest Image/CameraInfo stamp difference in s", floats=(0.0, 1.0), at_start=True),
    Spec("num_threads", 2, "torch CPU threads for inference", ints=(1, 64), at_start=True),
    Spec(
        "warmup_boxes",
        8,
        "at start, one blank-frame pass per box count up to this, so first frames skip setup; 0: none",
        ints=(0, 64),
        at_start=True,
    ),
    Spec(
        "batch_boxes",
        8,
        "most boxes posed in one AGM batch; a frame with more runs several, so memory stays bounded "
        "and the warm-up covers every batch shape",
        ints=(1, 64),
        at_start=True,
    ),
    Spec("roi_timeout", 1.0, "age in s after which an ROI is ignored", floats=(0.0, 3600.0)),
    Spec("refine", True, "refine each pose on the image's contours where the checkpoint carries a contour refiner"),
    Spec("score_threshold", 0.3, "least published score (the checkpoint's verifier's, else the localiser's)", floats=(0.0, 1.0)),
    Spec("marker_lifetime", 1.0, "lifetime of ~/markers in s (0: until replaced)", floats=(0.0, 3600.0)),
    Spec(
        "mode",
        "auto",
        "how frames are treated: stills (each on its own), video (tracks followed by their contours, the AGM for new and "
        "lost objects), video_odometry (video, each still object's views fused in camera_odom's fixed frame and the "
        "search in a process of its own), auto (picks from what arrives: camera_odom, whether the node keeps up, "
        "whether contours hold; /diagnostics says which and why)",
    ),
    Spec(
        "follow_passes",
        0,
        "video modes: correspondence passes per followed object: the last n of the checkpoint's following schedule "
        "(0: all): fewer make a frame cheaper and reach less far",
        ints=(0, 16),
    ),
    Spec("redetect_period", 5, "video modes: run the localiser on every n-th frame (and when a track is lost)", ints=(1, 1000)),
    Spec(
        "measure_every",
        1,
        "video modes: pose each track on every n-th frame, the tracks taking turns (all of them when "
        "the localiser runs); in between a track publishes its filter's prediction",
        ints=(1, 1000),
    ),
    Spec("track_timeout", 1.0, "video modes: seconds without an accepted pose after which a track ends", floats=(0.0, 3600.0)),
    Spec(
        "view_window",
        160,
        "in video_odometry, each still object's pose fused from its views over the last n frames (0: not fused)",
        ints=(0, 1000),
    ),
    Spec("latency_budget", 2.0, "median latency (s) over which /diagnostics warns; at start", floats=(0.01, 60.0), at_start=True),
)
AT_START = frozenset(s.name for s in SPECS if s.at_start)
REMOVED = {
    "tracking": "mode (video or video_odometry track; stills does not)",
    "follow": "mode (video and video_odometry follow tracks by their contours)",
    "background_detection": "mode video_odometry (the search in a process of its own)",
    "warm_strength": "nothing: warm-started samples lost accuracy",
    "warm_steps": "nothing: warm-started samples lost accuracy",
}
"""Parameters the node no longer has, and what replaced them: given at start, they stop it with that said."""


@dataclass(frozen=True)
class NodeSettings:
    """The node's parameters at one moment, typed (field names are the parameter names)."""

    checkpoint: str
    ddim_steps: int
    hypotheses: int
    guidance_scale: float
    object_scale: float
    device: str
    precision: str
    objects: tuple[str, ...]
    use_rectified: bool
    sync_slop: float
    num_threads: int
    warmup_boxes: int
    batch_boxes: int
    roi_timeout: float
    refine: bool
    score_threshold: float
    marker_lifetime: float
    mode: str
    follow_passes: int
    redetect_period: int
    measure_every: int
    track_timeout: float
    view_window: int
    latency_budget: float
    object_scales: Mapping[str, float] = field(default_factory=dict)
    """`object_scales.<name>` by name (0: not set)."""

    def scales(self, names: Mapping[int, str]) -> dict[int, float]:
        """λ_O by object id for the objects that have one: its own scale, else `object_scale`; the rest keep the
        checkpoint's."""
        out = {}
        for obj_id, name in names.items():
            own = self.object_scales.get(name, 0.0)
            if own > 0 or self.object_scale > 0:
                out[obj_id] = own if own > 0 else self.object_scale
        return out

    def poser(self, published: Mapping[int, str]) -> PoserSettings:
        """What the frame poser reads of these settings, λ_O resolved for the `published` objects (id -> name)."""
        names = {f.name for f in fields(PoserSettings)} - {"scales"}
        return PoserSettings(**{n: getattr(self, n) for n in names}, scales=self.scales(published))


def declare(node: Node) -> NodeSettings:
    """Declare every parameter of SPECS on `node` and read them; `device` auto becomes the device chosen. Raises
    ValueError (a device this torch lacks), CheckpointError (no checkpoint) or rclpy's ParameterException (out of
    range, wrong type) or ValueError (a removed parameter given, `REMOVED`): the node cannot start."""
    _refuse_removed(node)
    for spec in SPECS:
        node.declare_parameter(spec.name, spec.default, spec.descriptor())
    Mode.parse(node.get_parameter("mode").value)
    dev = node.get_parameter("device").value
    if dev not in ("cpu", "cuda", "auto"):
        raise ValueError(f"parameter 'device' must be cpu, cuda or auto, got {dev!r}")
    if dev == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"parameter 'device' is cuda, but this torch ({torch.__version__}) finds no CUDA device: use cpu or auto")
    if dev == "auto":
        node.set_parameters([Parameter("device", value="cuda" if torch.cuda.is_available() else "cpu")])
    settings = read(node)
    if not settings.checkpoint:
        raise CheckpointError("parameter 'checkpoint' is empty: pass -p checkpoint:=/path/to/estimator.safetensors")
    return settings


def _refuse_removed(node: Node) -> None:
    """A removed parameter given at start (`-p`, a params file) stops the node, naming what replaced it: a user's
    old `tracking: true` must not silently run another mode. Each is declared for the look only."""
    for name, replacement in REMOVED.items():
        node.declare_parameter(name, None, ParameterDescriptor(dynamic_typing=True))
        given = node.get_parameter(name).type_ != Parameter.Type.NOT_SET
        node.undeclare_parameter(name)
        if given:
            raise ValueError(f"parameter '{name}' was removed; use {replacement}")


def declare_objects(node: Node, settings: NodeSettings, names: Mapping[int, str]) -> dict[int, str]:
    """Check `objects` against the checkpoint's object `names` (id -> name) and declare `object_scales.<name>` for
    each; returns the objects to publish (id -> name). Raises ValueError for an object the checkpoint lacks."""
    unknown = sorted(set(settings.objects) - set(names.values()))
    if unknown:
        raise ValueError(f"parameter 'objects' names {unknown}, not in the checkpoint (it knows {sorted(names.values())})")
    for name in names.values():
        node.declare_parameter(OBJECT_SCALES + name, 0.0, ParameterDescriptor(description=f"λ_O of {name} in m (0: checkpoint's)"))
    return {i: n for i, n in names.items() if not settings.objects or n in settings.objects}


def read(node: Node, objects: Iterable[str] = ()) -> NodeSettings:
    """The current values of the parameters, with the `object_scales` of `objects` (names)."""
    values = {spec.name: _value(node, spec) for spec in SPECS}
    scales = {name: float(node.get_parameter(OBJECT_SCALES + name).value) for name in objects}
    return NodeSettings(**values, object_scales=scales)


def _value(node: Node, spec: Spec) -> Any:
    if not isinstance(spec.default, Parameter.Type):
        return type(spec.default)(node.get_parameter(spec.name).value)
    try:
        return tuple(node.get_parameter(spec.name).value or ())
    except ParameterUninitializedException:  # declared by type only: not given
        return ()


def check_change(params: list[Parameter]) -> SetParametersResult:
    """Refuse a change of a parameter read at start only, a `mode` that is none, or an `object_scales.<name>` that
    is not a length in [0, 10] m (rclpy checks the declared ranges of the others)."""
    for p in params:
        if p.name in AT_START:
            return SetParametersResult(successful=False, reason=f"'{p.name}' is read at start only; restart the node to change it")
        if p.name == "mode":
            try:
                Mode.parse(p.value)
            except ValueError as err:  # the same refusal as at start
                return SetParametersResult(successful=False, reason=str(err))
        if p.name.startswith(OBJECT_SCALES) and (p.type_ != Parameter.Type.DOUBLE or not 0.0 <= p.value <= MAX_OBJECT_SCALE):
            return SetParametersResult(successful=False, reason=f"'{p.name}' must be a length in [0, 10] m")
    return SetParametersResult(successful=True)
