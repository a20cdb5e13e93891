"""The node, launch-free: in-process executors with their own Context, a tiny random checkpoint (plumbing only)."""

import os
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
import rclpy
import torch
from conftest import TINY_AGM, save_tiny_estimator
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseArray, PoseStamped, PoseWithCovarianceStamped
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from sensor_msgs.msg import CameraInfo, Image, RegionOfInterest
from visualization_msgs.msg import Marker, MarkerArray

from axispose_core.agm.model import AxisGenerator
from axispose_core.checkpoint import CheckpointError
from axispose_core.estimator import Estimator, bf16_native
from axispose_core.estimator_checkpoint import EstimatorConfig
from axispose_core.lmo import LMO_K
from axispose_core.localiser.model import Localiser, LocaliserConfig
from axispose_core.localiser.verifier import DetectionVerifier
from axispose_core.objects import lmo_objects
from axispose_core.pose_estimate import PoseEstimate
from axispose_core.tbm.reader import SHIPPED_READER, load_reader
from axispose_core.trunks import ResidualBNConfig
from axispose_msgs.msg import DetectionArray
from axispose_ros.node import AxisPoseNode


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    return save_tiny_estimator(tmp_path_factory.mktemp("ckpt") / "tiny.safetensors")  # ape (1), can (5)


class Harness:
    """The node under test plus a peer node, spun by one executor in a private Context."""

    def __init__(self, checkpoint, **params):
        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx)
        overrides = [Parameter("checkpoint", value=str(checkpoint))]
        overrides += [Parameter(k, value=v) for k, v in ({"num_threads": 1, "warmup_boxes": 0} | params).items()]
        self.node = AxisPoseNode(context=self.ctx, parameter_overrides=overrides)
        self.peer = rclpy.create_node("peer", context=self.ctx)
        self.exe = SingleThreadedExecutor(context=self.ctx)
        self.exe.add_node(self.node)
        self.exe.add_node(self.peer)
        self.got: dict[str, list] = {"pose": [], "array": [], "debug": [], "diag": [], "ape": [], "cov": [], "det": []}
        self.pub_image = self.peer.create_publisher(Image, "image", 10)
        self.pub_info = self.peer.create_publisher(CameraInfo, "camera_info", 10)
        self.pub_roi = self.peer.create_publisher(RegionOfInterest, "/axispose/roi/ape", 10)
        self.peer.create_subscription(PoseStamped, "/axispose/pose", self.got["pose"].append, 10)
        self.peer.create_subscription(PoseStamped, "/axispose/poses/ape", self.got["ape"].append, 10)
        self.peer.create_subscription(PoseWithCovarianceStamped, "/axispose/pose_cov", self.got["cov"].append, 10)
        self.peer.create_subscription(PoseArray, "/axispose/pose_array", self.got["array"].append, 10)
        self.peer.create_subscription(DetectionArray, "/axispose/detections", self.got["det"].append, 10)
        self.peer.create_subscription(DiagnosticArray, "/diagnostics", self.got["diag"].append, 10)

    def subscribe_debug(self):
        self.peer.create_subscription(Image, "/axispose/debug/axis_image", self.got["debug"].append, 10)

    def spin_until(self, cond, timeout=20.0):
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            self.exe.spin_once(timeout_sec=0.05)
            if cond():
                return True
        return False

    def frame(self, sec=1, encoding="rgb8", K=LMO_K, size=(640, 480), info_size=(640, 480), with_info=True, rows=None):
        """Publish a frame of random pixels and its CameraInfo; `rows`: send only that many rows of data."""
        w, h = size
        img = Image(height=h, width=w, encoding=encoding, step=w * 3)
        img.header.frame_id = "cam"
        img.header.stamp.sec = sec
        img.data = np.random.default_rng(sec).integers(0, 255, (h if rows is None else rows) * w * 3, dtype=np.uint8).tobytes()
        if with_info:
            info = CameraInfo(width=info_size[0], height=info_size[1])
            info.header = img.header
            info.k = [float(v) for v in np.asarray(K).ravel()]
            self.pub_info.publish(info)
        self.pub_image.publish(img)
        return img

    def roi(self):
        self.pub_roi.publish(RegionOfInterest(x_offset=280, y_offset=200, width=80, height=90))

    def close(self):
        self.exe.shutdown()
        self.node.destroy_node()
        self.peer.destroy_node()
        rclpy.shutdown(context=self.ctx)


