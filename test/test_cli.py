from dataclasses import replace
from pathlib import Path

import pytest

from axispose_core.cli import main
from axispose_core.estimator import Estimator
from axispose_core.train.agm import TrainConfig
from axispose_core.train.command import training_config
from axispose_core.train.direct import DirectTrainConfig
from axispose_core.train.localiser import LocaliserTrainConfig
from axispose_ros.node import DEFAULT_CHECKPOINT


def test_geometry_demo_recovers_every_pose(tmp_path, capsys):
    assert main(["demo", "--out", str(tmp_path), "--seed", "3"]) == 0
    out = capsys.readouterr().out
    assert "driller" in out and "failed" not in out
    rows = [line.split() for line in out.splitlines() if line.split()[:1] and line.split()[1:2] in (["net"], ["line-fit"])]
    assert len(rows) == 16
    assert all(float(r[2]) < 5.0 for r in rows)  # rotation error of a clean axis image, degrees
    assert (tmp_path / "geometry_demo.png").stat().st_size > 10_000


CONFIGS = sorted((Path(__file__).resolve().parents[1] / "config").glob("train_*.yaml"))


@pytest.mark.parametrize("path", CONFIGS, ids=[p.name for p in CONFIGS])
def test_shipped_training_configs_load_into_their_dataclasses(path):
    kinds = {"train_agm": TrainConfig, "train_direct": DirectTrainConfig, "train_localiser": LocaliserTrainConfig}
    cls = next(c for prefix, c in kinds.items() if path.name.startswith(prefix))
    cfg = training_config(cls, str(path))  # unknown or misspelt fields raise
    if path.name == "train_agm.yaml":  # the defaults are the shipped recipe's first stage
        assert cfg == TrainConfig()
    if path.name == "train_agm_gpu.yaml":  # the CPU recipe's network and stream, a larger batch: --init a CPU run
        assert cfg.agm == training_config(TrainConfig, str(path.with_name("train_agm.yaml"))).agm
    if path.name == "train_localiser.yaml":  # the shipped localiser's network, so --init can be the shipped model
        assert cfg.localiser == replace(Estimator.load(DEFAULT_CHECKPOINT).config.localiser, obj_ids=())
