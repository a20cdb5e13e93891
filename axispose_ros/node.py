"""`axispose_node`: 6D poses of known objects from an RGB camera stream.

Inputs: `image` (sensor_msgs/Image) and `camera_info`, paired by stamp within `sync_slop`; the boxes to
estimate come from `~/roi/<object_name>` (sensor_msgs/RegionOfInterest, the latest one per object within
`roi_timeout` seconds), for users with their own detector. Outputs keep the image header:
- `~/detections` (axispose_msgs/DetectionArray, every processed frame): each posed instance with its object id
  and name, score, pose with covariance and image box; the message for a robot stack;
- `~/pose` (each object's pose in turn, for simple consumers), `~/pose_cov` (the same poses with the covariance
  of the AGM's `hypotheses` samples, when two or more of them gave a pose), `~/poses/<object_name>`,
  `~/pose_array` (every frame, empty when nothing was estimated);
- `~/markers` (every frame: a DELETEALL, then three arrows per estimated instance with ids of their own and
  `marker_lifetime`), `~/debug/axis_image` (only built while subscribed), `/diagnostics`.
Only the objects of `objects` are looked for, estimated and published.

Images with lens distortion (a non-zero CameraInfo D) are undistorted to the pinhole image of K first; with
`use_rectified` the images are taken as rectified and P is used instead.

Inference runs on a worker thread fed by a latest-frame-wins slot, so the executor never blocks and stale
frames are dropped and counted instead of queueing. `image` and `camera_info` use the sensor-data QoS (best
effort): frames the transport discards never arrive and are estimated from stamp gaps (`frames_lost_in_transport`).
"""

from __future__ import annotations

import sys
import threading
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import rclpy
import rclpy.executors
import torch
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import Point, Pose, PoseArray, PoseStamped, PoseWithCovarianceStamped
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult
from rclpy.exceptions import ParameterException, ParameterUninitializedException
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import qos_profile_sensor_data
from rclpy.qos_overriding_options import QoSOverridingOptions
from scipy.spatial.transform import Rotation
from sensor_msgs.msg import CameraInfo, Image, RegionOfInterest
from visualization_msgs.msg import Marker, MarkerArray

from axispose_core.agm.sampler import Cancelled
from axispose_core.axis_image import draw_axes
from axispose_core.camera import crop_transform
from axispose_core.checkpoint import CheckpointError
from axispose_core.estimator import Estimator
from axispose_core.lmo import LMO_K
from axispose_msgs.msg import Detection, DetectionArray
from axispose_ros.conversions import InputError, Undistorter, camera_for_image, camera_from_info, image_to_rgb, rgb_to_image
from axispose_ros.health import Health, HealthConfig
from axispose_ros.sync import GapCounter, StampSynchronizer

DEFAULT_CHECKPOINT = Path(__file__).resolve().parents[1] / "axispose_core" / "models" / "axispose_lmo.safetensors"


def _stamp_seconds(header) -> float:
    return header.stamp.sec + 1e-9 * header.stamp.nanosec


@dataclass
class Frame:
    image: Image
    info: CameraInfo
    received: float


