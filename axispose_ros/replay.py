"""`axispose replay`: the real node, in-process, on a recorded bag; its outputs recorded; metrics against GT.

A private rclpy Context holds the node under test and a player node. The player publishes the bag's camera
stream (and its `/roi/<name>` boxes, onto the node's `~/roi/<name>`) on the bag's topic names, which the node
subscribes by remapping; its image and CameraInfo subscriptions are switched to reliable delivery through the
node's own QoS-override parameters, so that DDS does not discard large images in a burst. Two pacings:
- lock-step (as fast as possible, the default): each image is published once the node is idle, so every frame
  is processed and the metrics see all of them;
- `rate` R: the bag's own timing scaled by R, as a live camera would deliver it; frames the node cannot keep up
  with are dropped by its latest-frame-wins slot and counted.
Every message the node publishes is written into the output bag (stamped by its header). When the bag holds
`/gt/<name>` poses and `/gt/models/<name>` points (as `make_bag` writes them), the report has the same metrics
as `axispose eval` plus latency and the node's counters.
"""

from __future__ import annotations

import time
from collections import defaultdict
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseArray, PoseStamped, PoseWithCovarianceStamped
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message, serialize_message
from rosbags.rosbag2 import Writer
from scipy.spatial.transform import Rotation
from sensor_msgs.msg import CameraInfo, Image, RegionOfInterest
from tqdm import tqdm
from visualization_msgs.msg import MarkerArray

import axispose_msgs
from axispose_core.evaluate import Record, instance_scores, summarize
from axispose_msgs.msg import DetectionArray
from axispose_ros.bag import (
    FORMATS,
    GT_PREFIX,
    MODELS_PREFIX,
    ROI_PREFIX,
    TYPESTORE,
    BagError,
    BagMessage,
    bag_topics,
    cloud_points,
    deserialize,
    read_bag,
    register_types,
)
from axispose_ros.conversions import image_to_rgb
from axispose_ros.node import AxisPoseNode

# How long one spin of the replay's executor may wait for an event before it re-checks its condition. The node's
# inference runs on its own thread in this process, and a fast spin takes CPU from it (and lengthens the frame
# latency being measured: docs/BENCHMARKS.md, Latency), so conditions that no ROS event signals (a count, a
# clock) are polled no faster than this.
POLL_S = 0.05

ROS_TYPES = {
    "sensor_msgs/msg/Image": Image,
    "sensor_msgs/msg/CameraInfo": CameraInfo,
    "sensor_msgs/msg/RegionOfInterest": RegionOfInterest,
}


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


@dataclass
class ReplayResult:
    out_bag: Path
    frames_published: int
    counts: dict[str, int]
    frame_latency_ms: list[float]
    report: dict | None
    overlays: list[Path] = field(default_factory=list)


def _stamp_ns(header) -> int:
    return int(header.stamp.sec) * 10**9 + int(header.stamp.nanosec)


def _unique_topic(topics: dict[str, str], msgtype: str, given: str | None) -> str:
    if given:
        if topics.get(given) != msgtype:
            raise BagError(f"the bag has no {msgtype} topic '{given}' (it has: {sorted(topics)})")
        return given
    found = [t for t, m in topics.items() if m == msgtype]
    if len(found) != 1:
        raise BagError(f"the bag has {len(found)} {msgtype} topics ({found}); name the one to use")
    return found[0]


def _pose_rt(pose) -> tuple[np.ndarray, np.ndarray]:
    q = pose.orientation
    R = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
    return R, np.array([pose.position.x, pose.position.y, pose.position.z])


