"""`axispose soak`: the node in a process of its own, fed a bag's camera stream in a loop at a camera's rate for a
given time while faults are injected, as a robot stack would meet them; the report says whether it held.

This process is the camera (it loads the shipped Fast DDS profile, as a camera driver beside the node must) and the
listener: it publishes the bag's frames (and their camera odometry, where the bag has it) restamped by the clock,
one fault at a time on a schedule, follows
`/diagnostics` and `~/detections`, and samples the node's resident memory. The faults and the counters each must
move in `/diagnostics` (FAULTS):
- `camera_info_gap`: no CameraInfo for 3 s (the images go on) -> `dropped_no_camera_info`;
- `stamps_back`: one frame stamped 5 s in the past -> `stamps_backwards`;
- `other_size`: one frame of another size than its CameraInfo, not a uniform scale -> `dropped_camera_info_mismatch`
  (the node checks a frame as it arrives, so a busy node counts it too);
- `corrupt`: one frame whose data is shorter than its size says -> `dropped_image_data`;
- `objects_leave`: 2 s of an empty grey frame, then the scene again -> in the video modes, tracks end and start again.
"""

from __future__ import annotations

import copy
import json
import os
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from nav_msgs.msg import Odometry
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import CameraInfo, Image

from axispose_msgs.msg import DetectionArray
from axispose_ros.bag import BagError, bag_topics, read_bag
from axispose_ros.node import use_shipped_fastdds_profile

FAULTS: dict[str, tuple[str, ...]] = {
    "camera_info_gap": ("dropped_no_camera_info",),
    "stamps_back": ("stamps_backwards",),
    "other_size": ("dropped_camera_info_mismatch",),
    "corrupt": ("dropped_image_data",),
    "objects_leave": ("tracking_ended_misses", "tracking_ended_unseen", "tracking_ended_timeout", "tracking_ended_unfound"),
}
"""Each fault and the /diagnostics counters of which at least one must grow (objects_leave's only where frames ran in a
video mode meanwhile)."""
SETTLE_S = 4.0
"""Seconds after a fault ends before the counters it moved are read (diagnostics come once a second)."""
IMAGE_TOPIC, INFO_TOPIC, ODOM_TOPIC = "/soak/image", "/soak/camera_info", "/soak/camera_odom"


@dataclass(frozen=True)
class SoakOptions:
    """How long, how fast, which node settings."""

    seconds: float = 600.0
    rate: float = 30.0
    mode: str = "auto"
    """The node's `mode` (the bag's camera odometry is played on `camera_odom` either way)."""
    view_window: int = 160
    """The node's `view_window` (video_odometry)."""
    follow_passes: int = 0
    """The node's `follow_passes` (video modes)."""
    faults: bool = True
    precision: str = "float32"
    threads: int = 2
    warmup_boxes: int = 8
    domain: int | None = None
    """ROS domain of the node and this process (None: one from the process id, apart from other runs)."""

    def __post_init__(self) -> None:
        if not self.seconds > 0 or not self.rate > 0:
            raise ValueError(f"seconds and rate must be > 0, got {self.seconds}, {self.rate}")


