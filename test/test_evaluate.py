"""Eval report: schema, perfect scores for a ground-truth predictor, failures counted as wrong."""

import dataclasses
import json
import shutil

import cv2
import numpy as np
import pytest

from axispose_core.cli import main
from axispose_core.data.bop import BopFormatError
from axispose_core.data.bop_scene import BopScene
from axispose_core.data.synth.config import SynthConfig
from axispose_core.data.synth.generate import generate
from axispose_core.data.synth.preview import contact_sheet
from axispose_core.evaluation.records import Prediction
from axispose_core.evaluation.report import plot_cdfs, plot_grid, plot_uncertainty, write_report
from axispose_core.evaluation.run import EvalOptions, evaluate
from axispose_core.evaluation.summary import summarize
from axispose_core.objects import objects_from_models
from axispose_core.stress import low_light, motion_blur

KEYS = {"n", "name", "add_0.1d", "add_0.2d", "reproj_5px", "reproj_15px", "rot_err_median_deg", "trans_err_median_mm",
        "depth_log_abs_mean", "depth_ratio_median"}  # fmt: skip
QUIET = EvalOptions(progress=False)


@pytest.fixture(scope="module")
def scenes(tmp_path_factory, lmo_dir):
    out = tmp_path_factory.mktemp("evaldata")
    generate(SynthConfig(seed=5, scenes=1, images_per_scene=2, objects=(1, 5, 10)), lmo_dir / "models", out, progress=False)
    return out


def _gt_predictor(scene_dir, scramble=False, tilt_deg=None, seen=None):
    """The GT poses; scrambled (and refused), or tilted about the camera's X by `tilt_deg(k)` degrees for the
    k-th pose with that tilt as its spread; `seen` collects the images it was given."""
    scene = BopScene(scene_dir)
    frames = {im_id: {g.obj_id: g for g in scene.gt[im_id]} for im_id in scene.image_ids}
    calls = iter(scene.image_ids)
    count = iter(range(1000))

    def predict(image, K, boxes):
        if seen is not None:
            seen.append(image)
        im_id = next(calls)
        while not all(o in frames[im_id] for o, _ in boxes):
            im_id = next(calls)
        out = []
        for obj_id, _ in boxes:
            g = frames[im_id][obj_id]
            if tilt_deg is None:
                out.append(Prediction(g.R, g.t + (0.5 if scramble else 0.0), not scramble))
            else:
                a = np.radians(tilt_deg(next(count)))
                Rx = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
                out.append(Prediction(Rx @ g.R, g.t, True, np.degrees(a)))
        return out

    return predict


def test_ground_truth_predictor_scores_perfectly(scenes, lmo_dir, tmp_path):
    objects = objects_from_models(scenes)
    records = evaluate(_gt_predictor(scenes / "000000"), scenes, lmo_dir / "models_eval", objects, QUIET).records
    assert records
    report = summarize(records, objects, {"note": "gt"})
    write_report(report, tmp_path / "r.json")
    again = json.loads((tmp_path / "r.json").read_text())
    assert set(again) == {"objects", "mean", "instances", "ms_per_object", "config"}
    assert again["instances"]["add_0.1d"] == 1.0 and again["instances"]["rot_err_median_deg"] == pytest.approx(0.0, abs=1e-6)
    for entry in again["objects"].values():
        assert set(entry) == KEYS
        assert entry["add_0.1d"] == entry["reproj_5px"] == 1.0
        assert entry["rot_err_median_deg"] == pytest.approx(0.0, abs=1e-6)
    assert again["mean"]["add_0.1d"] == 1.0
    assert set(again["ms_per_object"]) == {"median", "p90"}
    assert plot_cdfs(records, objects, tmp_path).stat().st_size > 5000
    bag_record = dataclasses.replace(records[0], rgb_path=None)  # a bag replay's records have no image file
    assert plot_grid([*records, bag_record], objects, lmo_dir / "models_eval", tmp_path).stat().st_size > 5000


