"""`axispose replay`: the real node, in-process, on a recorded bag; its outputs recorded; metrics against GT.

A private rclpy Context holds the node under test and a player node. The player publishes the bag's camera
stream (and its `/roi/<name>` boxes, onto the node's `~/roi/<name>`; its camera odometry, where it has one, onto
the node's `camera_odom`) on the bag's topic names, which the node subscribes by remapping; its image and
CameraInfo subscriptions are switched to reliable delivery through the node's own QoS-override parameters, so
that DDS does not discard large images in a burst. Two pacings:
- lock-step (as fast as possible, the default): each image is published once the node is idle, so every frame
  is processed and the metrics see all of them;
- `rate` R: the bag's own timing scaled by R, as a live camera would deliver it; frames the node cannot keep up
  with are dropped by its latest-frame-wins slot and counted.
Every message the node publishes is written into the output bag (stamped by its header). When the bag holds
`/gt/<name>` poses and `/gt/models/<name>` points (as `make_bag` writes them), the report has the same metrics
as `axispose eval` plus latency and the node's counters. What is read from the bag is `replay_bag.py`'s, the scores
`replay_report.py`'s.
"""

from __future__ import annotations

import time
from collections import defaultdict
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseArray, PoseStamped, PoseWithCovarianceStamped
from nav_msgs.msg import Odometry
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message
from rosbags.rosbag2 import Writer
from sensor_msgs.msg import CameraInfo, Image, RegionOfInterest
from tqdm import tqdm
from visualization_msgs.msg import MarkerArray

import axispose_msgs
from axispose_msgs.msg import DetectionArray
from axispose_ros.bag import FORMATS, ROI_PREFIX, TYPESTORE, BagError, bag_topics, camera_topics, read_bag, register_types
from axispose_ros.conversions import cdr_stamp, image_to_rgb, stamp_ns, stamp_seconds
from axispose_ros.node import AxisPoseNode
from axispose_ros.replay_bag import Truth, by_stamp, pose_rt, ros_message
from axispose_ros.replay_report import replay_report

# How long one spin of the replay's executor may wait for an event before it re-checks its condition. The node's
# inference runs on its own thread in this process, and a fast spin takes CPU from it (and lengthens the frame
# latency being measured: docs/BENCHMARKS.md, Latency), so conditions that no ROS event signals (a count, a
# clock) are polled no faster than this.
POLL_S = 0.05


def _msg_folder() -> Path:
    """share/axispose_msgs/msg of the installed axispose_msgs: from the ament index when a ROS environment is
    sourced, else beside the Python package (the prefix it was installed into, e.g. `make test`'s venv)."""
    try:
        from ament_index_python.packages import get_package_share_directory

        return Path(get_package_share_directory("axispose_msgs")) / "msg"
    except (LookupError, OSError):  # not in the index, or no AMENT_PREFIX_PATH
        pass
    for parent in Path(axispose_msgs.__file__).resolve().parents:
        if (parent / "share" / "axispose_msgs" / "msg").is_dir():
            return parent / "share" / "axispose_msgs" / "msg"
    raise BagError("axispose_msgs is importable but its share/axispose_msgs/msg folder was not found: reinstall it")


def register_axispose_msgs() -> None:
    """Teach the bag typestore axispose_msgs (rosbags knows only the standard messages), so that the node's
    ~/detections can be written into a bag; idempotent."""
    if "axispose_msgs/msg/DetectionArray" not in TYPESTORE.types:
        register_types({f"axispose_msgs/msg/{p.stem}": p.read_text() for p in sorted(_msg_folder().glob("*.msg"))})


@dataclass(frozen=True)
class ReplayOptions:
    """How `replay` plays a bag to the node and records it (module docstring); checked when made."""

    rate: float | None = None
    """Play at R x the recorded speed (the node drops what it cannot keep up with); None: lock-step."""
    params: Mapping[str, object] = field(default_factory=dict)
    """The node's parameters by name (its checkpoint is `replay`'s own argument)."""
    image_topic: str | None = None
    """The bag's Image topic; None: its only one."""
    info_topic: str | None = None
    """The bag's CameraInfo topic; None: its only one."""
    odom_topic: str | None = None
    """The bag's Odometry topic (the camera's pose) played onto the node's `camera_odom`; None: its only one, if any."""
    storage: str = "mcap"
    """Storage of the output bag (a key of FORMATS)."""
    overlays: str | Path | None = None
    """Folder for the first `overlay_count` debug images as PNG; None: none (and the node builds none)."""
    overlay_count: int = 3
    frame_timeout: float = 120.0
    """Seconds the node may take to finish a frame before replay gives up (TimeoutError)."""
    progress: bool = True
    use_rois: bool = True
    """Play the bag's `/roi/<name>` boxes; False: the node finds the objects with the checkpoint's localiser."""

    def __post_init__(self) -> None:
        if self.rate is not None and not self.rate > 0:
            raise ValueError(f"rate must be > 0, got {self.rate}")
        if self.storage not in FORMATS:
            raise ValueError(f"storage must be one of {sorted(FORMATS)}, got {self.storage!r}")