@dataclass
class _Log:
    """What the listener saw: the latest counters, the diagnostics' levels, answered frames, RSS samples."""

    counters: dict[str, int] = field(default_factory=dict)
    levels: dict[str, int] = field(default_factory=dict)
    answered: int = 0
    rss: list[tuple[float, float]] = field(default_factory=list)

    def on_diagnostics(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            raw = status.level
            level = {0: "OK", 1: "WARN", 2: "ERROR"}.get(raw[0] if isinstance(raw, bytes) else int(raw), "STALE")
            self.levels[level] = self.levels.get(level, 0) + 1
            self.counters.update({kv.key: int(kv.value) for kv in status.values if kv.value.isdigit()})

    def on_detections(self, _: DetectionArray) -> None:
        self.answered += 1


def load_frames(bag: str | Path) -> list[tuple[Image, CameraInfo, Odometry | None]]:
    """The bag's (Image, CameraInfo) pairs in order, as ROS messages, each with the camera's odometry of its stamp
    where the bag has an Odometry topic (else None)."""
    from rclpy.serialization import deserialize_message

    topics = bag_topics(bag)
    image_topic = next((t for t, m in topics.items() if m == "sensor_msgs/msg/Image"), None)
    info_topic = next((t for t, m in topics.items() if m == "sensor_msgs/msg/CameraInfo"), None)
    odom_topic = next((t for t, m in topics.items() if m == "nav_msgs/msg/Odometry"), None)
    if image_topic is None or info_topic is None:
        raise BagError(f"{bag}: needs an Image and a CameraInfo topic, has {sorted(topics)}")
    infos, odometry, frames = {}, {}, []
    for m in read_bag(bag, [t for t in (image_topic, info_topic, odom_topic) if t]):
        if m.topic == info_topic:
            infos[m.stamp_ns] = deserialize_message(m.raw, CameraInfo)
        elif m.topic == odom_topic:
            odometry[m.stamp_ns] = deserialize_message(m.raw, Odometry)
        elif m.stamp_ns in infos:
            frames.append((deserialize_message(m.raw, Image), infos[m.stamp_ns], odometry.get(m.stamp_ns)))
    if not frames:
        raise BagError(f"{bag}: no Image with a CameraInfo of the same stamp")
    return frames


def node_command(checkpoint: str, opts: SoakOptions) -> list[str]:
    """The node's command line: its parameters from the options, its topics remapped to the soak's."""
    params = {"checkpoint": checkpoint, "precision": opts.precision, "num_threads": opts.threads, "warmup_boxes": opts.warmup_boxes,
              "mode": opts.mode, "view_window": opts.view_window, "follow_passes": opts.follow_passes}  # fmt: skip
    return [sys.executable, "-m", "axispose_ros.node", "--ros-args", *[a for k, v in params.items() for a in ("-p", f"{k}:={v}")],
            "-r", f"image:={IMAGE_TOPIC}", "-r", f"camera_info:={INFO_TOPIC}", "-r", f"camera_odom:={ODOM_TOPIC}"]  # fmt: skip


def _node_process(checkpoint: str, opts: SoakOptions, env: dict, log_path: Path) -> subprocess.Popen:
    return subprocess.Popen(node_command(checkpoint, opts), env=env, stdout=open(log_path, "w"), stderr=subprocess.STDOUT)


def _rss_mb(pid: int) -> float:
    """Resident memory (MB) of the node and the processes it started (its background search,
    `axispose_core/tracking/background.py`)."""
    return sum(_own_rss_mb(p) for p in [pid, *_descendants(pid)])


def _own_rss_mb(pid: int) -> float:
    """One process's resident memory (MB): none for one that ended (gone, or a zombie not yet reaped: no VmRSS)."""
    try:
        lines = Path(f"/proc/{pid}/status").read_text().splitlines()
    except OSError:
        return 0.0
    return next((int(line.split()[1]) / 1024 for line in lines if line.startswith("VmRSS:")), 0.0)


def _descendants(pid: int) -> list[int]:
    children = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            parent = int(stat.read_text().rsplit(")", 1)[1].split()[1])
        except (OSError, IndexError, ValueError):
            continue
        if parent == pid:
            children.append(int(stat.parent.name))
    return children + [d for c in children for d in _descendants(c)]


class _Camera:
    """Publishes the frames in a loop, stamped by the clock, with the fault of the moment applied."""

    def __init__(self, node, frames: list[tuple[Image, CameraInfo, Odometry | None]]) -> None:
        self.node, self.frames, self.k, self.sent = node, frames, 0, 0
        self.pub_image = node.create_publisher(Image, IMAGE_TOPIC, qos_profile_sensor_data)
        self.pub_info = node.create_publisher(CameraInfo, INFO_TOPIC, qos_profile_sensor_data)
        self.pub_odom = node.create_publisher(Odometry, ODOM_TOPIC, 50)
        h, w = frames[0][0].height, frames[0][0].width
        self.grey = Image(height=h, width=w, encoding="rgb8", step=3 * w, data=np.full(h * w * 3, 128, np.uint8).tobytes())

    def publish(self, fault: str | None) -> None:
        image, info, odometry = self.frames[self.k % len(self.frames)]
        self.k += 1
        image, info = copy.copy(image), copy.copy(info)
        stamp = self.node.get_clock().now()
        if fault == "stamps_back":
            stamp = stamp - rclpy.duration.Duration(seconds=5.0)
        image.header.stamp = info.header.stamp = stamp.to_msg()
        if odometry is not None:
            odometry = copy.copy(odometry)
            odometry.header.stamp = image.header.stamp
            self.pub_odom.publish(odometry)
        if fault == "objects_leave":
            image = copy.copy(self.grey)
            image.header = info.header
        elif fault == "other_size":
            image = _cropped(image, image.width * 4 // 5)
        elif fault == "corrupt":
            image.data = bytes(image.data)[: len(image.data) // 2]
        if fault != "camera_info_gap":
            self.pub_info.publish(info)
        self.pub_image.publish(image)
        self.sent += 1


def _cropped(image: Image, width: int) -> Image:
    """The image's left `width` columns: another size than its CameraInfo, not a uniform scale of it."""
    c = image.step // image.width
    rows = np.frombuffer(bytes(image.data), np.uint8).reshape(image.height, image.step)[:, : width * c]
    return Image(header=image.header, height=image.height, width=width, encoding=image.encoding, step=width * c,
                 data=np.ascontiguousarray(rows).tobytes())  # fmt: skip


def _schedule(opts: SoakOptions, start: float) -> list[tuple[str, float, float]]:
    """(fault, from, to) in seconds after `start`: the faults in turn, evenly over the run after a quiet first tenth."""
    if not opts.faults:
        return []
    span = {"camera_info_gap": 3.0, "objects_leave": 2.0}
    names = list(FAULTS)
    period = 0.9 * opts.seconds / max(len(names), int(0.9 * opts.seconds // 20))
    out, t, k = [], 0.1 * opts.seconds, 0
    while t + span.get(names[k % len(names)], 1.0 / opts.rate) + SETTLE_S < opts.seconds:
        name = names[k % len(names)]
        out.append((name, start + t, start + t + span.get(name, 1.0 / opts.rate)))  # one frame period: one frame
        t, k = t + period, k + 1
    return out


def soak(bag: str | Path, checkpoint: str | Path, opts: SoakOptions, work: str | Path) -> dict:
    """Run the soak (module docstring); the report, also written as `work`/soak.json with the RSS plot. Call it in
    a fresh process (`axispose soak` is one): Fast DDS reads the transport profile at the process's first DDS use."""
    work = Path(work)
    work.mkdir(parents=True, exist_ok=True)
    frames = load_frames(bag)
    domain = opts.domain if opts.domain is not None else 100 + os.getpid() % 100
    use_shipped_fastdds_profile()
    env = {**os.environ, "ROS_DOMAIN_ID": str(domain), "PYTHONUNBUFFERED": "1", "ROS_LOG_DIR": str(work / "ros_log")}
    node = _node_process(str(checkpoint), opts, env, work / "node.log")
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain)
    try:
        return _run(node, frames, opts, ctx, work)
    finally:
        node.terminate()
        try:
            node.wait(timeout=20)
        except subprocess.TimeoutExpired:
            node.kill()
        rclpy.try_shutdown(context=ctx)


def _run(node: subprocess.Popen, frames: list, opts: SoakOptions, ctx, work: Path) -> dict:
    me = rclpy.create_node("axispose_soak", context=ctx)
    log, exe = _Log(), SingleThreadedExecutor(context=ctx)
    exe.add_node(me)
    me.create_subscription(DiagnosticArray, "/diagnostics", log.on_diagnostics, 10)
    me.create_subscription(DetectionArray, "/axispose/detections", log.on_detections, 100)
    camera = _Camera(me, frames)
    end = time.monotonic() + 180  # the node's start: imports, checkpoint, warm-up
    while camera.pub_image.get_subscription_count() == 0 or not log.levels:  # matched, and the node reports
        if node.poll() is not None or time.monotonic() > end:
            raise RuntimeError(f"the node did not come up (exit {node.poll()}); see {work / 'node.log'}")
        exe.spin_once(timeout_sec=0.05)
    events = _stream(node, camera, log, exe, opts)
    return _report(node, camera, log, events, opts, work)


def _stream(node: subprocess.Popen, camera: _Camera, log: _Log, exe, opts: SoakOptions) -> list[dict]:
    """Publish at the rate for the run's time, faults on their schedule; per fault the counters before and after."""
    start = time.monotonic()
    schedule, events = _schedule(opts, start), []
    next_frame, next_rss = start, start
    while (now := time.monotonic()) < start + opts.seconds and node.poll() is None:
        if now >= next_rss:
            log.rss.append((now - start, _rss_mb(node.pid)))
            next_rss += 2.0
        if now >= next_frame:
            fault = next((f for f, a, b in schedule if a <= now < b), None)
            for f, a, b in schedule:
                if a <= now and not any(e["fault"] == f and e["at"] == a for e in events):
                    events.append({"fault": f, "at": a, "t": round(a - start, 1), "before": dict(log.counters), "until": b + SETTLE_S})
            camera.publish(fault)
            next_frame += 1.0 / opts.rate
        for e in events:
            if "after" not in e and now >= e["until"]:
                e["after"] = dict(log.counters)
        exe.spin_once(timeout_sec=max(0.0, min(next_frame, next_rss) - time.monotonic()))
    drain = time.monotonic() + SETTLE_S + 2.0
    while time.monotonic() < drain:
        exe.spin_once(timeout_sec=0.05)
    for e in events:
        e.setdefault("after", dict(log.counters))
    return events


def _tracked_during(event: dict) -> bool:
    """Whether frames ran in a video mode while the fault lasted (only then do tracks end)."""
    return any(event["after"].get(k, 0) > event["before"].get(k, 0) for k in ("mode_video", "mode_video_odometry"))


def _report(node: subprocess.Popen, camera: _Camera, log: _Log, events: list[dict], opts: SoakOptions, work: Path) -> dict:
    c = log.counters
    dropped = {k[len("dropped_") :]: v for k, v in c.items() if k.startswith("dropped_")}
    faults = []
    for e in events:
        moved = {k: e["after"].get(k, 0) - e["before"].get(k, 0) for k in FAULTS[e["fault"]]}
        needed = e["fault"] != "objects_leave" or _tracked_during(e)
        faults.append({"fault": e["fault"], "t": e["t"], "moved": moved, "counted": any(v > 0 for v in moved.values()) or not needed})
    rss = log.rss
    base = next((r for t, r in rss if t >= min(60.0, opts.seconds / 3)), rss[0][1] if rss else float("nan"))
    report = {
        "config": {**opts.__dict__, "frames_in_bag": len(camera.frames)},
        "alive": node.poll() is None,
        "frames_sent": camera.sent,
        "frames_in": c.get("frames_in", 0),
        "frames_processed": c.get("frames_processed", 0),
        "answered": log.answered,
        "dropped": dropped,
        "tracking": {k[len("tracking_") :]: v for k, v in c.items() if k.startswith("tracking_")},
        "stamps": {k: v for k, v in c.items() if k.startswith("stamps_")},
        "faults": faults,
        "diagnostics_levels": log.levels,
        "rss_mb": {"after_first_minute": base, "end": rss[-1][1] if rss else float("nan"), "max": max((r for _, r in rss), default=0.0)},
        "rss_growth": (rss[-1][1] - base) / base if rss else float("nan"),
        "rss_series": rss,
    }
    (work / "soak.json").write_text(json.dumps(report, indent=1))
    _plot(rss, work / "rss.png")
    return report


def _plot(rss: list[tuple[float, float]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3))
    if rss:
        ax.plot([t for t, _ in rss], [r for _, r in rss])
    ax.set_xlabel("s")
    ax.set_ylabel("node RSS (MB)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