class AxisPoseNode(Node):
    """Pose estimation node; raises CheckpointError/ValueError at construction for unusable parameters."""

    def __init__(self, **kwargs) -> None:
        super().__init__("axispose", **kwargs)
        self._declare()
        checkpoint = self.get_parameter("checkpoint").value
        if not checkpoint:
            raise CheckpointError("parameter 'checkpoint' is empty: pass -p checkpoint:=/path/to/estimator.safetensors")
        self.threads = int(self.get_parameter("num_threads").value)
        # Inference runs on its own thread with `num_threads` OpenMP threads (set in `_work`). If this thread also
        # formed a team of several, libgomp would count more threads than cores and stop spinning between
        # parallel regions: every small op of the sampler then waits on a futex, 20-30 % per frame. So the
        # loading runs single-threaded, and the caller's setting comes back afterwards.
        caller_threads = torch.get_num_threads()
        torch.set_num_threads(1)
        try:
            self.estimator = Estimator.load(checkpoint, self.get_parameter("device").value)
        finally:
            torch.set_num_threads(caller_threads)
        self.precision = self.estimator.set_precision(self.get_parameter("precision").value)
        self.names = {o.obj_id: o.name for o in self.estimator.config.objects}
        try:
            wanted = list(self.get_parameter("objects").value or [])
        except ParameterUninitializedException:  # declared by type only: not given, so every object
            wanted = []
        unknown = sorted(set(wanted) - set(self.names.values()))
        if unknown:
            raise ValueError(f"parameter 'objects' names {unknown}, not in the checkpoint (it knows {sorted(self.names.values())})")
        self.published = {i: n for i, n in self.names.items() if not wanted or n in wanted}
        for name in self.names.values():
            self.declare_parameter(f"object_scales.{name}", 0.0, ParameterDescriptor(description=f"λ_O of {name} in m (0: checkpoint's)"))
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.counts: Counter[str] = Counter()
        self.latency: list[float] = []
        self._slot: Frame | None = None
        self._slot_lock = threading.Lock()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._busy = False
        self._rois: dict[int, tuple[RegionOfInterest, float]] = {}
        self._state_lock = threading.Lock()  # counts and _rois: the executor and the inference thread share them
        self.health = Health(HealthConfig(latency_budget_s=float(self.get_parameter("latency_budget").value)), time.monotonic())
        self.sync = StampSynchronizer(float(self.get_parameter("sync_slop").value), self._on_pair, self._on_drop)
        self.gaps = GapCounter()
        self._ready = threading.Event()
        self._worker = threading.Thread(target=self._work, name="axispose_inference", daemon=True)
        self._worker.start()
        self._ready.wait()  # warmed up: frames are taken only from here on
        qos_opts = QoSOverridingOptions.with_default_policies()
        self.create_subscription(Image, "image", self._on_image, qos_profile_sensor_data, qos_overriding_options=qos_opts)
        self.create_subscription(CameraInfo, "camera_info", self._on_info, qos_profile_sensor_data, qos_overriding_options=qos_opts)
        self.undistort = Undistorter()
        for obj_id, name in self.published.items():
            self.create_subscription(RegionOfInterest, f"~/roi/{name}", lambda m, i=obj_id: self._on_roi(i, m), 10)
        self.pub_pose = self.create_publisher(PoseStamped, "~/pose", 10)
        self.pub_pose_cov = self.create_publisher(PoseWithCovarianceStamped, "~/pose_cov", 10)
        self.pub_object = {i: self.create_publisher(PoseStamped, f"~/poses/{n}", 10) for i, n in self.published.items()}
        self.pub_array = self.create_publisher(PoseArray, "~/pose_array", 10)
        self.pub_detections = self.create_publisher(DetectionArray, "~/detections", 10)
        self.pub_markers = self.create_publisher(MarkerArray, "~/markers", 10)
        self.pub_debug = self.create_publisher(Image, "~/debug/axis_image", 1)
        self.pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.create_timer(1.0, self._publish_diagnostics)

    # ------------------------------------------------------------------ parameters
    def _declare(self) -> None:
        def desc(text: str, **rng) -> ParameterDescriptor:
            d = ParameterDescriptor(description=text)
            if "ints" in rng:
                d.integer_range = [IntegerRange(from_value=rng["ints"][0], to_value=rng["ints"][1], step=1)]
            if "floats" in rng:
                d.floating_point_range = [FloatingPointRange(from_value=rng["floats"][0], to_value=rng["floats"][1], step=0.0)]
            return d

        self.declare_parameter("checkpoint", str(DEFAULT_CHECKPOINT), desc("AxisPose estimator checkpoint (.safetensors)"))
        self.declare_parameter("ddim_steps", 4, desc("DDIM steps per estimate", ints=(1, 1000)))
        self.declare_parameter("hypotheses", 4, desc("AGM samples per object; >= 2 fills ~/pose_cov", ints=(1, 64)))
        self.declare_parameter("guidance_scale", 0.0, desc("run-time geometric guidance (0: off)", floats=(0.0, 100.0)))
        self.declare_parameter("object_scale", 0.0, desc("λ_O in m for every object (0: checkpoint's)", floats=(0.0, 10.0)))
        self.declare_parameter("device", "cpu", desc("cpu, cuda or auto"))
        self.declare_parameter(
            "precision", "auto", desc("the AGM's arithmetic: float32, bfloat16, or auto (bfloat16 where the device has it natively)")
        )
        self.declare_parameter("objects", Parameter.Type.STRING_ARRAY, desc("object names to look for, estimate and publish (empty: all)"))
        self.declare_parameter("use_rectified", False, desc("use P instead of K (images already rectified)"))
        self.declare_parameter("sync_slop", 0.02, desc("largest Image/CameraInfo stamp difference in s", floats=(0.0, 1.0)))
        self.declare_parameter("num_threads", 2, desc("torch CPU threads for inference", ints=(1, 64)))
        self.declare_parameter(
            "warmup_boxes",
            8,
            desc("at start, one blank-frame pass per box count up to this, so first frames skip setup; 0: none", ints=(0, 64)),
        )
        self.declare_parameter("roi_timeout", 1.0, desc("age in s after which an ROI is ignored", floats=(0.0, 3600.0)))
        self.declare_parameter("score_threshold", 0.3, desc("least localiser score of an instance", floats=(0.0, 1.0)))
        self.declare_parameter("marker_lifetime", 1.0, desc("lifetime of ~/markers in s (0: until replaced)", floats=(0.0, 3600.0)))
        self.declare_parameter(
            "latency_budget", 2.0, desc("median latency (s) over which /diagnostics warns; at start", floats=(0.01, 60.0))
        )
        dev = self.get_parameter("device").value
        if dev not in ("cpu", "cuda", "auto"):
            raise ValueError(f"parameter 'device' must be cpu, cuda or auto, got {dev!r}")
        if dev == "cuda" and not torch.cuda.is_available():
            raise ValueError(f"parameter 'device' is cuda, but this torch ({torch.__version__}) finds no CUDA device: use cpu or auto")
        if dev == "auto":
            self.set_parameters([Parameter("device", value="cuda" if torch.cuda.is_available() else "cpu")])

    def _on_set_parameters(self, params: list[Parameter]) -> SetParametersResult:
        fixed = {
            "checkpoint",
            "device",
            "precision",
            "objects",
            "use_rectified",
            "sync_slop",
            "num_threads",
            "warmup_boxes",
            "latency_budget",
        }
        for p in params:
            if p.name in fixed:
                return SetParametersResult(successful=False, reason=f"'{p.name}' is read at start only; restart the node to change it")
            if p.name.startswith("object_scales.") and (p.type_ != Parameter.Type.DOUBLE or not 0.0 <= p.value <= 10.0):
                return SetParametersResult(successful=False, reason=f"'{p.name}' must be a length in [0, 10] m")
        return SetParametersResult(successful=True)

    # ------------------------------------------------------------------ inputs
    def _on_image(self, msg: Image) -> None:
        self._count("frames_in")
        self.health.image(time.monotonic())
        stamp = _stamp_seconds(msg.header)
        lost = self.gaps.add(stamp)  # the sensor-data QoS is best effort: what DDS dropped never arrives
        if lost:
            self._count("frames_lost_in_transport", lost)
        self.sync.add_image(stamp, msg)

    def _on_info(self, msg: CameraInfo) -> None:
        self.sync.add_info(_stamp_seconds(msg.header), msg)

    def _on_roi(self, obj_id: int, msg: RegionOfInterest) -> None:
        with self._state_lock:
            self._rois[obj_id] = (msg, time.monotonic())

    def latest_roi(self, obj_id: int) -> RegionOfInterest | None:
        """The last box received for an object (None before any)."""
        entry = self._rois.get(obj_id)
        return entry[0] if entry else None

    def _dropped(self, reason: str) -> None:
        """A frame dropped for a reason: its counter, and the health of the recent window."""
        self._count(f"dropped_{reason}")
        self.health.drop(time.monotonic(), reason)

    def _on_drop(self, _: Image, reason: str) -> None:
        self._dropped(reason)
        self.get_logger().warning(f"dropped a frame: {reason}", throttle_duration_sec=5.0)

    def _on_pair(self, image: Image, info: CameraInfo) -> None:
        with self._slot_lock:
            if self._slot is not None:
                self._count("dropped_stale")
            self._slot = Frame(image, info, time.monotonic())
        self._wake.set()

    # ------------------------------------------------------------------ inference
    def _work(self) -> None:
        torch.set_num_threads(self.threads)  # this thread's OpenMP team; see __init__
        try:
            self._warm_up()
        finally:
            self._ready.set()
        while not self._stop.is_set():
            if not self._wake.wait(timeout=0.1):
                continue
            with self._slot_lock:
                frame, self._slot = self._slot, None
                self._wake.clear()
                self._busy = frame is not None
            if frame is None:
                continue
            try:
                self._process(frame)
            except Cancelled:  # shutting down mid-frame: the frame is abandoned, not dropped
                return
            except InputError as err:
                self._dropped(err.reason)
                self.get_logger().error(f"dropped a frame: {err}", throttle_duration_sec=5.0)
            except Exception as err:
                self._dropped("error")
                self.get_logger().error(f"inference failed on a frame: {err!r}", throttle_duration_sec=5.0)
            finally:
                with self._slot_lock:
                    self._busy = False

    def _warm_up(self) -> None:
        """One pass over a blank frame per box count up to `warmup_boxes` (1 DDIM step, the configured hypotheses):
        the first use of each batch shape sets its kernels up, about 50 ms per shape on a CPU, which the first
        frames with that many objects would otherwise pay."""
        count = int(self.get_parameter("warmup_boxes").value)
        if count == 0:
            return
        start = time.monotonic()
        rgb = np.full((480, 640, 3), 127, np.uint8)
        ids, hypotheses = list(self.published), int(self.get_parameter("hypotheses").value)
        try:
            if self.estimator.localiser is not None:
                self.estimator.detect(rgb)
            for k in range(1, count + 1):
                boxes = [(ids[i % len(ids)], (280.0, 200.0, 80.0, 90.0)) for i in range(k)]
                self.estimator.estimate(rgb, LMO_K, boxes, steps=1, hypotheses=hypotheses, cancelled=self._stop.is_set)
        except Cancelled:
            return
        except Exception as err:
            self.get_logger().warning(f"warm-up failed ({err!r}); the first frames will be slower")
            return
        self.get_logger().info(f"warmed up for 1-{count} boxes in {time.monotonic() - start:.1f} s")

    def frames_done(self) -> int:
        """Frames that left the node: processed, or dropped for a reason."""
        counts = self.counters()
        return counts.get("frames_processed", 0) + sum(v for k, v in counts.items() if k.startswith("dropped_"))

    def _count(self, key: str, n: int = 1) -> None:
        with self._state_lock:
            self.counts[key] += n

    def counters(self) -> dict[str, int]:
        """A consistent copy of the counters (iterating `counts` while the other thread adds a key would fail)."""
        with self._state_lock:
            return dict(self.counts)

    def idle(self) -> bool:
        """No frame waits for, or is in, inference (frames still waiting for their CameraInfo do not count)."""
        with self._slot_lock:
            return self._slot is None and not self._busy

    def _boxes(self, width: int, height: int) -> list[tuple[int, tuple[float, float, float, float]]]:
        """The fresh ROIs (only objects of `objects` have ROI topics), each inside the image."""
        now, timeout = time.monotonic(), float(self.get_parameter("roi_timeout").value)
        boxes = []
        with self._state_lock:
            rois = list(self._rois.items())
        for obj_id, (roi, seen) in rois:
            if now - seen > timeout or roi.width == 0 or roi.height == 0:
                continue
            if roi.x_offset + roi.width > width or roi.y_offset + roi.height > height:
                self._count("roi_outside")
                continue
            boxes.append((obj_id, (roi.x_offset, roi.y_offset, roi.width, roi.height)))
        return boxes

    def _scales(self) -> dict[int, float]:
        common = float(self.get_parameter("object_scale").value)
        out = {}
        for obj_id, name in self.names.items():
            own = float(self.get_parameter(f"object_scales.{name}").value)
            if own > 0 or common > 0:
                out[obj_id] = own if own > 0 else common
        return out

    def _process(self, frame: Frame) -> None:
        rgb = image_to_rgb(frame.image)
        rectified = bool(self.get_parameter("use_rectified").value)
        camera = camera_for_image(camera_from_info(frame.info, rectified), rgb.shape[1], rgb.shape[0])
        if not rectified and Undistorter.needed(frame.info):
            rgb = self.undistort(frame.info, camera.K, rgb)
        boxes = self._boxes(rgb.shape[1], rgb.shape[0])
        scores = [1.0] * len(boxes)
        if not boxes and self.estimator.localiser is not None:
            threshold = float(self.get_parameter("score_threshold").value)
            dets = [d for d in self.estimator.detect(rgb, threshold) if d.obj_id in self.published]
            boxes, scores = [(d.obj_id, d.box) for d in dets], [d.score for d in dets]
        estimates = self.estimator.estimate(
            rgb,
            camera.K,
            boxes,
            steps=int(self.get_parameter("ddim_steps").value),
            guidance_scale=float(self.get_parameter("guidance_scale").value),
            scales=self._scales(),
            hypotheses=int(self.get_parameter("hypotheses").value),
            cancelled=self._stop.is_set,
        )
        header = frame.image.header
        array = PoseArray(header=header)
        detections = DetectionArray(header=header)
        markers = MarkerArray(markers=[Marker(header=header, action=Marker.DELETEALL)])  # the last frame's go
        lifetime = float(self.get_parameter("marker_lifetime").value)
        best: dict[int, tuple[float, PoseStamped, np.ndarray | None]] = {}
        for k, (est, score, (_, box)) in enumerate(zip(estimates, scores, boxes, strict=True)):
            if not est.ok:
                self._count("pose_refused")
                continue
            pose = _pose(est.R, est.t)
            array.poses.append(pose)
            detections.detections.append(_detection(est, self.names[est.obj_id], score, pose, box))
            stamped = PoseStamped(header=header, pose=pose)
            self.pub_object[est.obj_id].publish(stamped)
            if est.obj_id not in best or score > best[est.obj_id][0]:
                best[est.obj_id] = (score, stamped, est.covariance)
            lengths = self.estimator.objects[est.obj_id].axes.lengths
            markers.markers.extend(_axis_markers(header, est, self.names[est.obj_id], lengths, k, lifetime))
        for _, stamped, cov in best.values():
            self.pub_pose.publish(stamped)
            if cov is not None:
                msg = PoseWithCovarianceStamped(header=header)
                msg.pose.pose, msg.pose.covariance = stamped.pose, [float(v) for v in cov.ravel()]
                self.pub_pose_cov.publish(msg)
        self.pub_array.publish(array)
        self.pub_detections.publish(detections)
        self.pub_markers.publish(markers)
        if self.pub_debug.get_subscription_count() > 0:
            self.pub_debug.publish(rgb_to_image(_debug_overlay(rgb, camera.K, estimates, self.estimator), header))
        self._count("frames_processed")
        now = time.monotonic()
        self.latency.append(now - frame.received)
        self.latency = self.latency[-100:]
        self.health.output(now, now - frame.received)

    def _publish_diagnostics(self) -> None:
        status = DiagnosticStatus(name="axispose: pose estimation", hardware_id=self.get_name())
        status.level, status.message = self.health.judge(time.monotonic())  # the recent window; counters below are totals
        values: dict[str, float] = dict(self.counters())
        if self.latency:
            values["latency_median_ms"] = 1000 * float(np.median(self.latency))
        status.values = [KeyValue(key=k, value=f"{v:.1f}" if isinstance(v, float) else str(v)) for k, v in sorted(values.items())]
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self.get_clock().now().to_msg()
        self.pub_diag.publish(msg)

    def destroy_node(self) -> None:
        self._stop.set()
        self._wake.set()
        self._worker.join(timeout=10.0)
        super().destroy_node()