@pytest.fixture
def harness(checkpoint):
    h = Harness(checkpoint)
    h.spin_until(lambda: h.pub_image.get_subscription_count() > 0 and h.pub_roi.get_subscription_count() > 0, 5.0)
    yield h
    h.close()


def test_pose_array_keeps_the_image_header_and_is_empty_without_boxes(harness):
    sent = harness.frame(sec=3)
    assert harness.spin_until(lambda: harness.got["array"])
    msg = harness.got["array"][0]
    assert msg.header.stamp.sec == sent.header.stamp.sec and msg.header.frame_id == "cam"
    assert msg.poses == []
    assert harness.spin_until(lambda: harness.got["det"])
    assert harness.got["det"][0].header == msg.header and list(harness.got["det"][0].detections) == []


def test_precision_auto_takes_bfloat16_only_where_the_device_has_it(harness):
    assert harness.node.get_parameter("precision").value == "auto"
    assert harness.node.precision == ("bfloat16" if bf16_native(torch.device("cpu")) else "float32")
    assert harness.node.estimator.bf16 == (harness.node.precision == "bfloat16")
    assert not harness.node.set_parameters([Parameter("precision", value="float32")])[0].successful  # at start only


def test_inference_thread_has_num_threads_and_the_callers_setting_is_left_alone(checkpoint):
    """The node loads on one thread and restores the caller's count; its inference thread sets `num_threads` for
    itself (two OpenMP teams of several threads on two cores put libgomp in its slow, non-spinning mode)."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)  # the caller's setting differs from the node's, so either leaking shows
    h = Harness(checkpoint, num_threads=2)
    try:
        assert torch.get_num_threads() == 1
        seen, real = [], h.node.estimator.estimate

        def spy(*args, **kwargs):
            seen.append((threading.current_thread().name, torch.get_num_threads()))
            return real(*args, **kwargs)

        h.node.estimator.estimate = spy
        h.spin_until(lambda: h.pub_image.get_subscription_count() > 0, 5.0)
        h.frame(sec=7)
        assert h.spin_until(lambda: h.got["array"])
        assert seen == [("axispose_inference", 2)]
    finally:
        h.close()
        torch.set_num_threads(before)


def test_warm_up_runs_each_box_count_once_on_the_inference_thread_before_frames_are_taken(checkpoint, monkeypatch):
    calls, real = [], Estimator.estimate

    def spy(self, image, K, boxes, **kwargs):
        calls.append((threading.current_thread().name, len(boxes), kwargs["options"].steps, kwargs["options"].hypotheses))
        return real(self, image, K, boxes, **kwargs)

    monkeypatch.setattr(Estimator, "estimate", spy)
    h = Harness(checkpoint, warmup_boxes=3, hypotheses=2)
    try:
        assert calls == [("axispose_inference", k, 1, 2) for k in (1, 2, 3)]  # done before the constructor returned
        h.spin_until(lambda: h.pub_image.get_subscription_count() > 0, 5.0)
        h.frame(sec=9)
        assert h.spin_until(lambda: h.got["array"])
        assert len(calls) == 4 and h.node.counters().get("frames_processed") == 1
    finally:
        h.close()


def test_pose_stamped_for_a_box_with_the_same_header(harness):
    real = harness.node.estimator.estimate

    def succeed(*args, **kwargs):  # the random checkpoint draws noise: fix the pose, keep the plumbing
        out = real(*args, **kwargs)
        return [
            PoseEstimate(e.obj_id, np.eye(3), np.array([0.0, 0.0, 0.8]), True, "", e.axis_image, e.K_patch, e.center, e.side) for e in out
        ]

    harness.node.estimator.estimate = succeed
    harness.roi()
    harness.spin_until(lambda: harness.node.rois.latest(1) is not None, 5.0)
    sent = harness.frame(sec=5)
    assert harness.spin_until(lambda: harness.got["ape"])
    got = harness.got["ape"][0]
    assert (got.header.stamp.sec, got.header.frame_id) == (sent.header.stamp.sec, "cam")
    assert got.pose.position.z == pytest.approx(0.8) and got.pose.orientation.w == pytest.approx(1.0)
    assert harness.spin_until(lambda: harness.got["pose"] and harness.got["array"])  # published after the per-object topics
    assert len(harness.got["array"][-1].poses) == 1 and harness.got["pose"][0].header == got.header
    assert harness.got["debug"] == []  # nobody subscribed: no debug image built
    assert harness.got["cov"] == []  # a pose without a covariance publishes none
    assert harness.spin_until(lambda: harness.got["det"])
    (det,) = harness.got["det"][0].detections
    assert harness.got["det"][0].header == got.header
    assert (det.obj_id, det.name, det.score) == (1, "ape", 1.0)  # an ROI's box scores 1
    assert det.pose.pose == got.pose and not np.any(det.pose.covariance)  # covariance unknown: all zeros
    np.testing.assert_allclose(det.box, [280, 200, 80, 90])


def test_pose_cov_carries_the_estimators_covariance(harness):
    real = harness.node.estimator.estimate
    calls = []
    cov = np.diag([1e-4, 2e-4, 9e-4, 0.01, 0.02, 0.03])
    cov[0, 5] = cov[5, 0] = 1e-5

    def succeed(*args, **kwargs):
        calls.append(kwargs["options"].hypotheses)
        spread = {"samples": 4, "samples_ok": 4, "spread_deg": 3.0, "spread_m": 0.01, "covariance": cov}
        return [
            PoseEstimate(e.obj_id, np.eye(3), np.array([0.0, 0.0, 0.8]), True, "", e.axis_image, e.K_patch, e.center, e.side, **spread)
            for e in real(*args, **kwargs)
        ]

    harness.node.estimator.estimate = succeed
    harness.roi()
    harness.spin_until(lambda: harness.node.rois.latest(1) is not None, 5.0)
    sent = harness.frame(sec=6)
    assert harness.spin_until(lambda: harness.got["cov"])
    got = harness.got["cov"][0]
    assert calls == [1]  # the node's default: one sample; its covariance is the dense fusion's
    assert got.header.stamp.sec == sent.header.stamp.sec and got.pose.pose.position.z == pytest.approx(0.8)
    np.testing.assert_allclose(np.reshape(got.pose.covariance, (6, 6)), cov)
    assert harness.spin_until(lambda: harness.got["det"])
    np.testing.assert_allclose(np.reshape(harness.got["det"][0].detections[0].pose.covariance, (6, 6)), cov)


def test_debug_image_only_when_subscribed(harness):
    harness.subscribe_debug()
    harness.spin_until(lambda: harness.node.outputs.pub_debug.get_subscription_count() > 0, 5.0)
    harness.roi()
    harness.spin_until(lambda: harness.node.rois.latest(1) is not None, 5.0)
    harness.frame(sec=7)
    assert harness.spin_until(lambda: harness.got["debug"])
    assert harness.got["debug"][0].header.stamp.sec == 7 and harness.got["debug"][0].encoding == "rgb8"


@pytest.mark.parametrize(
    "kwargs, counter",
    [
        ({"encoding": "16UC1"}, "dropped_encoding"),
        ({"K": np.full((3, 3), np.nan)}, "dropped_camera_info_k"),
        ({"K": np.zeros((3, 3))}, "dropped_camera_info_k"),
        ({"info_size": (640, 400)}, "dropped_camera_info_mismatch"),
        ({"K": [[572.4, 0, 1e9], [0, 573.6, 242.0], [0, 0, 1]]}, "dropped_camera_info_principal_point"),  # the fuzz run's
        ({"K": [[1e-12, 0, 325.3], [0, 1e-12, 242.0], [0, 0, 1]]}, "dropped_camera_info_focal_length"),  # the fuzz run's
    ],
)
def test_bad_input_is_dropped_and_counted(harness, kwargs, counter):
    """Refused at the check, under its own reason: no such frame reaches inference (the fuzz run's absurd but finite
    K used to fail there, counted as dropped_error)."""
    calls, real = [], harness.node.estimator.estimate
    harness.node.estimator.estimate = lambda *a, **k: calls.append(1) or real(*a, **k)
    harness.frame(sec=9, **kwargs)
    assert harness.spin_until(lambda: harness.node.counts[counter] >= 1)
    assert not calls and "dropped_error" not in harness.node.counters()
    harness.frame(sec=11)  # still alive and processing
    assert harness.spin_until(lambda: harness.node.counts["frames_processed"] >= 1)


def test_bad_frames_are_counted_as_they_arrive_while_the_worker_is_busy(harness):
    """Frames the worker would refuse are refused on arrival: each is counted under its reason even while a slow
    frame holds the worker, and none of them takes the waiting good frame's place (no dropped_stale)."""
    real = harness.node.poser.pose
    harness.node.poser.pose = lambda *a, **k: time.sleep(1.5) or real(*a, **k)
    counts = harness.node.counts

    def send(n: int, **kwargs) -> None:  # one at a time: a burst of large best-effort messages loses some in transport
        harness.frame(**kwargs)
        assert harness.spin_until(lambda: counts["frames_in"] >= n, 5.0)

    send(1, sec=40)
    assert harness.spin_until(lambda: not harness.node.worker.idle(), 5.0)
    send(2, sec=41)  # waits in the slot behind the slow frame
    for k in range(3):
        send(3 + 2 * k, sec=42 + 2 * k, rows=100)
        send(4 + 2 * k, sec=43 + 2 * k, info_size=(640, 400))
    assert harness.spin_until(lambda: counts["dropped_image_data"] == 3 and counts["dropped_camera_info_mismatch"] == 3, 2.0)
    assert harness.spin_until(lambda: counts["frames_processed"] >= 2, 10.0)
    assert "dropped_stale" not in harness.node.counters()