def test_contact_sheet_tiles_frames_and_refuses_an_unreadable_one(scenes, tmp_path):
    sheet = cv2.imread(str(contact_sheet(scenes, tmp_path / "sheet.png", count=2, columns=2, tile_width=200)))
    assert sheet.shape == (150, 400, 3) and sheet.std() > 10
    broken = tmp_path / "broken"
    shutil.copytree(scenes, broken)
    scene = BopScene(broken / "000000")
    scene.rgb_path(scene.image_ids[0]).write_bytes(b"not an image")
    with pytest.raises(BopFormatError, match="unreadable image"):
        contact_sheet(broken, tmp_path / "broken.png")


def test_evaluation_of_a_scene_as_real_data_comes(scenes, lmo_dir, tmp_path, official_like):
    """No scene_gt_info.json, no masks, GT rotations off orthonormal as the official LM-O GT: visibility is
    estimated from the models, the rotations are projected, and the report says both."""
    real = official_like(scenes / "000000", tmp_path / "real" / "000000")
    objects = objects_from_models(scenes)
    run = evaluate(_gt_predictor(real), real.parent, lmo_dir / "models_eval", objects, QUIET)
    records = run.records
    assert run.notes == {
        "visibility_estimated_scenes": ["000000"],
        "gt_rotations_projected": sum(len(v) for v in BopScene(real).gt.values()),
    }
    assert records and all(r.scores["add_0.1d"] == 1.0 for r in records)
    # Unannotated distractors and cut-outs hide nothing in the estimate: it counts at least the files' instances.
    assert len(records) >= len(evaluate(_gt_predictor(scenes / "000000"), scenes, lmo_dir / "models_eval", objects, QUIET).records)


def test_a_symmetric_objects_equivalent_pose_is_no_error(scenes, lmo_dir):
    """Every pose turned half about its model's z axis: the eggbox looks the same so (as ADD-S) its rotation and
    reprojection errors vanish; the ape and the can are 180 degrees off."""
    objects = objects_from_models(scenes)
    gt, half_turn = _gt_predictor(scenes / "000000"), np.diag([-1.0, -1.0, 1.0])

    def turned(image, K, boxes):
        return [dataclasses.replace(p, R=p.R @ half_turn) for p in gt(image, K, boxes)]

    report = summarize(evaluate(turned, scenes, lmo_dir / "models_eval", objects, QUIET).records, objects, {})
    eggbox, others = report["objects"]["10"], [report["objects"][k] for k in ("1", "5")]  # by obj_id
    assert eggbox["reproj_5px"] == eggbox["add_0.1d"] == 1.0 and eggbox["rot_err_median_deg"] == pytest.approx(0.0, abs=1e-6)
    assert all(e["reproj_15px"] == 0.0 and e["rot_err_median_deg"] == pytest.approx(180.0) for e in others)


def test_failed_poses_count_as_wrong(scenes, lmo_dir):
    objects = objects_from_models(scenes)
    records = evaluate(_gt_predictor(scenes / "000000", scramble=True), scenes, lmo_dir / "models_eval", objects, QUIET).records
    report = summarize(records, objects, {})
    assert report["mean"]["add_0.2d"] == 0.0 and report["mean"]["reproj_15px"] == 0.0
    assert all(np.isinf(r.scores["trans_err_mm"]) for r in records)


def test_a_refined_pose_is_scored_beside_the_pose_before_it(scenes, lmo_dir):
    """A predictor whose poses were refined from ones 0.2 m off (and one kept): the report gives per object the
    refined poses' scores, the unrefined ones' under `refine`, and what the refiner kept and why."""
    objects = objects_from_models(scenes)
    inner, seen = _gt_predictor(scenes / "000000"), []

    def predict(image, K, boxes):
        out = []
        for p in inner(image, K, boxes):
            kept = not seen
            seen.append(p)
            off = (p.R, p.t + 0.2)
            out.append(dataclasses.replace(p, R=off[0], t=off[1], unrefined=off, refine_kept="run_away") if kept
                       else dataclasses.replace(p, unrefined=off))  # fmt: skip
        return out

    report = summarize(evaluate(predict, scenes, lmo_dir / "models_eval", objects, QUIET).records, objects, {})
    refine = report["mean"]["refine"]
    assert refine["refined"] == len(seen) - 1 and refine["kept"] == {"run_away": 1}
    assert refine["unrefined"]["add_0.1d"] == 0.0 and refine["unrefined"]["depth_log_abs_mean"] > 0.1
    assert 0.5 < report["mean"]["add_0.1d"] < 1.0  # all right but the kept one
    assert all(e["refine"]["unrefined"]["reproj_15px"] == 0.0 for e in report["objects"].values())