@dataclass
class ReplayResult:
    out_bag: Path
    frames_published: int
    counts: dict[str, int]
    frame_latency_ms: list[float]
    report: dict | None
    overlays: list[Path] = field(default_factory=list)


@dataclass
class _Session:
    """The node under test and the player node, spun by one executor, with the bag's camera topics."""

    node: AxisPoseNode
    player: Node
    exe: SingleThreadedExecutor
    image_topic: str
    info_topic: str
    odom_topic: str | None = None


@dataclass
class _Recording:
    """What the player heard from the node: per-object poses (stamp -> name -> [(R, t)]), when each stamp's
    PoseArray reached the player (DDS receipt, ns since the epoch), and the overlay PNGs written."""

    poses: dict[int, dict[str, list]] = field(default_factory=lambda: defaultdict(lambda: defaultdict(list)))
    arrays: dict[int, int] = field(default_factory=dict)
    overlays: list[Path] = field(default_factory=list)


def replay(bag: str | Path, checkpoint: str | Path, out_bag: str | Path, options: ReplayOptions | None = None) -> ReplayResult:
    """Run the node on `bag` (module docstring) as `options` say (default: lock-step, the bag's boxes played).
    Raises BagError for an unreadable bag; what was recorded until then stays a valid bag at `out_bag`."""
    opts = options or ReplayOptions()
    out_bag = Path(out_bag)
    if out_bag.exists():
        raise FileExistsError(f"{out_bag} exists; rosbag2 writers refuse to overwrite a bag")
    topics = bag_topics(bag)
    image_topic, info_topic, odom_topic = camera_topics(topics, opts.image_topic, opts.info_topic, opts.odom_topic)
    remaps = [f"image:={image_topic}", f"camera_info:={info_topic}"] + ([f"camera_odom:={odom_topic}"] if odom_topic else [])

    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    node = player = None
    try:
        node = AxisPoseNode(
            context=ctx,
            parameter_overrides=_overrides(checkpoint, opts.params, (image_topic, info_topic)),
            cli_args=["--ros-args", *[a for r in remaps for a in ("-r", r)]],
        )
        player = rclpy.create_node("axispose_replay", context=ctx, start_parameter_services=False, enable_rosout=False)
        exe = SingleThreadedExecutor(context=ctx)
        exe.add_node(node)
        exe.add_node(player)
        return _run(bag, _Session(node, player, exe, image_topic, info_topic, odom_topic), out_bag, opts)
    finally:
        if node is not None:
            node.destroy_node()
        if player is not None:
            player.destroy_node()
        rclpy.try_shutdown(context=ctx)


def _overrides(checkpoint: str | Path, params: Mapping[str, object], camera_topics: Iterable[str]) -> list[Parameter]:
    """The node's parameters: the checkpoint, the caller's, and reliable delivery of the camera topics through
    the node's QoS-override parameters, so that DDS does not discard large images in a burst."""
    overrides = [Parameter("checkpoint", value=str(checkpoint))]
    overrides += [Parameter(k, value=v) for k, v in params.items()]
    for topic in camera_topics:
        overrides += [
            Parameter(f"qos_overrides.{topic}.subscription.reliability", value="reliable"),
            Parameter(f"qos_overrides.{topic}.subscription.depth", value=10),
        ]
    return overrides


def _run(bag: str | Path, s: _Session, out_bag: Path, opts: ReplayOptions) -> ReplayResult:
    """Play the bag to the node, record what it publishes into `out_bag`, and score it when the bag has GT."""
    player = _Player(s, opts)
    with Writer(out_bag, version=9, storage_plugin=FORMATS[opts.storage]) as writer:
        rec = _record(s, writer, opts)
        try:
            player.play(bag)
        finally:
            _await_frame(s.exe, s.node, player.frames, opts.frame_timeout)
            _spin_until(s.exe, lambda: len(rec.arrays) >= s.node.counts["frames_processed"], 5.0)
            _spin_until(s.exe, lambda: False, 0.3)  # last per-object poses and debug images

    latency = {t: (rec.arrays[t] - player.published_at[t]) / 1e6 for t in sorted(rec.arrays) if t in player.published_at}
    counts = dict(s.node.counts)
    report = None
    if player.truth.gt and player.truth.points:
        report = replay_report(s.node, player.truth, rec.poses, latency, counts, {"bag": str(bag), "rate": opts.rate})
    return ReplayResult(out_bag, player.frames, counts, list(latency.values()), report, rec.overlays)