def test_diagnostics_stop_saying_ok_when_frames_stop_going_through(harness):
    """One good frame, then only frames it must drop: the health of the recent window is no longer OK."""
    harness.frame(sec=300)
    assert harness.spin_until(lambda: harness.node.counts["frames_processed"] >= 1)
    for k in range(6):
        harness.frame(sec=301 + k, encoding="16UC1")
        harness.spin_until(lambda n=k: harness.node.counts["dropped_encoding"] >= n + 1, 2.0)

    def warned() -> bool:
        return any(s.level != DiagnosticStatus.OK and "dropped" in s.message for d in harness.got["diag"] for s in d.status)

    assert harness.spin_until(warned, 5.0)


def test_counters_are_safe_to_read_while_the_other_thread_adds_keys(harness):
    """The executor reads the counters (diagnostics, frames_done) while drops add new keys from another thread."""
    import threading

    node, errors = harness.node, []

    def drops() -> None:
        for k in range(300):
            node._on_drop(None, f"race{k}")

    writer = threading.Thread(target=drops)
    writer.start()
    reads = 0
    while writer.is_alive():
        try:
            node.frames_done()
            if reads % 200 == 0:
                node._publish_diagnostics()
            reads += 1
        except RuntimeError as err:  # "dictionary changed size during iteration"
            errors.append(err)
            break
    writer.join()
    assert not errors and node.counters()["dropped_race299"] == 1


