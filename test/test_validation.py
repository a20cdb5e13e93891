"""The real-frame validation command: both passes, depth statistics, one table; on two real slice frames."""

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from conftest import TINY_AGM

from axispose_core.agm.model import AxisGenerator
from axispose_core.cli import main
from axispose_core.data.meshes import refiner_meshes
from axispose_core.estimator import SHIPPED_ESTIMATOR, EstimateOptions, Estimator
from axispose_core.estimator_checkpoint import EstimatorConfig
from axispose_core.evaluation.records import Record
from axispose_core.evaluation.run import EvalOptions, estimator_runs, evaluate
from axispose_core.evaluation.summary import depth_errors, summarize
from axispose_core.lmo import REAL_SLICE
from axispose_core.localiser.model import Localiser, LocaliserConfig
from axispose_core.objects import lmo_objects
from axispose_core.tbm.reader import SHIPPED_READER, load_reader
from axispose_core.tracking.background import LockStepFinder
from axispose_core.tracking.poser import FramePoser
from axispose_core.trunks import ResidualBNConfig
from axispose_core.validation import ValidationSettings, format_validation, run_crops


def _record(t, t_gt, ok=True):
    eye = np.eye(3)
    return Record(1, "s", 0, {}, 0.0, eye, np.array(t_gt), eye, np.array(t), ok, eye, None, (0, 0, 1, 1))


def test_depth_errors_are_the_log_spread_and_the_median_ratio_of_the_posed():
    records = [_record([0, 0, 1.02], [0, 0, 1.0]), _record([0.1, 0, 0.49], [0, 0, 0.5]), _record([0, 0, 9.0], [0, 0, 1.0], ok=False)]
    d = depth_errors(records)
    assert d["depth_log_abs_mean"] == pytest.approx((np.log(1.02) + abs(np.log(0.98))) / 2)
    assert d["depth_ratio_median"] == pytest.approx(1.0)
    assert np.isnan(depth_errors([_record([0, 0, 2.0], [0, 0, 1.0], ok=False)])["depth_ratio_median"])


def _real_frames(out: Path, count: int) -> Path:
    """The first `count` frames of the real validation slice, as their own BOP split in `out`."""
    src = REAL_SLICE / "000002"
    if not src.is_dir():
        pytest.fail(f"the real validation slice is missing at {src} (CI keeps ../shared beside the clone)")
    scene = out / "000002"
    (scene / "rgb").mkdir(parents=True)
    keep = sorted(json.loads((src / "scene_gt.json").read_text()), key=int)[:count]
    for name in ("scene_gt.json", "scene_camera.json"):
        data = json.loads((src / name).read_text())
        (scene / name).write_text(json.dumps({k: data[k] for k in keep}))
    for k in keep:
        shutil.copy(src / "rgb" / f"{int(k):06d}.png", scene / "rgb")
    return out


@pytest.fixture(scope="module")
def two_real_frames(tmp_path_factory):
    """The first two frames of the real validation slice, as their own BOP split."""
    return _real_frames(tmp_path_factory.mktemp("real") / "test", 2)


@pytest.fixture(scope="module")
def tiny_checkpoint(tmp_path_factory, lmo_dir):
    """The tiny estimator of ape and can with an untrained localiser and a contour refiner."""
    reader = load_reader(SHIPPED_READER)
    cfg = EstimatorConfig(agm=TINY_AGM, reader=reader.config, objects=tuple(lmo_objects()[:2]), ddim_steps=1)
    localiser = Localiser(LocaliserConfig(obj_ids=(1, 5), input_size=(160, 128), trunk=ResidualBNConfig(widths=(8, 16, 24, 32))))
    ckpt = tmp_path_factory.mktemp("tiny") / "tiny.safetensors"
    meshes = refiner_meshes(lmo_dir / "models", [1, 5])
    Estimator(cfg, AxisGenerator(cfg.agm), reader).with_localiser(localiser).with_refiner(meshes).save(ckpt)
    return ckpt