def replay(
    bag: str | Path,
    checkpoint: str | Path,
    out_bag: str | Path,
    rate: float | None = None,
    params: dict[str, object] | None = None,
    image_topic: str | None = None,
    info_topic: str | None = None,
    storage: str = "mcap",
    overlays: str | Path | None = None,
    overlay_count: int = 3,
    frame_timeout: float = 120.0,
    progress: bool = True,
    use_rois: bool = True,
) -> ReplayResult:
    """Run the node on `bag` (module docstring). Raises BagError for an unreadable bag; what was recorded until
    then stays a valid bag at `out_bag`. With `use_rois` False the bag's boxes are not played, so the node
    finds the objects with the checkpoint's localiser."""
    if rate is not None and not rate > 0:
        raise ValueError(f"rate must be > 0, got {rate}")
    if storage not in FORMATS:
        raise ValueError(f"storage must be one of {sorted(FORMATS)}, got {storage!r}")
    out_bag = Path(out_bag)
    if out_bag.exists():
        raise FileExistsError(f"{out_bag} exists; rosbag2 writers refuse to overwrite a bag")
    topics = bag_topics(bag)
    image_topic = _unique_topic(topics, "sensor_msgs/msg/Image", image_topic)
    info_topic = _unique_topic(topics, "sensor_msgs/msg/CameraInfo", info_topic)

    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    overrides = [Parameter("checkpoint", value=str(checkpoint))]
    overrides += [Parameter(k, value=v) for k, v in (params or {}).items()]
    for topic in (image_topic, info_topic):
        overrides += [
            Parameter(f"qos_overrides.{topic}.subscription.reliability", value="reliable"),
            Parameter(f"qos_overrides.{topic}.subscription.depth", value=10),
        ]
    node = player = None
    try:
        node = AxisPoseNode(
            context=ctx,
            parameter_overrides=overrides,
            cli_args=["--ros-args", "-r", f"image:={image_topic}", "-r", f"camera_info:={info_topic}"],
        )
        player = rclpy.create_node("axispose_replay", context=ctx)
        exe = SingleThreadedExecutor(context=ctx)
        exe.add_node(node)
        exe.add_node(player)
        return _run(
            bag,
            node,
            player,
            exe,
            out_bag,
            storage,
            image_topic,
            info_topic,
            rate,
            overlays,
            overlay_count,
            frame_timeout,
            progress,
            use_rois,
        )
    finally:
        if node is not None:
            node.destroy_node()
        if player is not None:
            player.destroy_node()
        rclpy.try_shutdown(context=ctx)


