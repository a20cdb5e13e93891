"""tools/train_gpu.sh, run on the CPU with tiny networks: it plans the schedule from a probe, exports what a later
call needs in parts small enough to come back from the device, resumes from a split state, warm-starts from a
checkpoint (what a GPU lent for a few calls of ten minutes needs), and trains the localiser the same way."""

from __future__ import annotations

import csv
import os
import subprocess
import sys
from pathlib import Path

import yaml

from axispose_core.agm.model import AxisGenerator
from axispose_core.checkpoint import config_from_dict, read_checkpoint
from axispose_core.detect.model import LocaliserConfig
from axispose_core.estimator import Estimator, EstimatorConfig
from axispose_core.tbm.reader import SHIPPED_READER, load_reader
from axispose_core.train.agm import TrainConfig
from axispose_core.train.detector import KIND

REPO = Path(__file__).resolve().parents[1]
SCRIPT = REPO / "tools" / "train_gpu.sh"


def _tiny() -> dict:
    """The AGM's GPU recipe with a network and batch small enough for a CPU test."""
    cfg = yaml.safe_load((REPO / "config" / "train_agm_gpu.yaml").read_text())
    cfg |= {"batch": 2, "workers": 0, "save_every": 1000, "val_every": 100000, "val_samples": 2}
    cfg["agm"]["denoiser"] |= {"channels": 8, "multipliers": [1, 2], "groups": 4}
    return cfg


def _call(
    tmp_path: Path, lmo_dir: Path, work: str, budget: int, resume: Path | None = None, config: dict | None = None, **extra: str
) -> subprocess.CompletedProcess:
    tiny = tmp_path / "tiny.yaml"
    tiny.write_text(yaml.safe_dump(config or _tiny()))
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


def test_refuses_a_budget_with_no_time_to_train_and_an_unknown_trainer(tmp_path, lmo_dir):
    out = _call(tmp_path, lmo_dir, "w", 2)  # RESERVE_S is 2
    assert out.returncode != 0 and "leaves no time to train" in out.stderr
    out = _call(tmp_path, lmo_dir, "w", 60, TRAINER="train-agm")
    assert out.returncode != 0 and "TRAINER is train (the AGM) or train-detector" in out.stderr
    assert not (tmp_path / "w").exists()  # both refused before rendering anything


def test_trains_the_localiser_from_the_shipped_checkpoint(tmp_path, lmo_dir):
    cfg = yaml.safe_load((REPO / "config" / "train_detector_gpu.yaml").read_text())
    cfg |= {"batch": 2, "workers": 0, "save_every": 1000, "val_every": 100000}
    cfg["localiser"] |= {"input_size": [160, 128]}  # the shipped network at a small input: INIT's weights all fit
    shipped = REPO / "axispose_core" / "models" / "axispose_lmo.safetensors"
    export = tmp_path / "out"
    out = _call(tmp_path, lmo_dir, "w", 60, config=cfg, TRAINER="train-detector", INIT=str(shipped), EXPORT=str(export))
    assert out.returncode == 0, out.stderr[-2000:]
    assert "; 0 of" in out.stdout  # warm_start: no tensor of the shipped localiser's left fresh
    record = read_checkpoint(tmp_path / "w" / "run" / "localiser.safetensors", KIND, LocaliserConfig)[2]["training"]
    assert record["steps"] > 0 and record["init"] == str(shipped)
    assert {"localiser.csv", "localiser.safetensors", "train.yaml"} < {f.name for f in export.iterdir()}
    parts = sorted(export.glob("localiser.safetensors.state.pt.*"))  # this network's state is over 15 MB
    assert len(parts) > 1 and all(p.stat().st_size <= 15 * 2**20 for p in parts)
    state = (tmp_path / "w" / "run" / "localiser.safetensors.state.pt").read_bytes()
    assert b"".join(p.read_bytes() for p in parts) == state