def test_validate_scores_gt_crops_and_the_localisers_and_prints_one_table(two_real_frames, tiny_checkpoint, lmo_dir, tmp_path, capsys):
    ckpt = tiny_checkpoint
    out = tmp_path / "val"
    argv = ["validate", "--checkpoint", str(ckpt), "--data", str(two_real_frames), "--models", str(lmo_dir / "models_eval"),
            "--out", str(out), "--steps", "1", "--threads", "1"]  # fmt: skip
    assert main(argv) == 0
    report = json.loads((out / "validation.json").read_text())
    assert set(report) == {"config", "gt", "detect"}
    for crops in ("gt", "detect"):
        assert set(report[crops]["objects"]) == {"1", "5"}  # ape and can, in both frames
        assert report[crops]["objects"]["1"]["n"] == 2
        assert {"depth_log_abs_mean", "depth_ratio_median", "reproj_15px"} <= set(report[crops]["objects"]["1"])
        assert (out / "plots" / crops / "error_cdfs.png").exists()
    assert "det_recall" in report["detect"]["objects"]["5"]
    assert report["config"]["refine"] is True and "rot_err_median_deg" in report["gt"]["instances"]
    table = capsys.readouterr().out
    assert "ape" in table and "can" in table and "mean" in table and "detect crops: AR" in table and "all instances" in table
    assert main([*argv, "--refine", "off"]) == 0
    report = json.loads((out / "validation.json").read_text())
    assert report["config"]["refine"] is False and "refine" not in report["gt"]["mean"]


def test_the_table_sets_each_objects_refined_poses_beside_the_unrefined(two_real_frames, lmo_dir):
    """A report of poses the refiner moved: the `unrefined` columns read each object's scores before it (an object it
    never saw, as it is) and a line says what it refined and kept, with the pooled rotation and depth before it."""
    entry = {"n": 2, "name": "ape", "add_0.1d": 0.5, "reproj_15px": 1.0, "rot_err_median_deg": 3.0, "depth_log_abs_mean": 0.01,
             "depth_ratio_median": 1.0}  # fmt: skip
    unrefined = {"add_0.1d": 0.25, "reproj_15px": 0.75, "rot_err_median_deg": 9.0, "depth_log_abs_mean": 0.04}
    gt = {"objects": {"1": entry | {"refine": {"n": 2, "refined": 1, "kept": {"run_away": 1}, "unrefined": unrefined}},
                      "5": entry | {"name": "can", "add_0.1d": 0.125}},
          "mean": entry | {"refine": {"refined": 1, "kept": {"run_away": 1}, "unrefined": unrefined}},
          "instances": {"rot_err_median_deg": 3.0, "depth_log_abs_mean": 0.01, "unrefined": {"rot_err_median_deg": 9.0,
                                                                                             "depth_log_abs_mean": 0.04}},
          "bop19": {"ar": 0.5, "objects": {}}}  # fmt: skip
    config = {"steps": 1, "hypotheses": 1, "precision": "float32", "score_threshold": 0.3, "visib": [0.1, 1.0]}
    table = format_validation({"config": config, "gt": gt})
    rows = {line.split()[0]: line.split() for line in table.splitlines()}
    assert rows["ape"][7:9] == ["0.500", "0.250"] and rows["can"][7:9] == ["0.125", "0.125"]
    assert "1 refined, kept: run_away 1" in table and "before refinement 9.0°, 4.00%" in table


def test_validate_refuses_a_missing_folder_in_one_line(tmp_path, capsys):
    assert main(["validate", "--data", str(tmp_path / "nowhere"), "--out", str(tmp_path / "o")]) == 2
    assert capsys.readouterr().err.count("\n") == 1


def _detect_pass(report: dict) -> str:
    """A localiser's pass as JSON, its timings and the poser's counts left out (NaN compares equal as text)."""
    return json.dumps({k: v for k, v in report.items() if k not in ("ms_per_object", "poser")}, sort_keys=True)


def _as_before(est: Estimator, data: Path, models: Path, settings: ValidationSettings) -> tuple[list[Record], dict]:
    """The localiser's pass as validate ran it before it took a mode: `Estimator.find` on each frame."""
    options = EstimateOptions(steps=settings.steps, hypotheses=settings.hypotheses, refine=settings.refine)
    predict, find = estimator_runs(est, options, settings.score_threshold)
    objects = list(est.config.objects)
    run = evaluate(predict, data, models, objects, EvalOptions(progress=False, detector=find, visib=settings.visib, bop=True))
    return run.records, summarize(run.records, objects, {"crops": "detect", **run.notes}, run.detection_counts, run.bop)


def _same_pass(est: Estimator, data: Path, models: Path, settings: ValidationSettings) -> dict:
    """`--mode stills` scores as before it took a mode: the same records and report (the poser's counts beside);
    returns those counts."""
    records, report = run_crops(est, "detect", data, models, settings, progress=False)
    old_records, old_report = _as_before(est, data, models, settings)
    assert len(records) == len(old_records) > 0
    for new, old in zip(records, old_records, strict=True):
        assert (new.obj_id, new.im_id, new.ok, json.dumps(new.scores)) == (old.obj_id, old.im_id, old.ok, json.dumps(old.scores))
        np.testing.assert_array_equal(new.R, old.R)
        np.testing.assert_array_equal(new.t, old.t)
    assert _detect_pass(report) == _detect_pass(old_report)
    return report["poser"]