def _pose(R: np.ndarray, t: np.ndarray) -> Pose:
    pose = Pose()
    pose.position.x, pose.position.y, pose.position.z = (float(v) for v in t)
    q = Rotation.from_matrix(R).as_quat()  # x, y, z, w
    pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w = (float(v) for v in q)
    return pose


def _detection(est, name: str, score: float, pose: Pose, box: tuple[float, float, float, float]) -> Detection:
    """One posed instance as axispose_msgs/Detection; covariance all zeros (unknown) for a single sample."""
    msg = Detection(obj_id=int(est.obj_id), name=name, score=float(score), box=[float(v) for v in box])
    msg.pose.pose = pose
    if est.covariance is not None:
        msg.pose.covariance = [float(v) for v in est.covariance.ravel()]
    return msg


def _axis_markers(header, est, name: str, lengths: np.ndarray, instance: int, lifetime: float) -> list[Marker]:
    """Three arrows (X red, Y green, Z blue) from the object's origin, in the camera frame; ids 3 x instance + axis,
    so that two instances of one object keep their own, and gone after `lifetime` seconds (0: until replaced)."""
    out = []
    for k, color in enumerate(((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))):
        m = Marker(header=header, ns=f"axispose/{name}", id=3 * instance + k, type=Marker.ARROW, action=Marker.ADD)
        m.lifetime.sec, m.lifetime.nanosec = int(lifetime), round((lifetime % 1.0) * 1e9) % 1_000_000_000
        start, end = est.t, est.t + est.R[:, k] * lengths[k]
        m.points = [
            Point(x=float(start[0]), y=float(start[1]), z=float(start[2])),
            Point(x=float(end[0]), y=float(end[1]), z=float(end[2])),
        ]
        m.scale.x, m.scale.y, m.scale.z = 0.004, 0.008, 0.01
        m.color.r, m.color.g, m.color.b, m.color.a = (*color, 1.0)
        out.append(m)
    return out