def _record(s: _Session, writer: Writer, opts: ReplayOptions) -> _Recording:
    """Subscribe the player to the node's outputs: every message into `writer` (stamped by its header), and what
    the result and the report need into the returned _Recording. Every message is taken as its serialized bytes
    and written as it came (its stamp read from them), and only those a hook reads are deserialised, once: the
    player shares the node's process and interpreter, and decoding every marker and detection would take the
    node's time."""
    rec = _Recording()
    conns: dict[str, object] = {}

    def record(msg_class: type, topic: str, msgtype: str, hook: Callable | None = None, depth: int = 100) -> None:
        stamped = next(iter(msg_class.get_fields_and_field_types()), None) == "header"

        def on_raw(raw: bytes, info: dict) -> None:
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msgtype, typestore=TYPESTORE)
            writer.write(conns[topic], (cdr_stamp(raw) if stamped else None) or time.time_ns(), raw)
            if hook:
                hook(deserialize_message(raw, msg_class), info.get("received_timestamp") or time.time_ns())

        s.player.create_subscription(msg_class, topic, on_raw, depth, raw=True)

    def on_array(msg: PoseArray, received_ns: int) -> None:
        rec.arrays[stamp_ns(msg.header)] = received_ns

    def on_debug(msg: Image, _: int) -> None:
        if opts.overlays is not None and len(rec.overlays) < opts.overlay_count:
            path = Path(opts.overlays) / f"overlay_{len(rec.overlays):02d}.png"
            path.parent.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(path), cv2.cvtColor(image_to_rgb(msg), cv2.COLOR_RGB2BGR))
            rec.overlays.append(path)

    ns = s.node.resolve_topic_name("~")
    record(PoseArray, f"{ns}/pose_array", "geometry_msgs/msg/PoseArray", on_array)
    record(PoseStamped, f"{ns}/pose", "geometry_msgs/msg/PoseStamped")
    register_axispose_msgs()
    record(DetectionArray, f"{ns}/detections", "axispose_msgs/msg/DetectionArray")
    record(PoseWithCovarianceStamped, f"{ns}/pose_cov", "geometry_msgs/msg/PoseWithCovarianceStamped")
    for name in s.node.published.values():
        hook = (lambda n: lambda m, _: rec.poses[stamp_ns(m.header)][n].append(pose_rt(m.pose)))(name)
        record(PoseStamped, f"{ns}/poses/{name}", "geometry_msgs/msg/PoseStamped", hook)
    record(MarkerArray, f"{ns}/markers", "visualization_msgs/msg/MarkerArray")
    record(DiagnosticArray, "/diagnostics", "diagnostic_msgs/msg/DiagnosticArray")
    if opts.overlays is not None:
        record(Image, f"{ns}/debug/axis_image", "sensor_msgs/msg/Image", on_debug, depth=10)
    return rec


