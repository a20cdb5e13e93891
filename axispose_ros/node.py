"""`axispose_node`: 6D poses of known objects from an RGB camera stream.

Inputs: `image` (sensor_msgs/Image) and `camera_info`, paired by stamp within `sync_slop`; the boxes to
estimate come from `~/roi/<object_name>` (sensor_msgs/RegionOfInterest, the latest one per object within
`roi_timeout` seconds), for users with their own detector; in `mode` auto or video_odometry, `camera_odom`
(nav_msgs/Odometry: the camera's optical frame in a fixed frame, nearest the image's stamp within `sync_slop`).
Outputs keep the image header:
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
(`outputs.py`), with its parameters (`params.py`: declared, typed and checked in one place), its counters
(`counters.py`) and the estimator's warm-up (`warmup.py`); it wires them and publishes the diagnostics.
`image` and `camera_info` use the sensor-data QoS (best effort): frames the transport discards never arrive and
are estimated from stamp gaps (`frames_lost_in_transport`, at most one per frame seen); stamps that are zero, go
back, lie in the future or jump are counted apart (`stamps_<anomaly>`), and such frames are still processed.

Between processes, Fast DDS's defaults lose most full-size images (its 512 KB shared-memory segment cannot hold
them in flight): `main` loads the shipped profile `config/fastdds_profile.xml` unless the user named one, and the
camera driver's process needs it too (README, "Beside a camera driver").
"""

from __future__ import annotations

import os
import sys
import time
from collections.abc import MutableMapping
from dataclasses import dataclass
from pathlib import Path

import rclpy
import rclpy.executors
import torch
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from nav_msgs.msg import Odometry
from rclpy.exceptions import ParameterException
from rclpy.node import Node
from rclpy.qos import qos_profile_sensor_data
from rclpy.qos_overriding_options import QoSOverridingOptions
from sensor_msgs.msg import CameraInfo, Image, RegionOfInterest

from axispose_core.camera import Camera
from axispose_core.checkpoint import CheckpointError
from axispose_core.estimator import Estimator
from axispose_core.tracking.poser import FramePoser
from axispose_ros import params
from axispose_ros.conversions import InputError, Undistorter, check_frame, image_to_rgb, stamp_seconds
from axispose_ros.counters import Counters
from axispose_ros.health import Health, HealthConfig
from axispose_ros.odometry import CameraPoses
from axispose_ros.outputs import PoseOutputs
from axispose_ros.params import DEFAULT_CHECKPOINT as DEFAULT_CHECKPOINT  # re-exported: the node's default
from axispose_ros.params import NodeSettings
from axispose_ros.sync import RoiStore, StampAudit, StampSynchronizer
from axispose_ros.warmup import warm_up
from axispose_ros.worker import InferenceWorker

FASTDDS_PROFILE_NAME = "fastdds_profile.xml"
PROFILE_VARIABLES = ("FASTRTPS_DEFAULT_PROFILES_FILE", "FASTDDS_DEFAULT_PROFILES_FILE")
"""The variables Fast DDS reads its XML profiles from: 2.x (Jazzy) and 3.x."""


def _load_estimator(checkpoint: str, device: str) -> Estimator:
    """`Estimator.load` on one thread, the caller's setting restored afterwards. Inference runs on its own thread
    with `num_threads` OpenMP threads (worker.py); if this thread also formed a team of several, libgomp would
    count more threads than cores and stop spinning between parallel regions: every small op of the sampler then
    waits on a futex, 20-30 % per frame."""
    caller_threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        return Estimator.load(checkpoint, device)
    finally:
        torch.set_num_threads(caller_threads)


@dataclass
class Frame:
    image: Image
    info: CameraInfo
    camera: Camera
    """The image's pinhole camera, checked on arrival (`check_frame`)."""
    received: float


