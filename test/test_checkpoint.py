import json
from dataclasses import dataclass, field

import pytest
import torch
from safetensors.torch import save_file

from axispose_core.checkpoint import CheckpointError, config_from_dict, read_checkpoint, save_checkpoint


@dataclass(frozen=True)
class Inner:
    size: int = 64


@dataclass(frozen=True)
class Outer:
    name: str
    inner: Inner = field(default_factory=Inner)
    scales: tuple[float, ...] = (1.0,)


def test_nested_config_round_trip(tmp_path):
    cfg = Outer("x", Inner(32), (0.5, 2.0))
    save_checkpoint(tmp_path / "c.safetensors", "test", cfg, {"net": torch.nn.Linear(2, 2)}, extra={"steps": 3})
    again, states, extra = read_checkpoint(tmp_path / "c.safetensors", "test", Outer)
    assert again == cfg
    assert set(states["net"]) == {"weight", "bias"}
    assert extra == {"steps": 3}


def test_config_errors_name_the_key():
    with pytest.raises(CheckpointError, match="missing key 'name'"):
        config_from_dict(Outer, {})
    with pytest.raises(CheckpointError, match=r"unknown key\(s\) \['colour'\]"):
        config_from_dict(Outer, {"name": "x", "colour": 1})
    with pytest.raises(CheckpointError, match=r"inner.*unknown key"):
        config_from_dict(Outer, {"name": "x", "inner": {"size": 3, "depth": 2}})


def test_foreign_safetensors_file_is_refused(tmp_path):
    path = tmp_path / "foreign.safetensors"
    save_file({"w": torch.zeros(2)}, str(path), metadata={"format": "pt"})
    with pytest.raises(CheckpointError, match="not an AxisPose checkpoint"):
        read_checkpoint(path, "test", Outer)


def test_corrupt_config_metadata_is_refused(tmp_path):
    path = tmp_path / "bad.safetensors"
    save_file({"net.w": torch.zeros(2)}, str(path), metadata={"format": "axispose/1", "kind": "test", "config": json.dumps({"inner": {}})})
    with pytest.raises(CheckpointError, match="missing key 'name'"):
        read_checkpoint(path, "test", Outer)
