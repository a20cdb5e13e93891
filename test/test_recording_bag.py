"""A bag of a rendered camera path -> `bag_to_recording` -> `read_recording`: the scene's frames, K, images and camera
poses back; per-frame problems counted, bad bags and outputs refused in one line."""

import dataclasses
import json
import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from rosbags.rosbag2 import Writer

from axispose_core.adapt.recording import RecordingError, read_recording
from axispose_core.data.bop import load_camera_poses
from axispose_core.data.bop_scene import BopScene
from axispose_core.data.synth.config import CameraPathConfig, SynthConfig
from axispose_core.data.synth.generate import generate
from axispose_core.lmo import LMO_K
from axispose_ros.bag import IMAGE_TOPIC, INFO_TOPIC, STAMP_ORIGIN_NS, TYPESTORE, BagMessage, BagOptions, deserialize, make_bag, read_bag
from axispose_ros.conversions import Undistorter, image_to_rgb
from axispose_ros.recording import bag_to_recording

SCALE = 0.25  # 160x120 images: fast to render and to write


@pytest.fixture(scope="module")
def scene(tmp_path_factory, lmo_dir) -> BopScene:
    K = LMO_K * np.array([[SCALE], [SCALE], [1.0]])
    cfg = SynthConfig(
        width=160, height=120, K=tuple(K.ravel().tolist()), seed=3, scenes=1, images_per_scene=4, objects=(1, 5),
        camera_path=CameraPathConfig(orbit_deg=5.0),
    )  # fmt: skip
    out = tmp_path_factory.mktemp("recdata")
    generate(cfg, lmo_dir / "models", out, progress=False)
    return BopScene(out / "000000")