def test_stills_through_the_nodes_poser_scores_as_the_estimators_own_find(two_real_frames, tiny_checkpoint, lmo_dir):
    """`--mode stills` (the default) poses each frame through the node's poser: what `Estimator.find` called
    directly gives (what validate ran before), every box the untrained localiser finds at threshold 0 posed."""
    est = Estimator.load(tiny_checkpoint)
    settings = ValidationSettings(steps=1, score_threshold=0.0)
    assert _same_pass(est, two_real_frames, lmo_dir / "models_eval", settings) == {"mode_stills": 2}


@pytest.mark.slow
def test_stills_through_the_nodes_poser_scores_the_shipped_model_as_its_own_find(tmp_path, lmo_dir):
    """The same with the shipped model on a real frame: poses that hold, refined, some of them dropped by the
    verifier."""
    est = Estimator.load(SHIPPED_ESTIMATOR)
    est.set_precision("float32")
    counts = _same_pass(est, _real_frames(tmp_path, 1), lmo_dir / "models_eval", ValidationSettings(steps=1))
    assert counts["mode_stills"] == 1 and counts["refine_refined"] > 0 and counts["verifier_dropped"] > 0


def test_validate_in_video_mode_follows_each_scene_in_order(two_real_frames, tiny_checkpoint, lmo_dir, tmp_path, monkeypatch, capsys):
    """`--mode video`: the scene's frames go through one tracker in order, stamped at 30 Hz by their place in the
    scene; the report says the mode and what the poser counted."""
    stamps = []
    pose = FramePoser.pose
    monkeypatch.setattr(FramePoser, "pose", lambda self, rgb, K, stamp, *a: stamps.append(stamp) or pose(self, rgb, K, stamp, *a))
    out = tmp_path / "val"
    argv = ["validate", "--checkpoint", str(tiny_checkpoint), "--data", str(two_real_frames), "--models", str(lmo_dir / "models_eval"),
            "--out", str(out), "--steps", "1", "--threads", "1", "--score-threshold", "0", "--mode", "video"]  # fmt: skip
    assert main(argv) == 0
    report = json.loads((out / "validation.json").read_text())
    assert stamps == [0.0, 1 / 30] and report["config"]["mode"] == "video"
    counts = report["detect"]["poser"]
    assert counts["mode_video"] == 2 and counts["tracking_localiser_runs"] >= 1
    assert report["detect"]["objects"]["1"]["n"] == 2 and "mode video" in capsys.readouterr().out


def test_video_odometry_gets_the_recorded_camera_pose_and_searches_lock_step(
    two_real_frames, tiny_checkpoint, lmo_dir, tmp_path, monkeypatch
):
    """Where scene_camera.json gives the camera's pose (world to camera), each frame comes with its inverse (camera
    to fixed, as odometry gives it), and the search runs lock-step in this process and is ended afterwards."""
    data = tmp_path / "test"
    shutil.copytree(two_real_frames, data)
    cameras = json.loads((data / "000002" / "scene_camera.json").read_text())
    R = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    for k, camera in enumerate(cameras.values()):
        camera.update(cam_R_w2c=R.ravel().tolist(), cam_t_w2c=[100.0 * k, 200.0, 300.0])
    (data / "000002" / "scene_camera.json").write_text(json.dumps(cameras))
    given, stopped = [], []
    pose, stop = FramePoser.pose, LockStepFinder.stop
    monkeypatch.setattr(FramePoser, "pose", lambda self, *a: given.append(a[-1]) or pose(self, *a))
    monkeypatch.setattr(LockStepFinder, "stop", lambda self: stopped.append(self) or stop(self))
    settings = ValidationSettings(steps=1, score_threshold=0.0, mode="video_odometry")
    _, report = run_crops(Estimator.load(tiny_checkpoint), "detect", data, lmo_dir / "models_eval", settings, progress=False)
    for k, T in enumerate(given):
        np.testing.assert_allclose(T[:3, :3], R.T)
        np.testing.assert_allclose(T[:3, 3], -R.T @ [0.1 * k, 0.2, 0.3])
    assert len(given) == 2 and report["poser"]["mode_video_odometry"] == 2 and report["poser"]["background_searches"] >= 1
    assert len(stopped) == 1


def test_validate_refuses_an_unknown_mode_as_a_usage_error(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["validate", "--mode", "fast", "--out", str(tmp_path / "o")])
    assert exit_.value.code == 2
    errors = [line for line in capsys.readouterr().err.splitlines() if "error" in line]
    assert len(errors) == 1 and "--mode" in errors[0] and "stills" in errors[0] and "video_odometry" in errors[0]
