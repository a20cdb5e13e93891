"""make-bag -> replay round trips in both storage formats, metrics through the real node, damaged bags."""

import json
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import TINY_AGM
from scipy.spatial.transform import Rotation

from axispose_core.agm.model import AxisGenerator
from axispose_core.data.bop_models import model_path
from axispose_core.data.bop_scene import BopScene
from axispose_core.data.meshes import load_ply
from axispose_core.data.synth.config import SynthConfig
from axispose_core.data.synth.generate import generate
from axispose_core.estimator import Estimator
from axispose_core.estimator_checkpoint import EstimatorConfig
from axispose_core.objects import objects_from_models
from axispose_core.pose_estimate import PoseEstimate
from axispose_core.tbm.reader import SHIPPED_READER, load_reader
from axispose_core.tracking.poser import FramePoser
from axispose_ros.bag import (
    FRAME_ID,
    IMAGE_TOPIC,
    INFO_TOPIC,
    ODOM_TOPIC,
    BagError,
    BagOptions,
    bag_topics,
    cloud_points,
    deserialize,
    make_bag,
    read_bag,
)
from axispose_ros.cli import main
from axispose_ros.odometry import pose_matrix
from axispose_ros.replay import ReplayOptions, replay

OBJECTS = (1, 5, 8)  # ape, can, driller


@pytest.fixture(scope="module")
def scene(tmp_path_factory, lmo_dir):
    out = tmp_path_factory.mktemp("bagdata")
    generate(SynthConfig(seed=21, scenes=1, images_per_scene=3, objects=OBJECTS), lmo_dir / "models", out, progress=False)
    return out / "000000"


@pytest.fixture(scope="module")
def objects(scene):
    return objects_from_models(scene.parent, list(OBJECTS), names={1: "ape", 5: "can", 8: "driller"})


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory, objects):
    reader = load_reader(SHIPPED_READER)
    cfg = EstimatorConfig(
        agm=TINY_AGM,
        reader=reader.config,
        objects=tuple(objects),
        ddim_steps=1,
    )
    path = tmp_path_factory.mktemp("ckpt") / "tiny.safetensors"
    Estimator(cfg, AxisGenerator(cfg.agm), reader).save(path)
    return path


@pytest.fixture(scope="module", params=["sqlite3", "mcap"])
def bag(request, scene, objects, lmo_dir, tmp_path_factory):
    path = tmp_path_factory.mktemp(request.param) / "scene.bag"
    summary = make_bag(scene, path, objects, lmo_dir / "models_eval", BagOptions(storage=request.param, progress=False))
    assert summary.frames == 3 and summary.instances > 0
    return path


def test_bag_holds_the_scene(bag, scene, lmo_dir):
    s = BopScene(scene)
    topics = bag_topics(bag)
    assert topics[IMAGE_TOPIC] == "sensor_msgs/msg/Image" and topics[INFO_TOPIC] == "sensor_msgs/msg/CameraInfo"
    assert {"/gt/ape", "/roi/ape", "/gt/models/ape"} <= topics.keys()
    msgs = list(read_bag(bag))
    stamps = [m.stamp_ns for m in msgs]
    assert stamps == sorted(stamps)
    images = [deserialize(m) for m in msgs if m.topic == IMAGE_TOPIC]
    infos = [deserialize(m) for m in msgs if m.topic == INFO_TOPIC]
    assert len(images) == len(infos) == 3
    for im_id, img, info in zip(s.image_ids, images, infos, strict=True):
        rgb = cv2.cvtColor(cv2.imread(str(s.rgb_path(im_id))), cv2.COLOR_BGR2RGB)
        np.testing.assert_array_equal(np.asarray(img.data).reshape(img.height, img.width, 3), rgb)
        np.testing.assert_allclose(np.asarray(info.k).reshape(3, 3), s.cameras[im_id])
        assert img.header == info.header and img.header.frame_id
    ape_gt = [deserialize(m) for m in msgs if m.topic == "/gt/ape"]
    first = next(g for g in s.gt[s.image_ids[0]] if g.obj_id == 1)
    q = ape_gt[0].pose.orientation
    np.testing.assert_allclose(Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix(), first.R, atol=1e-9)
    np.testing.assert_allclose([ape_gt[0].pose.position.x, ape_gt[0].pose.position.y, ape_gt[0].pose.position.z], first.t)
    cloud = cloud_points(deserialize(next(m for m in msgs if m.topic == "/gt/models/ape")))
    pts = load_ply(model_path(lmo_dir / "models_eval", 1)).vertices
    assert cloud.shape[1] == 3 and len(cloud) == min(1000, len(pts))
    np.testing.assert_allclose(cloud[0], pts[0], atol=1e-6)


