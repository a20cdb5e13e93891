"""Eval report: schema, perfect scores for a ground-truth predictor, failures counted as wrong."""

import json

import numpy as np
import pytest

from axispose_core.cli import main
from axispose_core.data.bop import BopScene
from axispose_core.data.objects import objects_from_models
from axispose_core.data.synth.config import SynthConfig
from axispose_core.data.synth.generate import generate
from axispose_core.evaluate import Prediction, evaluate, plot_cdfs, plot_grid, summarize, write_report

KEYS = {"n", "name", "add_0.1d", "add_0.2d", "reproj_5px", "reproj_15px", "rot_err_median_deg", "trans_err_median_mm"}


@pytest.fixture(scope="module")
def scenes(tmp_path_factory, lmo_dir):
    out = tmp_path_factory.mktemp("evaldata")
    generate(SynthConfig(seed=5, scenes=1, images_per_scene=2, objects=(1, 5, 10)), lmo_dir / "models", out, progress=False)
    return out


def _gt_predictor(scene_dir, scramble=False):
    scene = BopScene(scene_dir)
    frames = {im_id: {g.obj_id: g for g in scene.gt[im_id]} for im_id in scene.image_ids}
    calls = iter(scene.image_ids)

    def predict(image, K, boxes):
        im_id = next(calls)
        while not all(o in frames[im_id] for o, _ in boxes):
            im_id = next(calls)
        out = []
        for obj_id, _ in boxes:
            g = frames[im_id][obj_id]
            out.append(Prediction(g.R, g.t + (0.5 if scramble else 0.0), not scramble))
        return out

    return predict


def test_ground_truth_predictor_scores_perfectly(scenes, lmo_dir, tmp_path):
    objects = objects_from_models(scenes)
    records = evaluate(_gt_predictor(scenes / "000000"), scenes, lmo_dir / "models_eval", objects, progress=False)
    assert records
    report = summarize(records, objects, {"note": "gt"})
    write_report(report, tmp_path / "r.json")
    again = json.loads((tmp_path / "r.json").read_text())
    assert set(again) == {"objects", "mean", "ms_per_object", "config"}
    for entry in again["objects"].values():
        assert set(entry) == KEYS
        assert entry["add_0.1d"] == entry["reproj_5px"] == 1.0
        assert entry["rot_err_median_deg"] == pytest.approx(0.0, abs=1e-6)
    assert again["mean"]["add_0.1d"] == 1.0
    assert set(again["ms_per_object"]) == {"median", "p90"}
    assert plot_cdfs(records, objects, tmp_path).stat().st_size > 5000
    assert plot_grid(records, objects, lmo_dir / "models_eval", tmp_path).stat().st_size > 5000


def test_failed_poses_count_as_wrong(scenes, lmo_dir):
    objects = objects_from_models(scenes)
    records = evaluate(_gt_predictor(scenes / "000000", scramble=True), scenes, lmo_dir / "models_eval", objects, progress=False)
    report = summarize(records, objects, {})
    assert report["mean"]["add_0.2d"] == 0.0 and report["mean"]["reproj_15px"] == 0.0
    assert all(np.isinf(r.scores["trans_err_mm"]) for r in records)


def test_low_visibility_instances_are_skipped(scenes, lmo_dir):
    objects = objects_from_models(scenes)
    scene = BopScene(scenes / "000000")
    visible = sum(i.visib_fract >= 0.1 for im in scene.image_ids for i in scene.gt_info[im])
    assert len(evaluate(_gt_predictor(scenes / "000000"), scenes, lmo_dir / "models_eval", objects, progress=False)) == visible


def test_eval_cli_writes_the_report(scenes, lmo_dir, tmp_path):
    from axispose_core.agm.denoiser import DenoiserConfig
    from axispose_core.agm.model import AGMConfig, AxisGenerator
    from axispose_core.estimator import Estimator, EstimatorConfig
    from axispose_core.tbm.reader import SHIPPED_READER, load_reader

    reader = load_reader(SHIPPED_READER)
    cfg = EstimatorConfig(
        agm=AGMConfig(denoiser=DenoiserConfig(channels=8, multipliers=(1, 2), groups=4)),
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
