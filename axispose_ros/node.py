"""`axispose_node`: 6D poses of known objects from an RGB camera stream.

Inputs: `image` (sensor_msgs/Image) and `camera_info`, paired by stamp within `sync_slop`; the boxes to
estimate come from `~/roi/<object_name>` (sensor_msgs/RegionOfInterest, the latest one per object within
`roi_timeout` seconds), for users with their own detector. Outputs keep the image header:
- `~/detections` (axispose_msgs/DetectionArray, every processed frame): each posed instance with its object id
  and name, score, pose with covariance and image box; the message for a robot stack;
- `~/pose` (each object's pose in turn, for simple consumers), `~/pose_cov` (the same poses with their
  covariance: the dense fusion's, plus the scatter of the AGM's samples when `hypotheses` >= 2), `~/poses/<object_name>`,
  `~/pose_array` (every frame, empty when nothing was estimated);
- `~/markers` (every frame: a DELETEALL, then three arrows per estimated instance with ids of their own and
  `marker_lifetime`), `~/debug/axis_image` (only built while subscribed), `/diagnostics`.
Only the objects of `objects` are looked for, estimated and published.

Images with lens distortion (a non-zero CameraInfo D) are undistorted to the pinhole image of K first; with
`use_rectified` the images are taken as rectified and P is used instead.

The node composes three parts: its inputs (Image/CameraInfo pairing by stamp, the stamps' audit, the latest ROI
per object: `sync.py`), the inference worker (`worker.py`: one thread fed by a latest-frame-wins slot, so the
executor never blocks and stale frames are dropped and counted instead of queueing) and its outputs
(`outputs.py`); it owns the parameters, the counters and the diagnostics. `image` and `camera_info` use the
sensor-data QoS (best effort): frames the transport discards never arrive and are estimated from stamp gaps
(`frames_lost_in_transport`, at most one per frame seen); stamps that are zero, go back, lie in the future or jump
are counted apart (`stamps_<anomaly>`), and such frames are still processed.

Between processes, Fast DDS's defaults lose most full-size images (its 512 KB shared-memory segment cannot hold
them in flight): `main` loads the shipped profile `config/fastdds_profile.xml` unless the user named one, and the
camera driver's process needs it too (README, "Beside a camera driver").
"""

from __future__ import annotations

import os
import sys
import threading
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import rclpy
import rclpy.executors
import torch
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult
from rclpy.exceptions import ParameterException, ParameterUninitializedException
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import qos_profile_sensor_data
from rclpy.qos_overriding_options import QoSOverridingOptions
from sensor_msgs.msg import CameraInfo, Image, RegionOfInterest

from axispose_core.agm.sampler import Cancelled
from axispose_core.checkpoint import CheckpointError
from axispose_core.estimator import SHIPPED_ESTIMATOR, EstimateOptions, Estimator
from axispose_core.lmo import LMO_K
from axispose_ros.conversions import InputError, Undistorter, camera_for_image, camera_from_info, image_to_rgb
from axispose_ros.health import Health, HealthConfig
from axispose_ros.outputs import PoseOutputs
from axispose_ros.sync import RoiStore, StampAudit, StampSynchronizer
from axispose_ros.worker import InferenceWorker

