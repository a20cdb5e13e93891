"""The direct-regression baseline: keypoint units, exact poses from exact keypoints, learning, checkpoint, CLI."""

import json

import numpy as np
import pytest
import torch
import yaml
from conftest import TINY_AGM_YAML, TINY_ENCODER

from axispose_core.axis_image import axis_keypoints
from axispose_core.baseline.direct import DirectConfig, DirectEstimator, DirectRegressor, keypoints_to_normalised
from axispose_core.camera import instance_crop
from axispose_core.checkpoint import CheckpointError
from axispose_core.cli import main
from axispose_core.data.synth.config import SynthConfig
from axispose_core.data.synth.generate import generate
from axispose_core.metrics import re, te
from axispose_core.objects import lmo_objects
from axispose_core.train.direct import KeypointCropDataset
from axispose_core.train.losses import direct_losses

TINY = TINY_ENCODER


@pytest.fixture(scope="module")
def data(tmp_path_factory, lmo_dir):
    out = tmp_path_factory.mktemp("directdata")
    generate(SynthConfig(seed=11, scenes=1, images_per_scene=3, objects=(1, 5, 6)), lmo_dir / "models", out, progress=False)
    return out


def test_keypoint_units_round_trip():
    model = DirectRegressor(DirectConfig(encoder=TINY))
    crops = torch.randint(0, 256, (3, 3, 64, 64), dtype=torch.uint8)
    objects = torch.tensor([0, 1, 0])
    out = model.keypoints(crops, objects)
    assert out.shape == (3, 4, 2)
    torch.testing.assert_close(keypoints_to_normalised(out, 64), model(crops, objects))


def test_exact_keypoints_give_the_exact_pose():
    spec = lmo_objects()[2]
    est = DirectEstimator(DirectRegressor(DirectConfig(encoder=TINY, objects=(spec,))))
    K = np.array([[572.4, 0, 325.3], [0, 573.6, 242.0], [0, 0, 1.0]])
    R = np.array([[0.36, 0.48, -0.8], [-0.8, 0.6, 0.0], [0.48, 0.64, 0.6]])
    t = np.array([0.03, -0.05, 0.7])
    box = (300.0, 150.0, 90.0, 90.0)
    image = np.zeros((480, 640, 3), np.uint8)
    K_patch = instance_crop(image, K, box, 64, pad=1.25).K_patch
    kp = torch.from_numpy(axis_keypoints(K_patch, R, t, spec.axes.lengths)).float()
    est.model.keypoints = lambda crops, objects: kp.expand(len(crops), 4, 2)  # an oracle regressor
    (res,) = est.estimate(image, K, [(spec.obj_id, box)])
    assert res.ok and re(res.R, R) < 0.05 and te(res.t, t) < 1e-4
    with pytest.raises(ValueError, match="not in this checkpoint"):
        est.estimate(image, K, [(99, box)])


@pytest.mark.slow
def test_loss_falls_on_a_tiny_set(data):
    objects = [o for o in lmo_objects() if o.obj_id in (1, 5, 6)]
    ds = KeypointCropDataset([data], objects, 64, jitter=None, color_aug=False)
    batch = {k: torch.stack([ds[i][k] for i in range(min(8, len(ds)))]) for k in ("crop", "keypoints", "object")}
    torch.manual_seed(0)
    model = DirectRegressor(DirectConfig(encoder=TINY))
    opt = torch.optim.Adam(model.parameters(), lr=2e-3)
    first = direct_losses(model, batch)["total"].item()
    for _ in range(60):
        loss = direct_losses(model, batch)["total"]
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert loss.item() < 0.3 * first


def test_train_direct_cli_then_eval_and_resume(data, lmo_dir, tmp_path):
    cfg = tmp_path / "cfg.yaml"
    optim = {"steps": 4, "batch": 2, "workers": 0, "warmup": 1, "save_every": 2, "val_every": 2}
    fields = {"optim": optim, "val_samples": 4, "size": 64, "encoder": TINY_AGM_YAML["denoiser"]["encoder"]}
    cfg.write_text(yaml.safe_dump(fields))
    out = tmp_path / "direct.safetensors"
    args = ["train-direct", "--data", str(data), "--val", str(data), "--out", str(out), "--config", str(cfg), "--threads", "1"]
    assert main(args) == 0
    est = DirectEstimator.load(out)
    assert {o.obj_id for o in est.model.config.objects} == {1, 5, 6}
    rows = (tmp_path / "direct.csv").read_text().splitlines()
    assert rows[0] == "step,samples,loss,lr,seconds,val_rot_median_deg,val_rot_within_15deg,val_kp_err_px,val_depth_head"
    assert any(r.split(",")[5] for r in rows[1:])
    assert torch.load(str(out) + ".state.pt", weights_only=False)["step"] == 4
    longer = tmp_path / "longer.yaml"
    longer.write_text(yaml.safe_dump(fields | {"optim": optim | {"steps": 6}}))
    assert main([*args[:-4], "--config", str(longer), "--resume", str(out) + ".state.pt", "--threads", "1"]) == 0
    assert torch.load(str(out) + ".state.pt", weights_only=False)["step"] == 6
    report = tmp_path / "rep.json"
    ev = ["eval", "--checkpoint", str(out), "--data", str(data), "--models", str(lmo_dir / "models_eval"), "--report", str(report),
          "--limit", "3", "--threads", "1"]  # fmt: skip
    assert main(ev) == 0
    got = json.loads(report.read_text())
    assert got["config"]["model"] == "direct_regressor" and got["objects"]
    assert main([*ev, "--crops", "detect"]) == 2
    with pytest.raises(CheckpointError, match="expected 'estimator'"):
        from axispose_core.estimator import Estimator

        Estimator.load(out)