def test_distinct_bad_encodings_share_one_counter(harness):
    """A stream of ever new encoding strings (one with a newline) must not grow the counters or the diagnostics."""
    for k in range(30):
        harness.frame(sec=200 + k, encoding=f"junk{k}\nINJECTED" if k == 0 else f"junk{k}")
        harness.spin_until(lambda n=k: harness.node.frames_done() >= n + 1, 2.0)
    assert harness.spin_until(lambda: harness.node.counts["dropped_encoding"] >= 1)
    assert [k for k in harness.node.counts if "encoding" in k] == ["dropped_encoding"]


def test_image_without_camera_info_is_dropped(harness):
    harness.frame(sec=20, with_info=False)
    harness.frame(sec=21)  # its CameraInfo is later than the first image + slop
    assert harness.spin_until(lambda: harness.node.counts["dropped_no_camera_info"] >= 1)


def test_image_scaled_uniformly_from_camera_info_is_handled(harness):
    harness.frame(sec=30, size=(320, 240), info_size=(640, 480))
    assert harness.spin_until(lambda: harness.node.counts["frames_processed"] >= 1)


def test_diagnostics_report_counts_and_the_mode(harness):
    harness.frame(sec=40)
    assert harness.spin_until(lambda: any(s.values for d in harness.got["diag"] for s in d.status if "processed" in s.message), 10.0)
    values = {v.key: v.value for d in harness.got["diag"] for s in d.status for v in s.values}
    assert values["mode"] == "stills" and "localiser" in values["mode_reason"]  # the harness's checkpoint has none