class _Player:
    """Plays the bag's camera stream and boxes to the node (lock-step, or paced by `rate`), keeping the ground
    truth it passes and when each image was published."""

    def __init__(self, s: _Session, opts: ReplayOptions) -> None:
        self.s, self.opts = s, opts
        reliable = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        self.pubs = {
            s.image_topic: s.player.create_publisher(Image, s.image_topic, reliable),
            s.info_topic: s.player.create_publisher(CameraInfo, s.info_topic, reliable),
        }
        if s.odom_topic:
            self.pubs[s.odom_topic] = s.player.create_publisher(Odometry, s.odom_topic, reliable)
        self.by_name = {o.name: o for o in s.node.estimator.config.objects} if opts.use_rois else {}
        for name in self.by_name:
            self.pubs[ROI_PREFIX + name] = s.player.create_publisher(RegionOfInterest, s.node.resolve_topic_name(f"~/roi/{name}"), 10)
        self.truth = Truth()
        self.published_at: dict[int, int] = {}
        self.frames = 0
        self._start = 0.0
        self._first_ns: int | None = None

    def play(self, bag: str | Path) -> None:
        """Every frame of `bag` in turn; in lock-step, each once the node has finished the one before."""
        self._start = time.perf_counter()
        # Let discovery match the player's publishers with the node's subscriptions before the first frame.
        _spin_until(self.s.exe, lambda: all(p.get_subscription_count() > 0 for p in self.pubs.values()), 10.0)
        bar = tqdm(desc="replay", unit="frame", disable=not self.opts.progress)
        try:
            for stamp, group in by_stamp(read_bag(bag)):
                stream = [(m.topic, ros_message(m)) for m in group if not self.truth.take(stamp, m) and m.topic in self.pubs]
                if stream:
                    self._frame(stamp, stream, bar)
        finally:
            bar.close()

    def _frame(self, stamp: int, stream: list[tuple[str, object]], bar: tqdm) -> None:
        """One frame: its boxes, the camera's pose, its CameraInfo, then its image (in lock-step, waiting for the
        node to finish it)."""
        s, lock_step = self.s, self.opts.rate is None
        if not lock_step:
            self._pace(stamp)
        self._boxes(stamp, {t[len(ROI_PREFIX) :]: msg for t, msg in stream if t.startswith(ROI_PREFIX)})
        self._odometry([msg for t, msg in stream if t == s.odom_topic])
        for topic, msg in stream:
            if topic == s.info_topic:
                self.truth.cameras[stamp_ns(msg.header)] = np.array(msg.k, dtype=float).reshape(3, 3)
                self.pubs[topic].publish(msg)
        for topic, msg in stream:
            if topic == s.image_topic:
                self.published_at[stamp_ns(msg.header)] = time.time_ns()
                self.pubs[topic].publish(msg)
                self.frames += 1
                bar.update(1)
                if lock_step:
                    _await_frame(s.exe, s.node, self.frames, self.opts.frame_timeout)

    def _odometry(self, messages: list[Odometry]) -> None:
        """Publish the frame's camera poses; in lock-step, wait until the node holds them (their stamps' poses)."""
        for msg in messages:
            self.pubs[self.s.odom_topic].publish(msg)
        if self.opts.rate is None and messages:
            poses, stamp = self.s.node.camera_poses, stamp_seconds(messages[-1].header)
            _spin_until(self.s.exe, lambda: poses.at(stamp, 0.0) is not None, 10.0)

    def _pace(self, stamp: int) -> None:
        """Spin until the frame of bag time `stamp` is due: the bag's timing scaled by `rate`."""
        self._first_ns = stamp if self._first_ns is None else self._first_ns
        due = self._start + (stamp - self._first_ns) / 1e9 / self.opts.rate
        while (left := due - time.perf_counter()) > 0:
            self.s.exe.spin_once(timeout_sec=min(POLL_S, left))

    def _boxes(self, stamp: int, rois: dict[str, RegionOfInterest]) -> None:
        """Publish every object's box of this frame; one without a box gets an empty one, so its old box is void.
        In lock-step, wait until the node holds them all, so that they are in place before the image is processed."""
        for name in self.by_name:
            roi = rois.get(name, RegionOfInterest())
            if name in rois:
                self.truth.boxes[(stamp, name)] = (roi.x_offset, roi.y_offset, roi.width, roi.height)
            self.pubs[ROI_PREFIX + name].publish(roi)
        if self.opts.rate is None:
            want = {self.by_name[n].obj_id: rois.get(n, RegionOfInterest()) for n in self.by_name}
            node = self.s.node
            _spin_until(self.s.exe, lambda: all(node.rois.latest(i) == roi for i, roi in want.items()), 10.0)


def _spin_until(exe, cond: Callable[[], bool], timeout: float) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return True
        exe.spin_once(timeout_sec=POLL_S)
    return cond()


def _await_frame(exe, node: AxisPoseNode, n: int, timeout: float, settle: float = 1.0) -> None:
    """Spin until `n` frames have left the node, or it has been idle for `settle` s (a frame still waiting in the
    synchroniser for a CameraInfo the bag does not have, or one DDS lost in rate mode)."""
    end = time.monotonic() + timeout
    idle_since = None
    while time.monotonic() < end:
        if node.frames_done() >= n:
            return
        now = time.monotonic()
        idle_since = (idle_since or now) if node.idle() else None
        if idle_since is not None and now - idle_since > settle:
            return
        exe.spin_once(timeout_sec=POLL_S)
    raise TimeoutError(f"the node did not finish frame {n} within {timeout} s")