class AxisPoseNode(Node):
    """Pose estimation node; raises CheckpointError/ValueError at construction for unusable parameters."""

    def __init__(self, **kwargs) -> None:
        super().__init__("axispose", **kwargs)
        settings = params.declare(self)
        self.rectified = settings.use_rectified  # start-only: read once, not per frame on the executor
        self.estimator = _load_estimator(settings.checkpoint, settings.device)
        self.precision = self.estimator.set_precision(settings.precision)
        self.names = {o.obj_id: o.name for o in self.estimator.config.objects}
        self.published = params.declare_objects(self, settings, self.names)
        self.add_on_set_parameters_callback(params.check_change)
        self.stats = Counters()
        self.counts = self.stats.counts
        self.rois = RoiStore()
        self.health = Health(HealthConfig(latency_budget_s=settings.latency_budget), time.monotonic())
        self.sync = StampSynchronizer(settings.sync_slop, self._on_pair, self._on_drop)
        self.stamps = StampAudit()
        self.worker: InferenceWorker[Frame] = InferenceWorker(self._process, self._warm_up, self._on_error, settings.num_threads)
        self.worker.start()  # warmed up: frames are taken only from here on
        qos_opts = QoSOverridingOptions.with_default_policies()
        self.create_subscription(Image, "image", self._on_image, qos_profile_sensor_data, qos_overriding_options=qos_opts)
        self.create_subscription(CameraInfo, "camera_info", self._on_info, qos_profile_sensor_data, qos_overriding_options=qos_opts)
        self.camera_poses = CameraPoses(lambda: self.stats.add("camera_odom_invalid"))
        self.create_subscription(Odometry, "camera_odom", self.camera_poses.on_message, 50)
        self.undistort = Undistorter()
        for obj_id, name in self.published.items():
            self.create_subscription(RegionOfInterest, f"~/roi/{name}", lambda m, i=obj_id: self._on_roi(i, m), 10)
        self.outputs = PoseOutputs(self, self.published)
        self.poser = FramePoser(self.estimator, self.published, self.stats.add, lambda: self.stats.snapshot().get("dropped_stale", 0))
        self.pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.create_timer(1.0, self._publish_diagnostics)

    def settings(self) -> NodeSettings:
        """The parameters now: those read per frame may have changed since start."""
        return params.read(self, self.names.values())

    def hypotheses(self) -> int:
        """AGM samples per object."""
        return self.settings().hypotheses

    def _scales(self) -> dict[int, float]:
        return self.settings().scales(self.names)

    # ------------------------------------------------------------------ inputs
    def _on_image(self, msg: Image) -> None:
        self.stats.add("frames_in")
        self.health.image(time.monotonic())
        stamp = stamp_seconds(msg.header)
        now = self.get_clock().now().nanoseconds * 1e-9  # a simulated clock reads 0 until /clock arrives: unknown
        verdict = self.stamps.add(stamp, now if now > 0 else None)
        if verdict.lost:  # the sensor-data QoS is best effort: what DDS dropped never arrives
            self.stats.add("frames_lost_in_transport", verdict.lost)
        if verdict.anomaly:
            self.stats.add(f"stamps_{verdict.anomaly}")
            self.get_logger().warning(f"image stamp {stamp:.9f}: {verdict.anomaly} (counted; the frame is still processed)",
                                      throttle_duration_sec=5.0)  # fmt: skip
        self.sync.add_image(stamp, msg)

    def _on_info(self, msg: CameraInfo) -> None:
        self.stats.add("camera_info_in")
        self.health.info(time.monotonic())
        self.sync.add_info(stamp_seconds(msg.header), msg)

    def _on_roi(self, obj_id: int, msg: RegionOfInterest) -> None:
        self.rois.add(obj_id, msg, time.monotonic())

    def _dropped(self, reason: str) -> None:
        """A frame dropped for a reason: its counter, and the health of the recent window."""
        self.stats.add(f"dropped_{reason}")
        self.health.drop(time.monotonic(), reason)

    def _on_drop(self, _: Image, reason: str) -> None:
        self._dropped(reason)
        self.get_logger().warning(f"dropped a frame: {reason}", throttle_duration_sec=5.0)

    def _on_pair(self, image: Image, info: CameraInfo) -> None:
        try:  # a frame the worker would refuse is counted here: it must neither go stale unseen nor displace a good one
            camera = check_frame(image, info, self.rectified)
        except InputError as err:
            self._on_error(err)
            return
        if self.worker.submit(Frame(image, info, camera, time.monotonic())):
            self.stats.add("dropped_stale")

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
        """Blank-frame passes for 1..`warmup_boxes` boxes, at most a batch (`warmup.py`): the first frames skip the setup."""
        s, start = self.settings(), time.monotonic()
        count = min(s.warmup_boxes, s.batch_boxes)
        try:
            if warm_up(self.estimator, list(self.published), count, s.hypotheses, self.worker.cancelled):
                self.get_logger().info(f"warmed up for 1-{count} boxes in {time.monotonic() - start:.1f} s")
        except Exception as err:
            self.get_logger().warning(f"warm-up failed ({err!r}); the first frames will be slower")

    def frames_done(self) -> int:
        """Frames that left the node: processed, or dropped for a reason."""
        return self.stats.frames_done()

    def counters(self) -> dict[str, int]:
        """A consistent copy of the counters (iterating `counts` while the other thread adds a key would fail)."""
        return self.stats.snapshot()

    def idle(self) -> bool:
        """No frame waits for, or is in, inference (frames still waiting for their CameraInfo do not count)."""
        return self.worker.idle()

    def _process(self, frame: Frame) -> None:
        s = self.settings()  # one frame, one set of parameters
        rgb, camera = image_to_rgb(frame.image), frame.camera
        if not self.rectified and Undistorter.needed(frame.info):
            rgb = self.undistort(frame.info, camera.K, rgb)
        rois, outside = self.rois.fresh(time.monotonic(), s.roi_timeout, rgb.shape[1], rgb.shape[0])
        if outside:
            self.stats.add("roi_outside", outside)
        stamp = stamp_seconds(frame.image.header)
        settings = s.poser(self.published)
        camera_pose = self.camera_poses.wait(stamp, s.sync_slop) if FramePoser.uses_odometry(settings) else None
        posed = self.poser.pose(rgb, camera.K, stamp, rois, settings, self.worker.cancelled, camera_pose)
        refused = self.outputs.publish(frame.image.header, posed, self.estimator, rgb, camera.K, s.marker_lifetime)
        if refused:
            self.stats.add("pose_refused", refused)
        self.stats.add("frames_processed")
        now = time.monotonic()
        self.stats.frame_latency(now - frame.received)
        self.health.output(now, now - frame.received)

    def _publish_diagnostics(self) -> None:
        status = DiagnosticStatus(name="axispose: pose estimation", hardware_id=self.get_name())
        status.level, status.message = self.health.judge(time.monotonic())  # the recent window; counters are totals
        status.values = self.stats.key_values(self.poser.choice.described())  # with the last frame's mode, and why
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self.get_clock().now().to_msg()
        self.pub_diag.publish(msg)

    def destroy_node(self) -> None:
        self.worker.stop()
        self.poser.stop()
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


def use_shipped_fastdds_profile(environ: MutableMapping[str, str] = os.environ) -> Path | None:
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