def test_low_visibility_instances_are_skipped(scenes, lmo_dir):
    objects = objects_from_models(scenes)
    scene = BopScene(scenes / "000000")
    visible = sum(i.visib_fract >= 0.1 for im in scene.image_ids for i in scene.gt_info[im])
    assert len(evaluate(_gt_predictor(scenes / "000000"), scenes, lmo_dir / "models_eval", objects, QUIET).records) == visible


@pytest.mark.slow
def test_eval_cli_writes_the_report(scenes, lmo_dir, tmp_path, official_like):
    from conftest import TINY_AGM

    from axispose_core.agm.model import AxisGenerator
    from axispose_core.estimator import Estimator
    from axispose_core.estimator_checkpoint import EstimatorConfig
    from axispose_core.tbm.reader import SHIPPED_READER, load_reader

    reader = load_reader(SHIPPED_READER)
    cfg = EstimatorConfig(
        agm=TINY_AGM,
        reader=reader.config,
        objects=tuple(objects_from_models(scenes)),
        ddim_steps=1,
    )
    Estimator(cfg, AxisGenerator(cfg.agm), reader).save(tmp_path / "est.safetensors")
    args = ["eval", "--checkpoint", str(tmp_path / "est.safetensors"), "--data", str(scenes), "--models", str(lmo_dir / "models_eval"),
            "--report", str(tmp_path / "rep.json"), "--limit", "4", "--threads", "1"]  # fmt: skip
    assert main(args) == 0
    report = json.loads((tmp_path / "rep.json").read_text())
    assert report["config"]["steps"] == 1 and report["objects"]
    real = official_like(scenes / "000000", tmp_path / "r" / "000000")
    official = [*args[:3], "--data", str(real), *args[5:7], "--report", str(tmp_path / "real.json"), "--limit", "2"]
    assert main(official) == 0
    config = json.loads((tmp_path / "real.json").read_text())["config"]
    assert config["visibility_estimated_scenes"] == ["000000"] and config["gt_rotations_projected"] > 0
    stress = [*args[:-4], "--report", str(tmp_path / "stress.json"), "--hypotheses", "2"]
    stress += ["--perturb", "motion_blur", "--visib", "0.1", "0.9"]
    assert main(stress) == 0
    config = json.loads((tmp_path / "stress.json").read_text())["config"]
    assert (config["hypotheses"], config["perturb"], config["visib"]) == (2, "motion_blur", [0.1, 0.9])


def test_visibility_band_keeps_only_its_instances(scenes, lmo_dir):
    objects = objects_from_models(scenes)
    scene = BopScene(scenes / "000000")
    band = sum(0.1 <= i.visib_fract <= 0.7 for im in scene.image_ids for i in scene.gt_info[im])
    records = evaluate(
        _gt_predictor(scenes / "000000"), scenes, lmo_dir / "models_eval", objects, EvalOptions(progress=False, visib=(0.1, 0.7))
    ).records
    assert len(records) == band
    with pytest.raises(ValueError, match="visib"):
        evaluate(_gt_predictor(scenes / "000000"), scenes, lmo_dir / "models_eval", objects, EvalOptions(visib=(0.0, 1.0)))


def test_perturbation_reaches_the_predictor_seeded_per_frame(scenes, lmo_dir):
    objects = objects_from_models(scenes)
    runs = []
    for perturb in (None, low_light, low_light):
        seen = []
        evaluate(
            _gt_predictor(scenes / "000000", seen=seen),
            scenes,
            lmo_dir / "models_eval",
            objects,
            EvalOptions(progress=False, perturb=perturb),
        )
        runs.append(seen)
    clean, dim, dim_again = runs
    assert all(d.mean() < 0.35 * c.mean() for c, d in zip(clean, dim, strict=True))
    assert all(np.array_equal(a, b) for a, b in zip(dim, dim_again, strict=True))  # reproducible


