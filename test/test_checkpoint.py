import json

import pytest
import torch
from safetensors import safe_open
from safetensors.torch import save_file
from test_config import Inner, Outer  # the same small nested configs the parser is tested on

from axispose_core.checkpoint import CheckpointError, read_checkpoint, save_checkpoint


def test_shipped_checkpoint_written_before_kinds_loads_with_its_classes_kinds():
    from axispose_core.estimator import Estimator
    from axispose_ros.node import DEFAULT_CHECKPOINT

    cfg = Estimator.load(DEFAULT_CHECKPOINT).config
    assert cfg.agm.denoiser.kind == "unet" and cfg.localiser.kind == "centernet"


def test_nested_config_round_trip(tmp_path):
    cfg = Outer("x", Inner(32), (0.5, 2.0))
    save_checkpoint(tmp_path / "c.safetensors", "test", cfg, {"net": torch.nn.Linear(2, 2)}, extra={"steps": 3})
    again, states, extra = read_checkpoint(tmp_path / "c.safetensors", "test", Outer)
    assert again == cfg
    assert set(states["net"]) == {"weight", "bias"}
    assert extra == {"steps": 3}


def test_a_section_reads_alone_whatever_the_rest_of_the_config_holds(tmp_path):
    path = tmp_path / "c.safetensors"
    save_checkpoint(path, "test", Outer("x", Inner(32)), {"net": torch.nn.Linear(2, 2)})
    with safe_open(str(path), framework="pt") as f:
        meta, tensors = f.metadata(), {k: f.get_tensor(k) for k in f.keys()}
    config = json.loads(meta["config"]) | {"from_a_later_version": 1}  # the whole config no longer reads
    save_file(tensors, str(path), metadata=meta | {"config": json.dumps(config)})
    with pytest.raises(CheckpointError, match="from_a_later_version"):
        read_checkpoint(path, "test", Outer)
    inner, states, _ = read_checkpoint(path, "test", Inner, section="inner")
    assert inner == Inner(32) and set(states["net"]) == {"weight", "bias"}
    assert read_checkpoint(path, "test", Inner, section="absent")[0] is None


def test_half_storage_halves_the_file_and_loads_back_into_float32(tmp_path):
    from axispose_core.checkpoint import load_state

    net = torch.nn.Sequential(torch.nn.Linear(64, 64), torch.nn.BatchNorm1d(64))
    save_checkpoint(tmp_path / "full.safetensors", "test", Outer("x"), {"net": net})
    save_checkpoint(tmp_path / "half.safetensors", "test", Outer("x"), {"net": net}, half=True)
    assert (tmp_path / "half.safetensors").stat().st_size < 0.6 * (tmp_path / "full.safetensors").stat().st_size
    _, states, _ = read_checkpoint(tmp_path / "half.safetensors", "test", Outer)
    assert states["net"]["0.weight"].dtype == torch.float16 and states["net"]["1.num_batches_tracked"].dtype == torch.int64
    again = torch.nn.Sequential(torch.nn.Linear(64, 64), torch.nn.BatchNorm1d(64))
    load_state(again, states["net"], "half")
    assert again[0].weight.dtype == torch.float32
    torch.testing.assert_close(again[0].weight, net[0].weight, atol=1e-3, rtol=1e-3)


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
