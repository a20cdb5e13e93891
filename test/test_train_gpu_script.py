"""tools/train_agm_gpu.sh, run on the CPU with a tiny network: it plans the schedule from a probe, exports what a
later call needs in parts small enough to come back from the device, resumes from a split state, and warm-starts
from a checkpoint (what a GPU lent for a few calls of ten minutes needs)."""

from __future__ import annotations

import csv
import os
import subprocess
import sys
from pathlib import Path

import yaml

from axispose_core.agm.model import AxisGenerator
from axispose_core.checkpoint import config_from_dict
from axispose_core.estimator import Estimator, EstimatorConfig
from axispose_core.tbm.reader import SHIPPED_READER, load_reader
from axispose_core.train.agm import TrainConfig

REPO = Path(__file__).resolve().parents[1]
SCRIPT = REPO / "tools" / "train_agm_gpu.sh"


def _tiny() -> dict:
    """The GPU recipe with a network and batch small enough for a CPU test."""
    cfg = yaml.safe_load((REPO / "config" / "train_agm_gpu.yaml").read_text())
    cfg |= {"batch": 2, "workers": 0, "save_every": 1000, "val_every": 100000, "val_samples": 2}
    cfg["agm"]["denoiser"] |= {"channels": 8, "multipliers": [1, 2], "groups": 4}
    return cfg


def _call(tmp_path: Path, lmo_dir: Path, work: str, budget: int, resume: Path | None = None, **extra: str) -> subprocess.CompletedProcess:
    tiny = tmp_path / "tiny.yaml"
    tiny.write_text(yaml.safe_dump(_tiny()))
    knobs = {"CONFIG": str(tiny), "DEVICE": "cpu", "PROBE_MINUTES": "0.25", "VAL_SCENES": "1", "RESERVE_S": "2"}
    env = os.environ | knobs | extra | {"PYTHON": sys.executable}  # CI runs the venv's python without activating it
    args = ["bash", str(SCRIPT), str(lmo_dir / "models"), str(tmp_path / work), str(budget), "2", "77:1"]
    return subprocess.run(args + ([str(resume)] if resume else []), cwd=REPO, env=env, capture_output=True, text=True, timeout=300)


def _steps(run: Path) -> list[int]:
    return [int(r["step"]) for r in csv.DictReader(open(run / "agm.csv"))]


def test_plans_the_schedule_then_resumes_from_a_split_state(tmp_path, lmo_dir):
    agm = config_from_dict(TrainConfig, _tiny()).agm
    reader = load_reader(SHIPPED_READER)
    init = tmp_path / "init.safetensors"  # a warm start, as from the shipped model
    Estimator(EstimatorConfig(agm=agm, reader=reader.config), AxisGenerator(agm), reader).save(init)
    export = tmp_path / "out"
    first = _call(tmp_path, lmo_dir, "w1", 60, INIT=str(init), EXPORT=str(export))
    assert first.returncode == 0, first.stderr[-2000:]
    planned = yaml.safe_load((tmp_path / "w1" / "train.yaml").read_text())["steps"]
    run1 = tmp_path / "w1" / "run"
    record = Estimator.load(run1 / "agm.safetensors").config.training
    reached = record["steps"]
    assert 0 < reached < planned  # the schedule spans two calls, so the first stops about half-way
    assert record["init"] == str(init)  # the probe started from it; the planned run resumed the probe
    assert sorted(f.name for f in export.iterdir()) == ["agm.csv", "agm.safetensors", "agm.safetensors.state.pt.00", "train.yaml"]
    assert (export / "agm.safetensors.state.pt.00").read_bytes() == (run1 / "agm.safetensors.state.pt").read_bytes()

    carried = tmp_path / "carried"  # the export, with the state in two parts as a full-size network's would be
    carried.mkdir()
    for name in ("train.yaml", "agm.csv"):
        (carried / name).write_text((export / name).read_text())
    state = (export / "agm.safetensors.state.pt.00").read_bytes()
    (carried / "agm.safetensors.state.pt.00").write_bytes(state[: len(state) // 2])
    (carried / "agm.safetensors.state.pt.01").write_bytes(state[len(state) // 2 :])

    second = _call(tmp_path, lmo_dir, "w2", 30, carried)
    assert second.returncode == 0, second.stderr[-2000:]
    record = Estimator.load(tmp_path / "w2" / "run" / "agm.safetensors").config.training
    assert reached < record["steps"] <= planned and record["init"] == str(init)
    logged = _steps(tmp_path / "w2" / "run")  # one log across both calls, every 10 steps
    assert logged == list(range(10, record["steps"] + 1, 10))


def test_refuses_a_budget_with_no_time_to_train(tmp_path, lmo_dir):
    out = _call(tmp_path, lmo_dir, "w", 2)  # RESERVE_S is 2
    assert out.returncode != 0 and "leaves no time to train" in out.stderr
    assert not (tmp_path / "w").exists()  # refused before rendering anything
