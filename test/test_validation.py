"""The real-frame validation command: both passes, depth statistics, one table; on two real slice frames."""

import json
import shutil

import numpy as np
import pytest
from conftest import TINY_AGM

from axispose_core.agm.model import AxisGenerator
from axispose_core.cli import main
from axispose_core.data.meshes import refiner_meshes
from axispose_core.estimator import Estimator
from axispose_core.estimator_checkpoint import EstimatorConfig
from axispose_core.evaluation.records import Record
from axispose_core.evaluation.summary import depth_errors
from axispose_core.lmo import REAL_SLICE
from axispose_core.localiser.model import Localiser, LocaliserConfig
from axispose_core.objects import lmo_objects
from axispose_core.tbm.reader import SHIPPED_READER, load_reader
from axispose_core.trunks import ResidualBNConfig
from axispose_core.validation import format_validation


def _record(t, t_gt, ok=True):
    eye = np.eye(3)
    return Record(1, "s", 0, {}, 0.0, eye, np.array(t_gt), eye, np.array(t), ok, eye, None, (0, 0, 1, 1))


def test_depth_errors_are_the_log_spread_and_the_median_ratio_of_the_posed():
    records = [_record([0, 0, 1.02], [0, 0, 1.0]), _record([0.1, 0, 0.49], [0, 0, 0.5]), _record([0, 0, 9.0], [0, 0, 1.0], ok=False)]
    d = depth_errors(records)
    assert d["depth_log_abs_mean"] == pytest.approx((np.log(1.02) + abs(np.log(0.98))) / 2)
    assert d["depth_ratio_median"] == pytest.approx(1.0)
    assert np.isnan(depth_errors([_record([0, 0, 2.0], [0, 0, 1.0], ok=False)])["depth_ratio_median"])


@pytest.fixture(scope="module")
def two_real_frames(tmp_path_factory):
    """The first two frames of the real validation slice, as their own BOP split."""
    src = REAL_SLICE / "000002"
    if not src.is_dir():
        pytest.fail(f"the real validation slice is missing at {src} (CI keeps ../shared beside the clone)")
    out = tmp_path_factory.mktemp("real") / "test"
    scene = out / "000002"
    (scene / "rgb").mkdir(parents=True)
    keep = sorted(json.loads((src / "scene_gt.json").read_text()), key=int)[:2]
    for name in ("scene_gt.json", "scene_camera.json"):
        data = json.loads((src / name).read_text())
        (scene / name).write_text(json.dumps({k: data[k] for k in keep}))
    for k in keep:
        shutil.copy(src / "rgb" / f"{int(k):06d}.png", scene / "rgb")
    return out


def test_validate_scores_gt_crops_and_the_localisers_and_prints_one_table(two_real_frames, lmo_dir, tmp_path, capsys):
    reader = load_reader(SHIPPED_READER)
    cfg = EstimatorConfig(agm=TINY_AGM, reader=reader.config, objects=tuple(lmo_objects()[:2]), ddim_steps=1)
    localiser = Localiser(LocaliserConfig(obj_ids=(1, 5), input_size=(160, 128), trunk=ResidualBNConfig(widths=(8, 16, 24, 32))))
    ckpt = tmp_path / "tiny.safetensors"
    meshes = refiner_meshes(lmo_dir / "models", [1, 5])
    Estimator(cfg, AxisGenerator(cfg.agm), reader).with_localiser(localiser).with_refiner(meshes).save(ckpt)
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