def test_parameters_are_validated_at_start_and_at_run_time(checkpoint, tmp_path):
    with pytest.raises(CheckpointError, match="not found"):
        Harness(tmp_path / "missing.safetensors")
    with pytest.raises(ValueError, match="not in the checkpoint"):
        Harness(checkpoint, objects=["teapot"])
    with pytest.raises(rclpy.exceptions.InvalidParameterValueException):
        Harness(checkpoint, ddim_steps=0)
    with pytest.raises(ValueError, match="stills, video, video_odometry, auto"):
        Harness(checkpoint, mode="tracking")
    with pytest.raises(ValueError, match="'follow' was removed; use mode"):
        Harness(checkpoint, follow=True)
    h = Harness(checkpoint, objects=["ape"])
    try:
        assert h.node.set_parameters([Parameter("ddim_steps", value=0)])[0].successful is False
        assert h.node.set_parameters([Parameter("ddim_steps", value=8)])[0].successful
        assert h.node.get_parameter("ddim_steps").value == 8
        assert h.node.set_parameters([Parameter("checkpoint", value="x")])[0].successful is False
        assert h.node.set_parameters([Parameter("mode", value="tracking")])[0].successful is False
        assert h.node.set_parameters([Parameter("mode", value="video")])[0].successful and h.node.settings().mode == "video"
        assert h.node.set_parameters([Parameter("object_scales.ape", value=-1.0)])[0].successful is False
        assert h.node.set_parameters([Parameter("object_scales.ape", value=0.06)])[0].successful
        assert h.node._scales() == {1: 0.06}
        assert set(h.node.outputs.pub_object) == {1}  # only 'ape' is published
    finally:
        h.close()


def test_burst_of_300_frames_stays_bounded(harness):
    def rss_mb():
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20

    harness.frame(sec=50)
    harness.spin_until(lambda: harness.node.counts["frames_processed"] >= 1)
    start = rss_mb()
    for k in range(300):
        harness.frame(sec=100 + k)
        harness.exe.spin_once(timeout_sec=0.0)
    node = harness.node

    def accounted() -> bool:
        """Every frame that came in was processed, dropped with a reason, or still waits in a bounded place."""
        c = node.counts
        dropped = sum(v for k, v in c.items() if k.startswith("dropped_"))
        # Sensor-data QoS (best effort, depth 5) lets DDS itself discard part of a burst: fewer than 300 arrive.
        return c["frames_in"] >= 30 and c["frames_in"] == c["frames_processed"] + dropped + len(node.sync.images)

    assert harness.spin_until(accounted, 60.0), dict(node.counts)
    assert len(node.sync.images) <= node.sync.max_images and node.worker.idle()
    assert rss_mb() - start < 200


def test_clean_shutdown_with_frames_in_flight(checkpoint):
    h = Harness(checkpoint)
    for k in range(5):
        h.frame(sec=200 + k)
        h.exe.spin_once(timeout_sec=0.01)
    h.close()
    assert not h.node.worker.alive()


def test_shutdown_mid_frame_is_prompt_even_with_1000_ddim_steps(checkpoint):
    """A frame in the AGM with ddim_steps 1000 (each step slowed to 10 ms: 10 s a frame) is abandoned between two
    steps when the node shuts down: the worker is gone long before the frame's remaining steps (at least 9 s)
    could have run, nothing counted as dropped. The bound leaves a busy host room for the shutdown itself."""
    h = Harness(checkpoint, ddim_steps=1000)
    denoiser = h.node.estimator.agm.denoiser
    real_forward = denoiser.forward

    def slow(*args, **kwargs):
        time.sleep(0.01)
        return real_forward(*args, **kwargs)

    denoiser.forward = slow
    try:
        h.spin_until(lambda: h.pub_roi.get_subscription_count() > 0, 5.0)
        h.roi()
        assert h.spin_until(lambda: h.node.rois.latest(1) is not None, 5.0)
        h.frame(sec=300)
        assert h.spin_until(lambda: h.node.worker.busy, 10.0)
        time.sleep(0.5)  # well inside the 1000 steps
    finally:
        start = time.monotonic()
        h.close()
    assert time.monotonic() - start < 4.0 and not h.node.worker.alive()
    assert not any(k.startswith("dropped_") for k in h.node.counters()) and not h.node.counters().get("frames_processed")


