"""The "train your own object" path of docs/OWN_OBJECT.md, end to end on a textured pybullet_data mesh (the duck:
OBJ + MTL + PNG): mesh -> `axispose synth` -> `axispose train` (a few steps) -> `axispose make-bag` -> the node
via `axispose replay`."""

import json
from pathlib import Path

import numpy as np
import pybullet_data
import pytest
import yaml

from axispose_core.data.bop_models import model_path
from axispose_core.data.meshes import load_ply
from axispose_core.estimator import Estimator
from axispose_ros.cli import main

DUCK = Path(pybullet_data.getDataPath()) / "duck.obj"  # textured: map_Kd duckCM.png


@pytest.mark.slow
def test_textured_duck_from_mesh_to_node(tmp_path, capsys):
    data = tmp_path / "duck_data"
    assert main(["synth", "--models", str(DUCK), "--mesh-units", "0.08", "--out", str(data), "--scenes", "1",
                 "--images-per-scene", "3", "--seed", "7"]) == 0  # fmt: skip
    assert "as object 1" in capsys.readouterr().out
    cfg = tmp_path / "train.yaml"
    cfg.write_text(yaml.safe_dump({"optim": {"steps": 3, "batch": 2, "workers": 0, "warmup": 1, "save_every": 3, "val_every": 3},
                                   "agm": {"denoiser": {"size": 64, "channels": 8, "multipliers": [1, 2], "groups": 4}}}))  # fmt: skip
    colours = load_ply(model_path(data / "models", 1)).colors  # the texture's yellow duck and orange beak, not grey
    assert colours is not None and np.median(colours, axis=0)[0] > 200 and np.median(colours, axis=0)[2] < 60
    ckpt = tmp_path / "duck.safetensors"
    assert main(["train", "--data", str(data), "--out", str(ckpt), "--config", str(cfg), "--threads", "1"]) == 0
    (duck,) = Estimator.load(ckpt).config.objects
    assert duck.obj_id == 1 and 0.12 < duck.diameter < 0.2  # metres: the mesh's units were honoured
    assert duck.name == "duck"  # named after its file, not after LM-O's object 1
    bag = tmp_path / "duck_bag"
    assert main(["make-bag", "--data", str(data / "000000"), "--models", str(data / "models"), "--out", str(bag)]) == 0
    report = tmp_path / "report.json"
    assert main(["replay", str(bag), "--checkpoint", str(ckpt), "--out", str(tmp_path / "out"), "--report", str(report),
                 "--steps", "1", "--threads", "1"]) == 0  # fmt: skip
    got = json.loads(report.read_text())
    assert got["counts"]["frames_processed"] == 3 and set(got["objects"]) == {"1"} and got["objects"]["1"]["n"] >= 1
    assert got["objects"]["1"]["name"] == "duck"
