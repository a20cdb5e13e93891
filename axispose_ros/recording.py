"""A rosbag2 recording of a user's scene written out as the BOP scene folder that `axispose adapt` reads
(`axispose_core/adapt/recording.py`): `rgb/{k:06d}.png`, `scene_camera.json` (K; the camera's pose where the bag's
odometry gives one) and `stamps.json` (each frame's image stamp in ns), so that everything after reads one format.

The frames are those the node would take: each Image paired with the CameraInfo of its stamp within the node's
default `sync_slop` (by the node's own StampSynchronizer), checked and undistorted as the node does, and posed by the
Odometry message (the camera's optical frame in a fixed frame, as the node's `camera_odom`) nearest its stamp
within the same slop. The folder is written as `<out>.tmp` and renamed once complete, so that a conversion killed
midway never leaves a folder that reads as a recording.
"""

from __future__ import annotations

import json
import shutil
from bisect import bisect
from collections import Counter
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np

from axispose_core.adapt.recording import RecordingError
from axispose_core.data.bop import write_scene_camera
from axispose_ros.bag import BagError, BagMessage, bag_topics, camera_topics, deserialize, read_bag
from axispose_ros.conversions import InputError, Undistorter, check_frame, image_to_rgb, stamp_ns, stamp_seconds
from axispose_ros.odometry import pose_matrix
from axispose_ros.params import SPECS
from axispose_ros.sync import StampSynchronizer

SYNC_SLOP: float = next(s.default for s in SPECS if s.name == "sync_slop")
"""The node's default largest Image/CameraInfo (and Image/Odometry) stamp difference, s."""


@dataclass(frozen=True)
class BagRecordingSummary:
    """What `bag_to_recording` wrote."""

    folder: Path
    frames: int
    """Frames written (images with K)."""
    skipped: dict[str, int]
    """Selected images not written, by reason: no_camera_info, out_of_order, time_jump (the node's synchroniser),
    image_undecodable, or the node's drop reason for an image or CameraInfo it refuses (encoding, camera_info_k, ...)."""
    odometry_frames: int
    """Frames written with the camera's pose."""
    ignored: dict[str, int]
    """CameraInfo and Odometry messages left out, by reason (camera_info_undecodable, odometry_undecodable,
    odometry_invalid)."""


@dataclass(frozen=True)
class _Topics:
    image: str
    info: str
    odom: str | None


def _one_line(text: object) -> str:
    return " ".join(str(text).split())


def _topics(bag: Path, image: str | None, info: str | None, odom: str | None) -> _Topics:
    """The bag's camera, CameraInfo and (where it has one, or one is named) Odometry topics."""
    try:
        return _Topics(*camera_topics(bag_topics(bag), image, info, odom))
    except BagError as err:
        raise RecordingError(str(err)) from err


def _sorted(counts: Counter) -> dict[str, int]:
    return dict(sorted(counts.items()))


class _CameraPoses:
    """Every camera pose (4x4, camera to fixed) of an odometry topic by stamp: the whole recording is at hand, so a
    frame finds the pose nearest its stamp whichever side of it the bag holds it (the node keeps only the last
    seconds of a live stream)."""

    def __init__(self, entries: list[tuple[float, np.ndarray]]) -> None:
        entries.sort(key=lambda e: e[0])
        self.stamps = [s for s, _ in entries]
        self.poses = [T for _, T in entries]

    def at(self, stamp: float, slop: float) -> np.ndarray | None:
        """The pose nearest `stamp` (s), within `slop`; None without one."""
        k = bisect(self.stamps, stamp)
        near = [i for i in (k - 1, k) if 0 <= i < len(self.stamps) and abs(self.stamps[i] - stamp) <= slop]
        return self.poses[min(near, key=lambda i: abs(self.stamps[i] - stamp))] if near else None


def _read_odometry(bag: Path, topic: str, ignored: Counter) -> _CameraPoses:
    entries = []
    for m in read_bag(bag, [topic]):
        try:
            msg = deserialize(m)
        except BagError:
            ignored["odometry_undecodable"] += 1
            continue
        T = pose_matrix(msg.pose.pose.position, msg.pose.pose.orientation)
        if T is None:
            ignored["odometry_invalid"] += 1
        else:
            entries.append((stamp_seconds(msg.header), T))
    return _CameraPoses(entries)