def _run(
    bag, node: AxisPoseNode, player, exe, out_bag: Path, storage: str, image_topic: str, info_topic: str,
    rate: float | None, overlays, overlay_count: int, frame_timeout: float, progress: bool, use_rois: bool,
) -> ReplayResult:  # fmt: skip
    reliable = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    pubs = {
        image_topic: player.create_publisher(Image, image_topic, reliable),
        info_topic: player.create_publisher(CameraInfo, info_topic, reliable),
    }
    by_name = {o.name: o for o in node.estimator.config.objects} if use_rois else {}
    for name in by_name:
        pubs[ROI_PREFIX + name] = player.create_publisher(RegionOfInterest, node.resolve_topic_name(f"~/roi/{name}"), 10)

    poses: dict[int, dict[str, list]] = defaultdict(lambda: defaultdict(list))
    arrays: dict[int, float] = {}
    overlay_paths: list[Path] = []
    published_at: dict[int, float] = {}
    with Writer(out_bag, version=9, storage_plugin=FORMATS[storage]) as writer:
        conns: dict[str, object] = {}

        def recorder(topic: str, msgtype: str, hook: Callable | None = None) -> Callable:
            def on_msg(msg) -> None:
                if topic not in conns:
                    conns[topic] = writer.add_connection(topic, msgtype, typestore=TYPESTORE)
                stamp = _stamp_ns(msg.header) if hasattr(msg, "header") else time.time_ns()
                writer.write(conns[topic], stamp or time.time_ns(), serialize_message(msg))
                if hook:
                    hook(msg)

            return on_msg

        def on_array(msg: PoseArray) -> None:
            arrays[_stamp_ns(msg.header)] = time.perf_counter()

        def on_debug(msg: Image) -> None:
            if overlays is not None and len(overlay_paths) < overlay_count:
                path = Path(overlays) / f"overlay_{len(overlay_paths):02d}.png"
                path.parent.mkdir(parents=True, exist_ok=True)
                cv2.imwrite(str(path), cv2.cvtColor(image_to_rgb(msg), cv2.COLOR_RGB2BGR))
                overlay_paths.append(path)

        ns = node.resolve_topic_name("~")
        player.create_subscription(
            PoseArray, f"{ns}/pose_array", recorder(f"{ns}/pose_array", "geometry_msgs/msg/PoseArray", on_array), 100
        )
        player.create_subscription(PoseStamped, f"{ns}/pose", recorder(f"{ns}/pose", "geometry_msgs/msg/PoseStamped"), 100)
        register_axispose_msgs()
        topic = f"{ns}/detections"
        player.create_subscription(DetectionArray, topic, recorder(topic, "axispose_msgs/msg/DetectionArray"), 100)
        player.create_subscription(
            PoseWithCovarianceStamped, f"{ns}/pose_cov", recorder(f"{ns}/pose_cov", "geometry_msgs/msg/PoseWithCovarianceStamped"), 100
        )
        for name in node.published.values():
            topic = f"{ns}/poses/{name}"
            hook = (lambda n: lambda m: poses[_stamp_ns(m.header)][n].append(_pose_rt(m.pose)))(name)
            player.create_subscription(PoseStamped, topic, recorder(topic, "geometry_msgs/msg/PoseStamped", hook), 100)
        player.create_subscription(MarkerArray, f"{ns}/markers", recorder(f"{ns}/markers", "visualization_msgs/msg/MarkerArray"), 100)
        player.create_subscription(DiagnosticArray, "/diagnostics", recorder("/diagnostics", "diagnostic_msgs/msg/DiagnosticArray"), 100)
        if overlays is not None:
            topic = f"{ns}/debug/axis_image"
            player.create_subscription(Image, topic, recorder(topic, "sensor_msgs/msg/Image", on_debug), 10)

        gt: dict[int, dict[str, list]] = defaultdict(lambda: defaultdict(list))
        cameras: dict[int, np.ndarray] = {}
        boxes: dict[tuple[int, str], tuple[int, int, int, int]] = {}
        points: dict[str, np.ndarray] = {}
        frames = 0
        first_ns: int | None = None
        start = time.perf_counter()
        # Let discovery match the player's publishers with the node's subscriptions before the first frame.
        _spin_until(exe, lambda: all(p.get_subscription_count() > 0 for p in pubs.values()), 10.0)
        bar = tqdm(desc="replay", unit="frame", disable=not progress)
        try:
            for stamp, group in _by_stamp(read_bag(bag)):
                stream = []
                for m in group:
                    if m.topic.startswith(MODELS_PREFIX):
                        points[m.topic[len(MODELS_PREFIX) :]] = cloud_points(deserialize(m))
                    elif m.topic.startswith(GT_PREFIX):
                        gt[stamp][m.topic[len(GT_PREFIX) :]].append(_pose_rt(deserialize(m).pose))
                    elif m.topic in pubs:
                        stream.append((m.topic, _ros_message(m)))
                if not stream:
                    continue
                if rate is not None:
                    first_ns = stamp if first_ns is None else first_ns
                    due = start + (stamp - first_ns) / 1e9 / rate
                    while (left := due - time.perf_counter()) > 0:
                        exe.spin_once(timeout_sec=min(POLL_S, left))
                rois = {t[len(ROI_PREFIX) :]: msg for t, msg in stream if t.startswith(ROI_PREFIX)}
                for name in by_name:  # an object without box in this frame gets an empty one: its old box is void
                    roi = rois.get(name, RegionOfInterest())
                    if name in rois:
                        boxes[(stamp, name)] = (roi.x_offset, roi.y_offset, roi.width, roi.height)
                    pubs[ROI_PREFIX + name].publish(roi)
                if rate is None:  # the boxes must be in place before the image is processed
                    want = {by_name[n].obj_id: rois.get(n, RegionOfInterest()) for n in by_name}
                    _spin_until(exe, lambda want=want: all(node.rois.latest(i) == roi for i, roi in want.items()), 10.0)
                for topic, msg in stream:
                    if topic == info_topic:
                        cameras[_stamp_ns(msg.header)] = np.array(msg.k, dtype=float).reshape(3, 3)
                        pubs[topic].publish(msg)
                for topic, msg in stream:
                    if topic == image_topic:
                        published_at[_stamp_ns(msg.header)] = time.perf_counter()
                        pubs[topic].publish(msg)
                        frames += 1
                        bar.update(1)
                        if rate is None:
                            _await_frame(exe, node, frames, frame_timeout)
        finally:
            bar.close()
            _await_frame(exe, node, frames, frame_timeout)
            _spin_until(exe, lambda: len(arrays) >= node.counts["frames_processed"], 5.0)
            _spin_until(exe, lambda: False, 0.3)  # last per-object poses and debug images

    latency = {s: 1000 * (arrays[s] - published_at[s]) for s in sorted(arrays) if s in published_at}
    counts = dict(node.counts)
    report = None
    if gt and points:
        report = _report(node, gt, poses, cameras, boxes, points, arrays, latency, counts, {"bag": str(bag), "rate": rate})
    return ReplayResult(out_bag, frames, counts, list(latency.values()), report, overlay_paths)