def test_with_a_refiner_every_pose_is_counted_and_bad_input_is_answered_as_before(tmp_path, lmo_dir):
    """A checkpoint with a contour refiner: each posed instance ends in `refine_refined` or one `refine_kept_<why>`;
    bad frames are still dropped under their reason; `refine` off at run time stops the refiner on the next frame."""
    h = Harness(save_tiny_estimator(tmp_path / "refine.safetensors", lmo_dir / "models"))
    try:
        assert h.node.estimator.refiner is not None
        h.spin_until(lambda: h.pub_roi.get_subscription_count() > 0, 5.0)
        h.roi()
        assert h.spin_until(lambda: h.node.rois.latest(1) is not None, 5.0)
        h.frame(sec=1)
        assert h.spin_until(lambda: h.node.counts["frames_processed"] >= 1)
        refined = {k: v for k, v in h.node.counters().items() if k.startswith("refine_")}
        assert sum(refined.values()) + h.node.counts["pose_refused"] == 1, refined
        h.frame(sec=2, K=np.full((3, 3), np.nan))
        assert h.spin_until(lambda: h.node.counts["dropped_camera_info_k"] >= 1)
        assert h.node.set_parameters([Parameter("refine", value=False)])[0].successful
        h.roi()
        h.frame(sec=3)
        assert h.spin_until(lambda: h.node.counts["frames_processed"] >= 2)
        assert {k: v for k, v in h.node.counters().items() if k.startswith("refine_")} == refined
        assert "dropped_error" not in h.node.counters()
    finally:
        h.close()


@pytest.mark.parametrize("mode", ["video", "auto"])
def test_following_tracks_by_their_contours_runs_the_frames_and_counts_them(tmp_path, lmo_dir, mode):
    """`video` (the tracks followed by their contours) on a checkpoint with a localiser and a refiner, with the camera's
    pose on camera_odom: every frame ends in frames_processed, each counted as followed or estimated by the tracker;
    an odometry message that is no pose is counted; nothing fails. In `video_odometry` the localiser and the AGM
    search frames in a process of their own (the node stops it): `auto` runs it on the frames with the camera's pose,
    and `video` on the one whose odometry was no pose; `/diagnostics` counts the frames of each mode."""
    reader = load_reader(SHIPPED_READER)
    cfg = EstimatorConfig(agm=TINY_AGM, reader=reader.config, objects=tuple(lmo_objects()[:2]), ddim_steps=1)
    localiser = Localiser(LocaliserConfig(obj_ids=(1, 5), input_size=(160, 128), trunk=ResidualBNConfig(widths=(8, 16, 24, 32))))
    from axispose_core.data.meshes import refiner_meshes

    path = tmp_path / "follow.safetensors"
    est = Estimator(cfg, AxisGenerator(cfg.agm), reader).with_localiser(localiser)
    est.with_refiner(refiner_meshes(lmo_dir / "models", [1, 5])).save(path)
    h = Harness(path, score_threshold=0.0, mode=mode, view_window=5)
    background = mode != "video"
    from nav_msgs.msg import Odometry

    odom = h.peer.create_publisher(Odometry, "camera_odom", 50)
    try:
        for sec in range(1, 4):  # the camera's pose comes on camera_odom, a non-pose among them
            msg = Odometry()
            msg.header.stamp.sec = sec
            msg.pose.pose.position.x, msg.pose.pose.orientation.w = 0.01 * sec, 1.0 if sec != 2 else 0.0
            odom.publish(msg)
            assert h.spin_until(lambda s=sec: h.node.camera_poses.at(s, 0.01) is not None or h.node.counts.get("camera_odom_invalid"))
            h.frame(sec=sec)
            assert h.spin_until(lambda s=sec: h.node.counts["frames_processed"] >= s)
        counts = h.node.counters()
        assert counts.get("tracking_frames_estimated", 0) + counts.get("tracking_frames_followed", 0) == 3
        assert counts["camera_odom_invalid"] == 1 and h.node.camera_poses.at(3.0, 0.01)[0, 3] == pytest.approx(0.03)
        assert "dropped_error" not in counts and "background_failed" not in counts
        assert (counts.get("background_searches", 0) > 0) == background
        expected = {"video": {"video": 3}, "auto": {"video_odometry": 2, "video": 1}}
        assert {k[len("mode_") :]: n for k, n in counts.items() if k.startswith("mode_")} == expected[mode]
        assert h.node.poser.choice.mode.value == ("video" if not background else "video_odometry")
    finally:
        h.close()
    assert h.node.poser._finder is None or not h.node.poser._finder.alive()


@pytest.fixture(scope="module")
def localised_checkpoint(tmp_path_factory):
    """The tiny estimator with an untrained localiser of ape and can: at threshold 0 it finds both, twice each."""
    reader = load_reader(SHIPPED_READER)
    trunk = ResidualBNConfig(widths=(8, 16, 24, 32))
    localiser = Localiser(LocaliserConfig(obj_ids=(1, 5), input_size=(160, 128), trunk=trunk, max_per_object=2))
    cfg = EstimatorConfig(
        agm=TINY_AGM, reader=reader.config,
        objects=tuple(lmo_objects()[:2]), ddim_steps=1,
    )  # fmt: skip
    path = tmp_path_factory.mktemp("loc") / "loc.safetensors"
    Estimator(cfg, AxisGenerator(cfg.agm), reader).with_localiser(localiser).save(path)
    return path