def test_replay_of_ground_truth_scores_perfectly(bag, scene, checkpoint, monkeypatch, tmp_path):
    """The estimator answers with the GT pose of the box it is given: every stage in between (ROIs reaching
    the node per frame, pose messages, matching, metrics) must then give perfect scores."""
    s = BopScene(scene)
    by_box = {}
    for im_id in s.image_ids:
        for g, info in zip(s.gt[im_id], s.gt_info[im_id], strict=True):
            x, y, w, h = info.bbox_obj
            x0, y0 = max(0, x), max(0, y)
            by_box[(g.obj_id, (x0, y0, min(640, x + w) - x0, min(480, y + h) - y0))] = g

    def gt_estimate(self, image, K, boxes, **kwargs):
        out = []
        for obj_id, box in boxes:
            g = by_box[(obj_id, tuple(int(v) for v in box))]
            out.append(PoseEstimate(obj_id, g.R, g.t, True, "", np.zeros((64, 64, 3)), K, (0.0, 0.0), 1.0))
        return out

    monkeypatch.setattr(Estimator, "estimate", gt_estimate)
    result = replay(bag, checkpoint, tmp_path / "out", ReplayOptions(progress=False))
    assert result.frames_published == 3 and result.counts["frames_processed"] == 3
    assert not any(k.startswith("dropped_") for k in result.counts)
    report = result.report
    assert report is not None and set(report["objects"]) == {"1", "5", "8"}
    for entry in report["objects"].values():
        assert entry["add_0.1d"] == entry["reproj_5px"] == 1.0
        assert entry["rot_err_median_deg"] == pytest.approx(0.0, abs=1e-4)
    assert report["counts"]["frames_in"] == 3
    recorded = bag_topics(tmp_path / "out")
    assert {"/axispose/pose_array", "/axispose/poses/ape", "/axispose/pose"} <= recorded.keys()
    in_stamps = [m.stamp_ns for m in read_bag(bag, [IMAGE_TOPIC])]
    arrays = list(read_bag(tmp_path / "out", ["/axispose/pose_array"]))
    assert [m.stamp_ns for m in arrays] == in_stamps
    assert deserialize(arrays[0]).header.frame_id == "camera_color_optical_frame"
    assert recorded["/axispose/detections"] == "axispose_msgs/msg/DetectionArray"
    raw_written = list(read_bag(tmp_path / "out", ["/axispose/detections"]))  # taken serialized, stamped from the bytes
    assert [m.stamp_ns for m in raw_written] == in_stamps
    assert {m.stamp_ns for m in read_bag(tmp_path / "out", ["/axispose/pose"])} == set(in_stamps)
    detections = [deserialize(m) for m in raw_written]
    assert [len(d.detections) for d in detections] == [len(deserialize(m).poses) for m in arrays]
    names = {d.name for msg in detections for d in msg.detections}
    assert names == {"ape", "can", "driller"} and all(d.score == 1.0 for msg in detections for d in msg.detections)
    # Another process, where nothing registered axispose_msgs, reads them from the definitions stored in the bag.
    code = (
        "import sys; from axispose_ros.bag import TYPESTORE, deserialize, read_bag; "
        "assert 'axispose_msgs/msg/DetectionArray' not in TYPESTORE.types; "
        "print(sum(len(deserialize(m).detections) for m in read_bag(sys.argv[1], ['/axispose/detections'])))"
    )
    done = subprocess.run([sys.executable, "-c", code, str(tmp_path / "out")], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert int(done.stdout) == sum(len(d.detections) for d in detections)


def test_replay_cli_with_a_real_checkpoint(bag, checkpoint, tmp_path, capsys):
    code = main(
        ["replay", str(bag), "--checkpoint", str(checkpoint), "--out", str(tmp_path / "out"), "--report", str(tmp_path / "r.json"),
         "--overlays", str(tmp_path / "png"), "--steps", "1", "--threads", "1"]
    )  # fmt: skip
    assert code == 0
    report = json.loads((tmp_path / "r.json").read_text())
    assert {"objects", "mean", "ms_per_object", "config", "frame_latency_ms", "counts"} <= set(report)
    assert report["counts"]["frames_processed"] == 3
    # the node's own latency of each frame (received to all published, the overlay drawn for --overlays included)
    assert report["node_frame_ms"]["frames"] == 3 and report["node_frame_ms"]["median"] > 0
    # image published to ~/pose_array received (before the overlay is drawn), in ms: a frame takes more than 1 ms
    assert 1 < report["frame_latency_ms"]["median"] < 60_000
    assert len(list((tmp_path / "png").glob("*.png"))) == 3
    out = capsys.readouterr().out
    assert "replayed 3 frames" in out and "mean" in out and "the node's own" in out


def test_replay_at_a_rate_keeps_bag_timing(bag, checkpoint, tmp_path):
    result = replay(bag, checkpoint, tmp_path / "out", ReplayOptions(rate=2.0, params={"num_threads": 1}, progress=False))
    assert result.frames_published == 3
    assert result.counts["frames_processed"] + result.counts.get("dropped_stale", 0) == 3


def test_damaged_bags_give_clear_errors_and_keep_the_output_valid(bag, checkpoint, tmp_path, capsys):
    damaged = tmp_path / "damaged"
    shutil.copytree(bag, damaged)
    data = next(p for p in damaged.iterdir() if p.suffix in (".db3", ".mcap"))
    raw = data.read_bytes()
    data.write_bytes(raw[: len(raw) // 2] + bytes(4096))  # truncated mid-file, then garbage
    code = main(["replay", str(damaged), "--checkpoint", str(checkpoint), "--out", str(tmp_path / "out"), "--threads", "1"])
    err = capsys.readouterr().err
    assert code == 2 and str(damaged) in err and ("truncated" in err or "cannot read" in err)
    if (tmp_path / "out").exists():  # whatever was recorded before the damage is a readable bag
        list(read_bag(tmp_path / "out"))
    with pytest.raises(BagError, match="no such bag"):
        bag_topics(tmp_path / "missing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(BagError):
        bag_topics(tmp_path / "empty")


def test_replay_refuses_what_would_not_start_in_one_line(bag, checkpoint, tmp_path, capsys):
    """An existing output, a missing checkpoint, a parameter out of range: one line on stderr and exit 2, no
    traceback, and nothing written."""
    (tmp_path / "exists").mkdir()
    cases = [
        (["--checkpoint", str(checkpoint), "--out", str(tmp_path / "exists")], "exists"),
        (["--checkpoint", str(tmp_path / "missing.safetensors"), "--out", str(tmp_path / "a")], "not found"),
        (["--checkpoint", str(checkpoint), "--out", str(tmp_path / "b"), "--steps", "0"], "ddim_steps"),
    ]
    for args, says in cases:
        code = main(["replay", str(bag), *args, "--threads", "1"])
        err = capsys.readouterr().err
        assert code == 2 and says in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["exists"]


def test_make_bag_refuses_bad_arguments(scene, objects, lmo_dir, tmp_path):
    with pytest.raises(ValueError, match="storage"):
        make_bag(scene, tmp_path / "a", objects, lmo_dir / "models_eval", BagOptions(storage="rosbag1"))
    (tmp_path / "exists").mkdir()
    with pytest.raises(FileExistsError):
        make_bag(scene, tmp_path / "exists", objects, lmo_dir / "models_eval")
    with pytest.raises(ValueError, match="fps"):
        BagOptions(fps=0.0)


def test_make_bag_cli_refuses_bad_arguments_in_one_line(scene, lmo_dir, tmp_path, capsys):
    """An output that exists, data or models missing, a bad rate: one line on stderr and exit 2, nothing written."""
    (tmp_path / "exists").mkdir()
    models = str(lmo_dir / "models_eval")
    cases = [
        (["--data", str(scene), "--out", str(tmp_path / "exists"), "--models", models], "exists"),
        (["--data", str(tmp_path / "none"), "--out", str(tmp_path / "a"), "--models", models], "not found"),
        (["--data", str(scene), "--out", str(tmp_path / "b"), "--models", str(tmp_path / "none")], "not found"),
        (["--data", str(scene), "--out", str(tmp_path / "c"), "--models", models, "--fps", "0"], "fps"),
    ]
    for args, says in cases:
        code = main(["make-bag", *args])
        err = capsys.readouterr().err
        assert code == 2 and says in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["exists"]


def test_a_camera_paths_bag_plays_the_cameras_pose_to_the_node(objects, checkpoint, lmo_dir, tmp_path, monkeypatch):
    """A rendered camera path's bag carries the camera's pose (`/camera/odom`, the optical frame in the world: the
    inverse of the scene's world-to-camera pose), and replay plays it onto the node's camera_odom, where each frame
    finds its own (what `view_window` averages over)."""
    from axispose_core.data.synth.config import CameraPathConfig

    cfg = SynthConfig(seed=21, scenes=1, images_per_scene=3, objects=OBJECTS, camera_path=CameraPathConfig(orbit_deg=5.0))
    generate(cfg, lmo_dir / "models", tmp_path / "data", progress=False)
    scene = BopScene(tmp_path / "data" / "000000")
    make_bag(scene.root, tmp_path / "bag", objects, lmo_dir / "models_eval", BagOptions(storage="mcap", progress=False))
    truth = []
    for im_id in scene.image_ids:
        R, t = scene.camera_poses[im_id]
        truth.append(np.block([[R.T, (-R.T @ t)[:, None]], [np.zeros((1, 3)), np.ones((1, 1))]]))
    odometry = [deserialize(m) for m in read_bag(tmp_path / "bag", [ODOM_TOPIC])]
    assert [(o.header.frame_id, o.child_frame_id) for o in odometry] == [("odom", FRAME_ID)] * 3
    for msg, T in zip(odometry, truth, strict=True):
        np.testing.assert_allclose(pose_matrix(msg.pose.pose.position, msg.pose.pose.orientation), T, atol=1e-9)
    given = []
    pose = FramePoser.pose
    monkeypatch.setattr(FramePoser, "pose", lambda self, *args: given.append(args[-1]) or pose(self, *args))
    params = {"mode": "video_odometry", "view_window": 3}
    assert replay(tmp_path / "bag", checkpoint, tmp_path / "out", ReplayOptions(params=params, progress=False)).frames_published == 3
    assert len(given) == 3
    for T_given, T in zip(given, truth, strict=True):
        np.testing.assert_allclose(T_given, T, atol=1e-6)
    with pytest.raises(BagError, match="no nav_msgs/msg/Odometry topic '/odom'"):
        replay(tmp_path / "bag", checkpoint, tmp_path / "out2", ReplayOptions(odom_topic="/odom", progress=False))


def test_replay_options_refuse_bad_values():
    with pytest.raises(ValueError, match="rate"):
        ReplayOptions(rate=0.0)
    with pytest.raises(ValueError, match="storage"):
        ReplayOptions(storage="rosbag1")


@pytest.mark.slow
def test_make_bag_of_a_scene_as_real_data_comes(scene, objects, lmo_dir, tmp_path, official_like):
    """No scene_gt_info.json or masks: the ROIs are the boxes of the models at the GT pose, as the files'."""
    real = official_like(scene, tmp_path / "real")
    make_bag(real, tmp_path / "real.bag", objects, lmo_dir / "models", BagOptions(storage="mcap", progress=False))
    make_bag(scene, tmp_path / "synth.bag", objects, lmo_dir / "models", BagOptions(storage="mcap", progress=False))

    def rois(path):
        return sorted((m.topic, m.stamp_ns, bytes(m.raw)) for m in read_bag(path) if m.topic.startswith("/roi/"))

    estimated, files = rois(tmp_path / "real.bag"), rois(tmp_path / "synth.bag")
    assert estimated and set(files) <= set(estimated)  # visibility estimated without cut-outs: no instance less


REPO = Path(__file__).resolve().parents[1]


@pytest.mark.slow
@pytest.mark.parametrize("ignore_rois", [False, True])
def test_the_readme_demo_runs_the_shipped_checkpoint_on_the_shipped_bag(ignore_rois, tmp_path, capsys):
    """What `make demo` runs (no ../shared needed: the bag carries the model points), with the bag's boxes and
    with the shipped localiser finding the objects. As `make demo` runs it (the bag's boxes, the checkpoint's
    settings), the poses must clear a floor, so that a broken model or a broken path fails here."""
    ckpt = REPO / "axispose_core" / "models" / "axispose_lmo.safetensors"
    est = Estimator.load(ckpt)
    assert len(est.config.objects) == 8 and est.localiser is not None
    args = ["replay", str(REPO / "demo" / "lmo_sample_bag"), "--checkpoint", str(ckpt), "--out", str(tmp_path / "out"),
            "--report", str(tmp_path / "r.json"), "--overlays", str(tmp_path / "png")]  # fmt: skip
    assert main(args + (["--ignore-rois", "--steps", "1", "--precision", "float32"] if ignore_rois else [])) == 0
    report = json.loads((tmp_path / "r.json").read_text())
    assert report["config"]["precision"] == "float32" or not ignore_rois  # `--precision` reaches the node
    assert report["counts"]["frames_processed"] == 6 and report["objects"]
    if not ignore_rois:  # the demo's floor: the shipped model reads about 0.83 here
        assert report["mean"]["reproj_15px"] >= 0.75, report["mean"]
    out = capsys.readouterr().out
    assert "axispose_node --ros-args -p checkpoint:=" in out and "-r image:=/camera/color/image_raw" in out


@pytest.mark.slow
def test_replay_in_video_mode_publishes_stable_track_ids_and_reports_jitter(tmp_path, capsys):
    """The node in `video` mode, through replay: every posed instance carries a track id that holds across frames,
    the localiser runs only on some frames, and the report has the modes the frames ran in and their jitter. The
    bag's frames are stills, too far apart for contours to hold: without refinement, tracks go by their filters."""
    ckpt = REPO / "axispose_core" / "models" / "axispose_lmo.safetensors"
    args = ["replay", str(REPO / "demo" / "lmo_sample_bag"), "--checkpoint", str(ckpt), "--out", str(tmp_path / "out"),
            "--report", str(tmp_path / "r.json"), "--ignore-rois", "--steps", "3", "--precision", "float32",
            "--mode", "video", "--refine", "off"]  # fmt: skip
    assert main(args) == 0
    report = json.loads((tmp_path / "r.json").read_text())
    counts = report["counts"]
    assert counts["frames_processed"] == 6 and 1 <= counts["tracking_localiser_runs"] < 6 and counts["tracking_tracks_started"] >= 1
    assert report["tracking"]["modes"] == {"video": 6} and report["tracking"]["n"] >= 1 and report["config"]["mode"] == "video"
    frames = [deserialize(m).detections for m in read_bag(tmp_path / "out", ["/axispose/detections"])]
    ids = [{(d.name, d.track_id) for d in dets} for dets in frames]
    assert all(track > 0 for frame in ids for _, track in frame)
    names = {}
    assert all(names.setdefault(track, name) == name for frame in ids for name, track in frame)  # an id keeps its object
    assert ids[0] and len(ids[0] & ids[4]) >= len(ids[0]) / 2  # most first-frame tracks go on to frame 5, same ids
    assert "modes {'video': 6}: jitter" in capsys.readouterr().out