def test_spread_that_tracks_the_error_is_reported_as_predictive(scenes, lmo_dir, tmp_path):
    objects = objects_from_models(scenes)
    predict = _gt_predictor(scenes / "000000", tilt_deg=lambda k: [1.0, 40.0, 3.0, 90.0, 2.0, 60.0][k % 6] + 0.01 * k)
    records = evaluate(predict, scenes, lmo_dir / "models_eval", objects, QUIET).records
    assert len(records) >= 4
    q = summarize(records, objects, {})["spread"]
    assert q["spearman_vs_rot_err"] == pytest.approx(1.0)
    assert q["reproj_15px_least_half"] >= q["reproj_15px_all_posed"]
    assert plot_uncertainty(records, tmp_path, "spread_deg").stat().st_size > 5000
    assert "spread" not in summarize([r for r in records if False], objects, {})  # no spreads, no entry
    assert "sigma" not in summarize(records, objects, {}) and "calibration" not in summarize(records, objects, {})


def test_covariance_is_checked_against_the_errors(scenes, lmo_dir, tmp_path):
    """Poses tilted about the camera's X by a, reported with a rotation covariance of standard deviation a / 2 about
    X and 100 a about Y and Z, and the translation exact: every rotation error is two standard deviations (squared
    Mahalanobis length 4, between χ²(3)'s 68 and 95 % quantiles), whichever the object's own axes; the rotation
    sigma ranks the poses by their error."""
    objects = objects_from_models(scenes)
    tilts = [1.0, 40.0, 3.0, 90.0, 2.0, 60.0]

    def cov(a_deg: float) -> np.ndarray:
        a = np.radians(a_deg)
        return np.diag([1e-6] * 3 + [(a / 2) ** 2, (100 * a) ** 2, (100 * a) ** 2])

    inner = _gt_predictor(scenes / "000000", tilt_deg=lambda k: tilts[k % 6] + 0.01 * k)

    def predict(image, K, boxes):
        return [Prediction(p.R, p.t, p.ok, covariance=cov(p.spread_deg)) for p in inner(image, K, boxes)]

    records = evaluate(predict, scenes, lmo_dir / "models_eval", objects, QUIET).records
    report = summarize(records, objects, {})
    q = report["calibration"]
    assert q["n"] == sum(not o.symmetric for o in objects for r in records if r.obj_id == o.obj_id) >= 4
    assert q["rotation_median_d2"] == pytest.approx(4.0, rel=1e-6) and q["translation_median_d2"] == pytest.approx(0.0, abs=1e-6)
    assert (q["rotation_within_68"], q["rotation_within_95"], q["translation_within_68"]) == (0.0, 1.0, 1.0)
    assert report["sigma"]["spearman_vs_rot_err"] == pytest.approx(1.0)
    assert plot_uncertainty(records, tmp_path, "sigma_deg").name == "error_vs_sigma.png"


def test_low_light_darkens_and_adds_noise():
    rgb = np.full((60, 80, 3), 200, np.uint8)
    out = low_light(rgb, np.random.default_rng(0))
    assert out.shape == rgb.shape and out.dtype == np.uint8
    assert 0.1 * 200 < out.mean() < 0.32 * 200 and out.std() > 1.0
    assert np.array_equal(out, low_light(rgb, np.random.default_rng(0)))


def test_motion_blur_smears_edges_but_keeps_brightness():
    rgb = np.random.default_rng(0).integers(0, 256, (64, 64, 3)).astype(np.uint8)  # white noise: any streak smooths it

    def edges(im):
        im = im.astype(int)
        return np.abs(np.diff(im, axis=0)).mean() + np.abs(np.diff(im, axis=1)).mean()

    for seed in range(5):
        out = motion_blur(rgb, np.random.default_rng(seed), length=(15, 15))
        assert out.shape == rgb.shape and out.dtype == np.uint8
        assert abs(float(out.mean()) - float(rgb.mean())) < 3.0
        assert edges(out) < 0.6 * edges(rgb)