def _debug_overlay(rgb: np.ndarray, K: np.ndarray, estimates, estimator: Estimator) -> np.ndarray:
    """The input with each generated axis image blended into its crop and the estimated axes drawn."""
    out = rgb.copy()
    S = estimator.size
    for est in estimates:
        A = crop_transform(est.center, est.side, S)[:2]
        warped = cv2.warpAffine((est.axis_image * 255).astype(np.uint8), A, (rgb.shape[1], rgb.shape[0]), flags=cv2.WARP_INVERSE_MAP)
        lit = warped.max(axis=2) > 64
        out[lit] = (0.4 * out[lit] + 0.6 * warped[lit]).astype(np.uint8)
        if est.ok:
            bgr = out[..., ::-1].copy()
            draw_axes(bgr, K, est.R, est.t, estimator.objects[est.obj_id].axes.lengths)
            out = bgr[..., ::-1].copy()
    return out


def main(args: list[str] | None = None) -> int:
    rclpy.init(args=args)
    try:
        node = AxisPoseNode()
    except (CheckpointError, ValueError, ParameterException) as err:  # a parameter out of range or of the wrong type
        print(f"axispose_node: {' '.join(str(err).split())}", file=sys.stderr)  # one line, whatever rclpy formats
        rclpy.try_shutdown()
        return 2
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, rclpy.executors.ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