def test_without_rois_the_checkpoints_localiser_finds_the_objects(localised_checkpoint):
    """An untrained localiser at threshold 0 yields max_per_object detections per object: every one is estimated
    (published or refused); at threshold 1, set at run time, none is and the PoseArray is empty."""
    h = Harness(localised_checkpoint, score_threshold=0.0)
    try:
        h.spin_until(lambda: h.pub_image.get_subscription_count() > 0, 5.0)
        h.frame(sec=11)
        assert h.spin_until(lambda: h.got["array"])
        assert len(h.got["array"][0].poses) + h.node.counts["pose_refused"] == 4
        assert h.node.set_parameters([Parameter("score_threshold", value=1.0)])[0].successful
        h.frame(sec=12)
        assert h.spin_until(lambda: len(h.got["array"]) == 2)
        assert h.got["array"][1].poses == []
    finally:
        h.close()


def _fixed_poses(node):
    """Make the node's estimator succeed with a fixed pose per box (the random AGM draws noise) and record its calls."""
    real, calls = node.estimator.estimate, []

    def succeed(image, K, boxes, **kwargs):
        calls.append([obj_id for obj_id, _ in boxes])
        out = real(image, K, boxes, **kwargs)
        return [PoseEstimate(e.obj_id, np.eye(3), np.array([0.0, 0.0, 0.8]), True, "", e.axis_image, e.K_patch, e.center, e.side)
                for e in out]  # fmt: skip

    node.estimator.estimate = succeed
    return calls


def test_objects_not_asked_for_are_neither_estimated_nor_published(localised_checkpoint):
    """With objects:=[ape] the localiser's can detections never reach the AGM, the PoseArray or the markers; every
    frame's MarkerArray first deletes the last frame's, then gives each instance its own ids and a lifetime."""
    h = Harness(localised_checkpoint, score_threshold=0.0, objects=["ape"], marker_lifetime=0.5)
    markers = []
    h.peer.create_subscription(MarkerArray, "/axispose/markers", markers.append, 10)
    try:
        calls = _fixed_poses(h.node)
        h.spin_until(lambda: h.pub_image.get_subscription_count() > 0, 5.0)
        h.frame(sec=21)
        assert h.spin_until(lambda: h.got["array"] and markers)
        assert calls == [[1, 1]] and len(h.got["array"][0].poses) == 2
        assert h.spin_until(lambda: h.got["det"])
        dets = h.got["det"][0].detections
        assert [(d.obj_id, d.name) for d in dets] == [(1, "ape"), (1, "ape")]
        assert all(0.0 <= d.score < 1.0 and d.box[2] > 0 and d.box[3] > 0 for d in dets)  # the localiser's scores and boxes
        first, *arrows = markers[0].markers
        assert first.action == Marker.DELETEALL
        assert sorted(m.id for m in arrows) == [0, 1, 2, 3, 4, 5] and {m.ns for m in arrows} == {"axispose/ape"}
        assert all(m.lifetime.sec == 0 and m.lifetime.nanosec == 500_000_000 for m in arrows)
        assert h.peer.count_subscribers("/axispose/roi/ape") == 1 and h.peer.count_subscribers("/axispose/roi/can") == 0
    finally:
        h.close()


@pytest.mark.parametrize("constant", [-3.0, 2.0])
def test_the_checkpoints_verifier_sets_the_published_score_and_its_drops_are_counted(localised_checkpoint, tmp_path, constant):
    """A verifier whose probability is sigmoid(constant) whatever the detection: below the threshold every detection
    of the untrained localiser (ape and can, twice each) is dropped and counted, above it every one is published with
    that score."""
    est = Estimator.load(localised_checkpoint)
    path = tmp_path / "verified.safetensors"
    est.with_verifier(DetectionVerifier((0.0, 0.0, 0.0, constant), min_score=1e-3)).save(path)
    h = Harness(path, score_threshold=0.3)
    try:
        _fixed_poses(h.node)
        h.spin_until(lambda: h.pub_image.get_subscription_count() > 0, 5.0)
        h.frame(sec=31)
        assert h.spin_until(lambda: h.got["det"])
        scores = [d.score for d in h.got["det"][0].detections]
        if constant < 0:
            assert scores == [] and h.node.counters()["verifier_dropped"] == 4
        else:
            assert scores == pytest.approx([1 / (1 + np.exp(-constant))] * 4, abs=1e-6) and "verifier_dropped" not in h.node.counters()
    finally:
        h.close()