def _by_stamp(messages: Iterable[BagMessage]) -> Iterator[tuple[int, list[BagMessage]]]:
    """Consecutive messages grouped by bag time: one camera frame with its boxes and ground truth."""
    group: list[BagMessage] = []
    for m in messages:
        if group and m.stamp_ns != group[0].stamp_ns:
            yield group[0].stamp_ns, group
            group = []
        group.append(m)
    if group:
        yield group[0].stamp_ns, group


def _ros_message(m):
    try:
        return deserialize_message(m.raw, ROS_TYPES[m.msgtype])
    except Exception as err:
        raise BagError(f"a '{m.topic}' message at {m.stamp_ns} ns does not decode as {m.msgtype} ({err})") from err


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


def _report(node, gt, poses, cameras, boxes, points, arrays, latency, counts, config) -> dict:
    """Per-instance scores as `axispose eval`: each GT instance matched to the nearest estimate of its object in
    the same frame (one-to-one); a frame the node dropped or an instance without estimate counts as wrong."""
    by_name = {o.name: o for o in node.estimator.config.objects}
    records: list[Record] = []
    for k, stamp in enumerate(sorted(gt)):
        n_inst = max(1, sum(len(v) for v in gt[stamp].values()))
        seconds = latency.get(stamp, 0.0) / 1000 / n_inst
        K = cameras.get(stamp)
        for name, instances in gt[stamp].items():
            spec = by_name.get(name)
            if spec is None or name not in points or name not in node.published.values() or K is None:
                continue
            ests = list(poses.get(stamp, {}).get(name, []))
            for R_gt, t_gt in instances:
                best = min(range(len(ests)), key=lambda i: np.linalg.norm(ests[i][1] - t_gt)) if ests else None
                R, t = ests.pop(best) if best is not None else (np.eye(3), np.zeros(3))
                scores = instance_scores(spec, points[name], K, R_gt, t_gt, (R, t) if best is not None else None)
                records.append(
                    Record(
                        spec.obj_id,
                        "bag",
                        k,
                        scores,
                        seconds,
                        R_gt,
                        t_gt,
                        R,
                        t,
                        best is not None,
                        K,
                        None,
                        boxes.get((stamp, name), (0, 0, 0, 0)),
                    )
                )
    objects = [o for o in node.estimator.config.objects if o.name in node.published.values()]
    used = {"ddim_steps": node.get_parameter("ddim_steps").value, "hypotheses": node.hypotheses(), "precision": node.precision}
    report = summarize(records, objects, config | used)
    lat = np.array(list(latency.values())) if latency else np.zeros(1)
    report["frame_latency_ms"] = {"median": float(np.median(lat)), "p90": float(np.percentile(lat, 90))}
    report["counts"] = counts
    return report