DEFAULT_CHECKPOINT = SHIPPED_ESTIMATOR
FASTDDS_PROFILE_NAME = "fastdds_profile.xml"
PROFILE_VARIABLES = ("FASTRTPS_DEFAULT_PROFILES_FILE", "FASTDDS_DEFAULT_PROFILES_FILE")
"""The variables Fast DDS reads its XML profiles from: 2.x (Jazzy) and 3.x."""


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
        self.rois = RoiStore()
        self._state_lock = threading.Lock()  # the counts: the executor and the inference thread share them
        self.health = Health(HealthConfig(latency_budget_s=float(self.get_parameter("latency_budget").value)), time.monotonic())
        self.sync = StampSynchronizer(float(self.get_parameter("sync_slop").value), self._on_pair, self._on_drop)
        self.stamps = StampAudit()
        self.worker: InferenceWorker[Frame] = InferenceWorker(self._process, self._warm_up, self._on_error, self.threads)
        self.worker.start()  # warmed up: frames are taken only from here on
        qos_opts = QoSOverridingOptions.with_default_policies()
        self.create_subscription(Image, "image", self._on_image, qos_profile_sensor_data, qos_overriding_options=qos_opts)
        self.create_subscription(CameraInfo, "camera_info", self._on_info, qos_profile_sensor_data, qos_overriding_options=qos_opts)
        self.undistort = Undistorter()
        for obj_id, name in self.published.items():
            self.create_subscription(RegionOfInterest, f"~/roi/{name}", lambda m, i=obj_id: self._on_roi(i, m), 10)
        self.outputs = PoseOutputs(self, self.published)
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
        self.declare_parameter("ddim_steps", 3, desc("DDIM steps per estimate", ints=(1, 1000)))
        self.declare_parameter(
            "hypotheses", 1, desc("AGM samples per object; >= 2: their consensus, their scatter added to the covariance", ints=(1, 64))
        )
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
        now = self.get_clock().now().nanoseconds * 1e-9  # a simulated clock reads 0 until /clock arrives: unknown
        verdict = self.stamps.add(stamp, now if now > 0 else None)
        if verdict.lost:  # the sensor-data QoS is best effort: what DDS dropped never arrives
            self._count("frames_lost_in_transport", verdict.lost)
        if verdict.anomaly:
            self._count(f"stamps_{verdict.anomaly}")
            self.get_logger().warning(f"image stamp {stamp:.9f}: {verdict.anomaly} (counted; the frame is still processed)",
                                      throttle_duration_sec=5.0)  # fmt: skip
        self.sync.add_image(stamp, msg)

    def _on_info(self, msg: CameraInfo) -> None:
        self._count("camera_info_in")
        self.health.info(time.monotonic())
        self.sync.add_info(_stamp_seconds(msg.header), msg)

    def _on_roi(self, obj_id: int, msg: RegionOfInterest) -> None:
        self.rois.add(obj_id, msg, time.monotonic())

    def _dropped(self, reason: str) -> None:
        """A frame dropped for a reason: its counter, and the health of the recent window."""
        self._count(f"dropped_{reason}")
        self.health.drop(time.monotonic(), reason)

    def _on_drop(self, _: Image, reason: str) -> None:
        self._dropped(reason)
        self.get_logger().warning(f"dropped a frame: {reason}", throttle_duration_sec=5.0)

    def _on_pair(self, image: Image, info: CameraInfo) -> None:
        if self.worker.submit(Frame(image, info, time.monotonic())):
            self._count("dropped_stale")

    # ------------------------------------------------------------------ inference (on the worker's thread)
    def _on_error(self, err: Exception) -> None:
        """A frame the worker could not process: dropped and counted, with its reason."""
        if isinstance(err, InputError):
            self._dropped(err.reason)
            self.get_logger().error(f"dropped a frame: {err}", throttle_duration_sec=5.0)
        else:
            self._dropped("error")
            self.get_logger().error(f"inference failed on a frame: {err!r}", throttle_duration_sec=5.0)

    def _warm_up(self) -> None:
        """One pass over a blank frame per box count up to `warmup_boxes` (1 DDIM step, the configured hypotheses):
        the first use of each batch shape sets its kernels up, about 50 ms per shape on a CPU, which the first
        frames with that many objects would otherwise pay."""
        count = int(self.get_parameter("warmup_boxes").value)
        if count == 0:
            return
        start = time.monotonic()
        rgb = np.full((480, 640, 3), 127, np.uint8)
        ids, hypotheses = list(self.published), self.hypotheses()
        try:
            if self.estimator.localiser is not None:
                self.estimator.detect(rgb)
            for k in range(1, count + 1):
                boxes = [(ids[i % len(ids)], (280.0, 200.0, 80.0, 90.0)) for i in range(k)]
                options = EstimateOptions(steps=1, hypotheses=hypotheses)
                self.estimator.estimate(rgb, LMO_K, boxes, options=options, cancelled=self.worker.cancelled)
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
        return self.worker.idle()

    def hypotheses(self) -> int:
        """AGM samples per object."""
        return int(self.get_parameter("hypotheses").value)

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
        timeout = float(self.get_parameter("roi_timeout").value)
        boxes, outside = self.rois.fresh(time.monotonic(), timeout, rgb.shape[1], rgb.shape[0])
        if outside:
            self._count("roi_outside", outside)
        scores = [1.0] * len(boxes)
        if not boxes and self.estimator.localiser is not None:
            threshold = float(self.get_parameter("score_threshold").value)
            dets = [d for d in self.estimator.detect(rgb, threshold) if d.obj_id in self.published]
            boxes, scores = [(d.obj_id, d.box) for d in dets], [d.score for d in dets]
        estimates = self.estimator.estimate(
            rgb,
            camera.K,
            boxes,
            options=EstimateOptions(
                steps=int(self.get_parameter("ddim_steps").value),
                guidance_scale=float(self.get_parameter("guidance_scale").value),
                scales=self._scales(),
                hypotheses=self.hypotheses(),
            ),
            cancelled=self.worker.cancelled,
        )
        lifetime = float(self.get_parameter("marker_lifetime").value)
        header, box_xywh = frame.image.header, [b for _, b in boxes]
        refused = self.outputs.publish(header, estimates, scores, box_xywh, self.estimator, rgb, camera.K, lifetime)
        if refused:
            self._count("pose_refused", refused)
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
        self.worker.stop()
        super().destroy_node()


def shipped_fastdds_profile() -> Path | None:
    """The Fast DDS profile shipped with the package: beside the sources (a checkout, pip -e), else in the package's
    share directory (colcon, pip)."""
    candidates = [Path(__file__).resolve().parents[1] / "config" / FASTDDS_PROFILE_NAME]
    try:
        from ament_index_python.packages import get_package_share_directory

        candidates.append(Path(get_package_share_directory("axispose_ros")) / "config" / FASTDDS_PROFILE_NAME)
    except Exception:  # not in an ament index (PackageNotFoundError, or no index at all)
        pass
    return next((p for p in candidates if p.is_file()), None)


def use_shipped_fastdds_profile(environ: dict[str, str] | os._Environ = os.environ) -> Path | None:
    """Point Fast DDS at the shipped profile, unless the user chose a profile (either variable set, even empty) or
    another middleware (RMW_IMPLEMENTATION not Fast DDS). Must run before the process's first DDS participant:
    Fast DDS reads the variable once. Returns the profile set, or None."""
    rmw = environ.get("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
    if any(v in environ for v in PROFILE_VARIABLES) or not rmw.startswith("rmw_fastrtps"):
        return None
    profile = shipped_fastdds_profile()
    if profile is not None:
        for v in PROFILE_VARIABLES:
            environ[v] = str(profile)
    return profile


def main(args: list[str] | None = None) -> int:
    use_shipped_fastdds_profile()
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