class _FrameWriter:
    """Writes the paired frames into the folder as they come, and what scene_camera.json and stamps.json need."""

    def __init__(self, folder: Path, poses: _CameraPoses | None, limit: int | None) -> None:
        self.folder, self.poses, self.limit = folder, poses, limit
        self.cams: dict[int, np.ndarray] = {}
        self.w2c: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self.stamps: dict[int, int] = {}
        self.skipped: Counter = Counter()
        self.undistort = Undistorter()

    @property
    def full(self) -> bool:
        return self.limit is not None and len(self.cams) >= self.limit

    def on_drop(self, _image, reason: str) -> None:
        self.skipped[reason] += 1

    def on_pair(self, image, info) -> None:
        """One frame as the node would see it: checked, converted and undistorted; one it would drop is counted."""
        if self.full:
            return
        try:
            camera = check_frame(image, info)
            rgb = image_to_rgb(image)
            if Undistorter.needed(info):
                rgb = self.undistort(info, camera.K, rgb)
        except InputError as err:
            self.skipped[err.reason] += 1
            return
        k = len(self.cams)
        path = self.folder / "rgb" / f"{k:06d}.png"
        if not cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)):
            raise OSError(f"cv2 could not write {path}")
        self.cams[k], self.stamps[k] = camera.K, stamp_ns(image.header)
        T = self.poses.at(stamp_seconds(image.header), SYNC_SLOP) if self.poses else None
        if T is not None:
            R_w2c = T[:3, :3].T
            self.w2c[k] = (R_w2c, -R_w2c @ T[:3, 3])

    def finish(self) -> None:
        write_scene_camera(self.folder / "scene_camera.json", self.cams, poses=self.w2c)
        (self.folder / "stamps.json").write_text(json.dumps({str(k): s for k, s in self.stamps.items()}, indent=1))


def _decoded(m: BagMessage):
    """The message, or None where it does not decode as its type."""
    try:
        return deserialize(m)
    except BagError:
        return None


def _convert(bag: Path, topics: _Topics, folder: Path, every: int, limit: int | None) -> BagRecordingSummary:
    """Pair and write the frames into `folder` (the bag read in time order, as the node would receive it)."""
    ignored: Counter = Counter()
    poses = _read_odometry(bag, topics.odom, ignored) if topics.odom else None
    writer = _FrameWriter(folder, poses, limit)
    sync: StampSynchronizer = StampSynchronizer(SYNC_SLOP, writer.on_pair, writer.on_drop)
    images = 0
    for m in read_bag(bag, [topics.image, topics.info]):
        if writer.full:
            break
        if m.topic == topics.info:
            info = _decoded(m)
            if info is None:
                ignored["camera_info_undecodable"] += 1
            else:
                sync.add_info(stamp_seconds(info.header), info)
            continue
        images += 1
        if (images - 1) % every:
            continue
        image = _decoded(m)
        if image is None:
            writer.skipped["image_undecodable"] += 1
        else:
            sync.add_image(stamp_seconds(image.header), image)
    if not writer.full:
        for _, image in sync.images:
            writer.on_drop(image, "no_camera_info")
    if not writer.cams:
        why = f"; skipped: {dict(writer.skipped)}" if writer.skipped else ""
        raise RecordingError(f"{bag}: no image of '{topics.image}' pairs with a CameraInfo of '{topics.info}' within {SYNC_SLOP} s{why}")
    writer.finish()
    return BagRecordingSummary(folder, len(writer.cams), _sorted(writer.skipped), len(writer.w2c), _sorted(ignored))


def _check_out(out: Path) -> None:
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise RecordingError(f"{out} exists and is not an empty folder; give a new one")


def bag_to_recording(
    bag: str | Path,
    out: str | Path,
    image_topic: str | None = None,
    info_topic: str | None = None,
    odom_topic: str | None = None,
    every: int = 1,
    limit: int | None = None,
) -> BagRecordingSummary:
    """Write every `every`-th image of a rosbag2 (at most `limit` frames) as the recording folder `out` (module
    docstring). Topics left out are the bag's only one of their type (Odometry: none where the bag has none). A bag
    that cannot be read or lacks what is asked of it, an `out` that exists and is not empty, or a bag with no usable
    frame is a RecordingError; frames the node would drop are counted in the summary."""
    bag, out = Path(bag), Path(out)
    if every < 1 or (limit is not None and limit < 1):
        raise RecordingError(f"every and limit must be >= 1, got {every} and {limit}")
    _check_out(out)
    tmp = out.with_name(out.name + ".tmp")
    try:
        topics = _topics(bag, image_topic, info_topic, odom_topic)
        shutil.rmtree(tmp, ignore_errors=True)  # a killed conversion's
        (tmp / "rgb").mkdir(parents=True)
        summary = _convert(bag, topics, tmp, every, limit)
        if out.exists():
            out.rmdir()
        tmp.rename(out)
    except (BagError, OSError) as err:
        shutil.rmtree(tmp, ignore_errors=True)
        raise RecordingError(_one_line(err if isinstance(err, BagError) else f"{out}: cannot write the recording ({err})")) from err
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return replace(summary, folder=out)