@pytest.fixture(scope="module", params=["sqlite3", "mcap"])
def bag(request, scene, lmo_dir, tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp(request.param) / "scene.bag"
    assert make_bag(scene.root, path, [], lmo_dir / "models_eval", BagOptions(storage=request.param, progress=False)).frames == 4
    return path


Edit = Callable[[int, BagMessage], list[tuple[str, str, bytes]]]


def _rewrite(src: Path, dst: Path, edit: Edit) -> Path:
    """A copy of a bag whose k-th message of each topic is replaced by what `edit(k, message)` gives (topic, type, raw)."""
    seen: dict[str, int] = {}
    with Writer(dst, version=9) as writer:
        conns: dict[tuple[str, str], object] = {}
        for m in read_bag(src):
            k = seen[m.topic] = seen.get(m.topic, -1) + 1
            for topic, msgtype, raw in edit(k, m):
                if (topic, msgtype) not in conns:
                    conns[topic, msgtype] = writer.add_connection(topic, msgtype, typestore=TYPESTORE)
                writer.write(conns[topic, msgtype], m.stamp_ns, raw)
    return dst


def _same(k: int, m: BagMessage) -> list[tuple[str, str, bytes]]:
    return [(m.topic, m.msgtype, m.raw)]


def _one_line_error(call: Callable[[], object], match: str) -> str:
    with pytest.raises(RecordingError, match=match) as err:
        call()
    assert "\n" not in str(err.value)
    return str(err.value)


def test_a_bag_becomes_the_recording_of_its_scene(bag, scene, tmp_path):
    summary = bag_to_recording(bag, tmp_path / "rec")
    assert (summary.folder, summary.frames, summary.skipped, summary.odometry_frames) == (tmp_path / "rec", 4, {}, 4)
    assert not (tmp_path / "rec.tmp").exists()
    rec = read_recording(tmp_path / "rec")
    assert [f.im_id for f in rec.frames] == [0, 1, 2, 3] and rec.has_odometry
    poses = load_camera_poses(tmp_path / "rec" / "scene_camera.json")
    for frame, im_id in zip(rec.frames, scene.image_ids, strict=True):
        np.testing.assert_allclose(frame.K, scene.cameras[im_id], atol=1e-6)
        np.testing.assert_array_equal(frame.rgb(), scene.rgb(im_id))
        for got, want in zip(poses[frame.im_id], scene.camera_poses[im_id], strict=True):
            np.testing.assert_allclose(got, want, atol=1e-6)
    stamps = json.loads((tmp_path / "rec" / "stamps.json").read_text())
    assert stamps == {str(k): STAMP_ORIGIN_NS + k * 10**8 for k in range(4)}


def test_every_and_limit_pick_the_frames(bag, scene, tmp_path):
    assert bag_to_recording(bag, tmp_path / "every", every=2).frames == 2
    rec = read_recording(tmp_path / "every")
    np.testing.assert_array_equal(rec.frames[1].rgb(), scene.rgb(scene.image_ids[2]))
    summary = bag_to_recording(bag, tmp_path / "limit", every=1, limit=3)
    assert (summary.frames, summary.skipped) == (3, {})
    (tmp_path / "empty").mkdir()
    assert bag_to_recording(bag, tmp_path / "empty", limit=1).frames == 1


def test_frames_the_node_would_drop_are_counted_and_skipped(bag, scene, tmp_path):
    def edit(k: int, m: BagMessage) -> list[tuple[str, str, bytes]]:
        if m.topic == IMAGE_TOPIC and k == 0:
            return [(m.topic, m.msgtype, m.raw[:40])]  # does not decode
        if m.topic == IMAGE_TOPIC and k == 2:
            msg = deserialize(m)
            return [(m.topic, m.msgtype, TYPESTORE.serialize_cdr(dataclasses.replace(msg, encoding="yuv422"), m.msgtype))]
        return [] if m.topic == INFO_TOPIC and k == 3 else _same(k, m)

    damaged = _rewrite(bag, tmp_path / "damaged", edit)
    summary = bag_to_recording(damaged, tmp_path / "rec")
    assert (summary.frames, summary.odometry_frames) == (1, 1)
    assert summary.skipped == {"encoding": 1, "image_undecodable": 1, "no_camera_info": 1}
    np.testing.assert_array_equal(read_recording(tmp_path / "rec").frames[0].rgb(), scene.rgb(scene.image_ids[1]))


def test_lens_distortion_is_undone_as_the_node_does(bag, tmp_path):
    D = np.array([0.2, -0.1, 0.001, 0.002, 0.0])

    def edit(k: int, m: BagMessage) -> list[tuple[str, str, bytes]]:
        if m.topic != INFO_TOPIC:
            return _same(k, m)
        return [(m.topic, m.msgtype, TYPESTORE.serialize_cdr(dataclasses.replace(deserialize(m), d=D), m.msgtype))]

    distorted = _rewrite(bag, tmp_path / "distorted", edit)
    rec = read_recording(bag_to_recording(distorted, tmp_path / "rec").folder)
    images = [deserialize(m) for m in read_bag(distorted, [IMAGE_TOPIC])]
    info = deserialize(next(read_bag(distorted, [INFO_TOPIC])))
    for frame, image in zip(rec.frames, images, strict=True):
        raw = image_to_rgb(image)
        undistorted = Undistorter()(info, frame.K, raw)
        np.testing.assert_array_equal(frame.rgb(), undistorted)
        assert not np.array_equal(undistorted, raw)


def test_topics_are_the_only_ones_or_named(bag, tmp_path):
    def twice(k: int, m: BagMessage) -> list[tuple[str, str, bytes]]:
        return _same(k, m) + ([("/camera/ir/image_raw", m.msgtype, m.raw)] if m.topic == IMAGE_TOPIC else [])

    two = _rewrite(bag, tmp_path / "two", twice)
    _one_line_error(lambda: bag_to_recording(two, tmp_path / "a"), "2 sensor_msgs/msg/Image topics .*name the one")
    assert bag_to_recording(two, tmp_path / "b", image_topic="/camera/ir/image_raw").frames == 4
    _one_line_error(lambda: bag_to_recording(bag, tmp_path / "c", image_topic="/nope"), "no sensor_msgs/msg/Image topic '/nope'")
    _one_line_error(lambda: bag_to_recording(bag, tmp_path / "d", odom_topic="/odom"), "no nav_msgs/msg/Odometry topic '/odom'")
    no_info = _rewrite(bag, tmp_path / "no_info", lambda k, m: [] if m.topic == INFO_TOPIC else _same(k, m))
    _one_line_error(lambda: bag_to_recording(no_info, tmp_path / "e"), "0 sensor_msgs/msg/CameraInfo topics")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b", "no_info", "two"]


def test_bad_bags_and_outputs_are_refused_in_one_line(bag, tmp_path):
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "keep.txt").write_text("mine")
    _one_line_error(lambda: bag_to_recording(bag, tmp_path / "full"), "exists and is not an empty folder")
    assert (tmp_path / "full" / "keep.txt").read_text() == "mine"
    _one_line_error(lambda: bag_to_recording(tmp_path / "missing", tmp_path / "a"), "no such bag")
    damaged = tmp_path / "damaged"
    shutil.copytree(bag, damaged)
    data = next(p for p in damaged.iterdir() if p.suffix in (".db3", ".mcap"))
    raw = data.read_bytes()
    data.write_bytes(raw[: len(raw) // 2] + bytes(4096))  # truncated mid-file, then garbage
    _one_line_error(lambda: bag_to_recording(damaged, tmp_path / "out"), str(damaged))
    assert not (tmp_path / "out").exists() and not (tmp_path / "out.tmp").exists()