def test_with_tracking_a_verified_detection_is_posed_once(localised_checkpoint, tmp_path):
    """In `video`, the verifier's poses of a frame's detections start the tracks: the localiser's frame goes
    through the AGM once, not once to score and again to track."""
    path = tmp_path / "verified.safetensors"
    Estimator.load(localised_checkpoint).with_verifier(DetectionVerifier((0.0, 0.0, 0.0, 2.0), min_score=1e-3)).save(path)
    h = Harness(path, score_threshold=0.3, mode="video")
    try:
        calls = _fixed_poses(h.node)
        h.spin_until(lambda: h.pub_image.get_subscription_count() > 0, 5.0)
        h.frame(sec=41)
        assert h.spin_until(lambda: h.got["det"])
        assert [sorted(c) for c in calls] == [[1, 1, 5, 5]] and len(h.got["det"][0].detections) == 4
    finally:
        h.close()


def test_frames_lost_in_transport_are_estimated_from_stamp_gaps(harness):
    for sec in (*range(70, 77), 79):  # a steady 1 s camera, then two frames that never arrived
        harness.frame(sec=sec)
        assert harness.spin_until(lambda s=sec: harness.node.stamps.last == s, 5.0)
    assert harness.node.counters().get("frames_lost_in_transport") == 2


def test_stamps_that_say_nothing_about_loss_have_their_own_counters(harness):
    """The fuzz run's stamps (zero, far future, back in time, a long pause) read 828,192,373,372 frames lost with
    nothing lost. Each is counted under its own anomaly, the frames are still answered, and nothing is lost."""
    future = int(time.time()) + 86_400
    for sec in (*range(80, 86), 0, future, 83, *range(86, 90), 5000):
        harness.frame(sec=sec)
        harness.spin_until(lambda n=harness.node.counts["frames_in"]: harness.node.counts["frames_in"] > n, 5.0)
    node = harness.node
    assert harness.spin_until(lambda: node.frames_done() + len(node.sync.images) == node.counts["frames_in"] == 14, 20.0)
    counts = node.counters()
    assert counts.get("frames_lost_in_transport", 0) == 0
    assert {k: v for k, v in counts.items() if k.startswith("stamps_")} == {
        "stamps_zero": 1, "stamps_future": 1, "stamps_backwards": 1, "stamps_discontinuity": 1,
    }  # fmt: skip
    assert counts["camera_info_in"] == 14


def test_an_unsupported_lens_model_drops_the_frame_with_a_reason(harness):
    info = CameraInfo(width=640, height=480, distortion_model="fov", d=[0.9])
    info.header.stamp.sec = 61
    info.k = [float(v) for v in np.asarray(LMO_K).ravel()]
    img = Image(height=480, width=640, encoding="rgb8", step=640 * 3, data=bytes(640 * 480 * 3))
    img.header.stamp.sec = 61
    harness.pub_info.publish(info)
    harness.pub_image.publish(img)
    assert harness.spin_until(lambda: harness.node.counters().get("dropped_distortion_model") == 1)
    assert not harness.got["array"]


@pytest.mark.slow
@pytest.mark.parametrize(
    "param",
    ["ddim_steps:=0", "ddim_steps:=abc", "sync_slop:=-1.0", "num_threads:=0", "device:=cuda", "precision:=half", "tracking:=true"],
)  # fmt: skip
def test_bad_parameters_at_start_are_one_line_and_exit_2(checkpoint, param):
    """Out of range, of the wrong type, a device this torch has not, or a parameter the node no longer has: one clear
    line, exit code 2, no traceback; a removed one names what replaced it."""
    if param == "device:=cuda" and torch.cuda.is_available():
        pytest.skip("this machine has CUDA")
    proc = subprocess.run(
        [sys.executable, "-m", "axispose_ros.node", "--ros-args", "-p", f"checkpoint:={checkpoint}", "-p", param],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1 and lines[0].startswith("axispose_node: "), proc.stderr
    assert param.split(":=")[0] in lines[0] and "Traceback" not in proc.stderr
    assert ("video_odometry" in lines[0]) == param.startswith("tracking")
