"""Images from a camera driver in another process, as a robot stack runs the node: over Fast DDS's shared memory,
full-size frames only arrive with the shipped profile (config/fastdds_profile.xml) on the camera's side; the node
loads it itself. Without it, 150-190 of 300 frames arrived at 15 Hz, and 7 of 20 at 2 Hz."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import rclpy
from conftest import save_tiny_estimator
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.executors import SingleThreadedExecutor

from axispose_msgs.msg import DetectionArray
from axispose_ros.node import PROFILE_VARIABLES, shipped_fastdds_profile, use_shipped_fastdds_profile

REPO = Path(__file__).resolve().parents[1]
FRAMES, RATE = 150, 15.0


def test_the_shipped_profile_is_found_and_a_users_choice_is_kept():
    profile = shipped_fastdds_profile()
    assert profile == REPO / "config" / "fastdds_profile.xml"
    env: dict[str, str] = {}
    assert use_shipped_fastdds_profile(env) == profile and all(env[v] == str(profile) for v in PROFILE_VARIABLES)
    own = {"FASTRTPS_DEFAULT_PROFILES_FILE": "/etc/mine.xml"}
    assert use_shipped_fastdds_profile(own) is None and own == {"FASTRTPS_DEFAULT_PROFILES_FILE": "/etc/mine.xml"}
    cyclone = {"RMW_IMPLEMENTATION": "rmw_cyclonedds_cpp"}
    assert use_shipped_fastdds_profile(cyclone) is None and cyclone == {"RMW_IMPLEMENTATION": "rmw_cyclonedds_cpp"}


def _counters(msg: DiagnosticArray) -> dict[str, int]:
    return {kv.key: int(kv.value) for s in msg.status for kv in s.values if kv.value.isdigit()}


@pytest.mark.slow
def test_full_size_frames_from_another_process_all_arrive_and_are_answered(tmp_path):
    """150 frames of 640x480 rgb8 (921,600 B) with their CameraInfo at 15 Hz, from a camera process that carries
    the shipped profile (as the README tells), to `axispose_node` started by its entry point: every frame arrives,
    every one is answered (a DetectionArray) or counted (`dropped_stale`: a newer frame replaced it), and each
    answered frame's box came back as a pose or was counted as refused (the tiny random checkpoint's are)."""
    checkpoint = save_tiny_estimator(tmp_path / "tiny.safetensors")
    domain = 101 + os.getpid() % 100  # of its own: no cross-talk with the other tests' nodes, nor theirs with it
    env = {k: v for k, v in os.environ.items() if k not in PROFILE_VARIABLES}
    env |= {"ROS_DOMAIN_ID": str(domain), "ROS_LOG_DIR": str(tmp_path / "log"), "PYTHONUNBUFFERED": "1"}
    profile = shipped_fastdds_profile()
    remaps = ["-r", "image:=/camera/color/image_raw", "-r", "camera_info:=/camera/color/camera_info"]
    params = ["-p", f"checkpoint:={checkpoint}", "-p", "num_threads:=1", "-p", "warmup_boxes:=0", "-p", "objects:=[ape]"]
    node_err = open(tmp_path / "node.err", "w")  # closed below, after the process
    node = subprocess.Popen([sys.executable, "-m", "axispose_ros.node", "--ros-args", *params, *remaps],
                            cwd=REPO, env=env, stdout=node_err, stderr=subprocess.STDOUT)  # fmt: skip
    camera = subprocess.Popen(
        [sys.executable, str(REPO / "test" / "camera_process.py"), "--frames", str(FRAMES), "--rate", str(RATE),
         "--image", "/camera/color/image_raw", "--camera-info", "/camera/color/camera_info", "--go-from-stdin"],
        cwd=REPO, env=env | dict.fromkeys(PROFILE_VARIABLES, str(profile)),
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain)
    listener = rclpy.create_node("listener", context=ctx)
    dets: list[DetectionArray] = []
    counters: dict[str, int] = {}
    subs = [
        listener.create_subscription(DetectionArray, "/axispose/detections", dets.append, 100),
        listener.create_subscription(DiagnosticArray, "/diagnostics", lambda m: counters.update(_counters(m)), 10),
    ]
    exe = SingleThreadedExecutor(context=ctx)
    exe.add_node(listener)
    try:
        end = time.monotonic() + 90  # the node's start: imports and the checkpoint
        while min(s.get_publisher_count() for s in subs) == 0 and node.poll() is None and time.monotonic() < end:
            exe.spin_once(timeout_sec=0.05)
        camera.stdin.write("go\n")
        camera.stdin.flush()
        end = time.monotonic() + 90
        while camera.poll() is None and time.monotonic() < end:
            exe.spin_once(timeout_sec=0.05)
        out, err = camera.communicate(timeout=10)
        assert camera.returncode == 0, err[-2000:]
        assert "XMLPARSER" not in err  # the profile parses (Fast DDS logs its XML errors and carries on)
        sent = json.loads(out.strip().splitlines()[-1])["stamps"]

        def settled() -> bool:
            done = counters.get("frames_processed", 0) + sum(v for k, v in counters.items() if k.startswith("dropped_"))
            return counters.get("frames_in", -1) == done and len(dets) == counters.get("frames_processed", -1)

        end = time.monotonic() + 30
        while not settled() and time.monotonic() < end:
            exe.spin_once(timeout_sec=0.05)
    finally:
        exe.shutdown()
        listener.destroy_node()
        rclpy.try_shutdown(context=ctx)
        if camera.poll() is None:
            camera.kill()
        node.send_signal(signal.SIGINT)
        try:
            node.wait(timeout=20)
        except subprocess.TimeoutExpired:
            node.kill()
        node_err.close()
    log = (tmp_path / "node.err").read_text()
    assert "XMLPARSER" not in log, log[-2000:]
    assert len(sent) == FRAMES
    assert counters.get("frames_in") == FRAMES and counters.get("camera_info_in") == FRAMES, (counters, log[-2000:])
    assert not {k for k in counters if k.startswith(("frames_lost", "stamps_"))}, counters
    dropped = {k: v for k, v in counters.items() if k.startswith("dropped_")}
    assert set(dropped) <= {"dropped_stale"}, counters  # paired, checked: only replaced by newer frames
    assert counters["frames_processed"] + sum(dropped.values()) == FRAMES
    answered = {round(d.header.stamp.sec + 1e-9 * d.header.stamp.nanosec, 6) for d in dets}
    unanswered = [k for k, s in enumerate(sent) if round(s, 6) not in answered]  # the stale ones, and any lost on the way back
    assert counters["frames_processed"] >= 30 and len(dets) == counters["frames_processed"], f"{counters}, frames unanswered {unanswered}"
    assert answered <= {round(s, 6) for s in sent} and len(answered) == len(dets)
    assert sum(len(d.detections) for d in dets) + counters.get("pose_refused", 0) == counters["frames_processed"]
