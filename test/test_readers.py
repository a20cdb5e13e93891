import dataclasses

import numpy as np
import pytest
import torch

from axispose_core.axis_image import axis_keypoints, render_axis_keypoints
from axispose_core.checkpoint import CheckpointError, save_checkpoint
from axispose_core.metrics import re
from axispose_core.pose_sampling import sample_patch
from axispose_core.tbm.backproject import backproject
from axispose_core.tbm.line_fit import fit_axis_keypoints
from axispose_core.tbm.reader import SHIPPED_READER, KeypointReader, ReaderConfig, load_reader
from axispose_core.train.reader import degrade, synth_batch


@pytest.fixture(scope="module")
def shipped() -> KeypointReader:
    return load_reader(SHIPPED_READER)


def _clean_samples(n: int, size: int, seed: int = 99):
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        lengths = np.array([1.0, rng.uniform(0.6, 1.4), rng.uniform(0.6, 1.4)]) * 0.05
        ps = sample_patch(rng, float(lengths.max()), size)
        kp = axis_keypoints(ps.K_patch, ps.R, ps.t, lengths)
        out.append((ps, lengths, kp, render_axis_keypoints(kp, size)))
    return out


def _rotation_success(read_fn, samples) -> float:
    good = 0
    for ps, lengths, _, image in samples:
        kp = read_fn(image)
        res = backproject(ps.K_patch, kp.origin, kp.endpoints, lengths, refine=True) if kp.ok else None
        good += res is not None and res.ok and re(res.R, ps.R) < 2.0
    return good / len(samples)


def test_line_fit_recovers_rotation_from_clean_images():
    samples = _clean_samples(200, 64)
    rate = _rotation_success(fit_axis_keypoints, samples)
    print(f"line fit: {100 * rate:.1f}% of poses within 2 deg")
    assert rate >= 0.95


@pytest.mark.slow
def test_network_reader_recovers_rotation_from_clean_images(shipped):
    samples = _clean_samples(200, shipped.config.size)
    rate = _rotation_success(lambda img: shipped.read(img)[0], samples)
    print(f"network reader: {100 * rate:.1f}% of poses within 2 deg")
    assert rate >= 0.95


def test_network_reader_beats_line_fit_on_degraded_images(shipped):
    rng = np.random.default_rng(5)
    gen = torch.Generator().manual_seed(5)
    images, kp = synth_batch(rng, gen, shipped.config, 64, degrade_prob=1.0)
    net = np.stack([k.array for k in shipped.read(images)])
    net_err = np.median(np.abs(net - kp.numpy()).mean(axis=(1, 2)))
    fits = [fit_axis_keypoints(img.permute(1, 2, 0).numpy()) for img in images]
    fit_err = np.median([np.abs(f.array - k).mean() if f.ok else np.inf for f, k in zip(fits, kp.numpy(), strict=True)])
    assert net_err < fit_err


def test_line_fit_refuses_unreadable_images():
    img = np.zeros((64, 64, 3), np.float32)
    img[10:20, 30, 0] = 1.0
    res = fit_axis_keypoints(img)
    assert not res.ok and "channel Y" in res.reason
    img[:] = np.nan
    assert "non-finite" in fit_axis_keypoints(img).reason
    with pytest.raises(ValueError, match="HxWx3"):
        fit_axis_keypoints(np.zeros((64, 64)))


def test_reader_rejects_wrong_size(shipped):
    with pytest.raises(ValueError, match="expects"):
        shipped.read(np.zeros((32, 32, 3), np.float32))


def test_degrade_is_seeded_and_bounded():
    cfg = ReaderConfig(size=32)
    a = synth_batch(np.random.default_rng(0), torch.Generator().manual_seed(0), cfg, 8, 1.0)[0]
    b = synth_batch(np.random.default_rng(0), torch.Generator().manual_seed(0), cfg, 8, 1.0)[0]
    assert torch.equal(a, b)
    assert a.min() >= 0 and a.max() <= 1
    clean = synth_batch(np.random.default_rng(0), torch.Generator().manual_seed(0), cfg, 8, 0.0)[0]
    assert not torch.equal(degrade(clean, torch.Generator().manual_seed(1), 1.0), clean)


@pytest.mark.slow
def test_training_fits_rendered_axis_images_and_resumes(tmp_path):
    import csv

    from axispose_core.train.loop import OptimConfig, RunOptions
    from axispose_core.train.reader import ReaderTrainConfig, train_reader
    from axispose_core.train.resume import state_path

    optim = OptimConfig(steps=120, batch=16, lr=3e-3, warmup=10, ema_decay=0.9, workers=0, save_every=1000, val_every=40)
    cfg = ReaderTrainConfig(reader=ReaderConfig(size=32, channels=16, blocks=(1, 2)), optim=optim, degrade_prob=0.0, val_samples=32)
    out = tmp_path / "reader.safetensors"
    assert train_reader(cfg, out, RunOptions(device="cpu", progress=False)) == 120
    rows = list(csv.DictReader(open(out.with_suffix(".csv"))))
    loss = [float(r["loss"]) for r in rows]
    assert np.mean(loss[-3:]) < 0.5 * np.mean(loss[:3])
    val = [float(r["val_kp_err_px"]) for r in rows if r["val_kp_err_px"]]
    assert len(val) == 3 and val[-1] < val[0]
    assert load_reader(out).config == cfg.reader
    longer = dataclasses.replace(cfg, optim=dataclasses.replace(optim, steps=130))
    assert train_reader(longer, out, RunOptions(state_path(out), "cpu", progress=False)) == 130


def test_checkpoint_round_trip_keeps_config_and_outputs(tmp_path):
    cfg = ReaderConfig(size=32, channels=16, blocks=(1, 2))
    model = KeypointReader(cfg).eval()
    path = tmp_path / "reader.safetensors"
    save_checkpoint(path, "tbm_reader", cfg, {"reader": model})
    again = load_reader(path)
    assert again.config == cfg
    x = torch.rand(2, 3, 32, 32)
    with torch.no_grad():
        assert torch.equal(model(x), again(x))


def test_bad_checkpoints_are_refused_clearly(tmp_path):
    cfg = ReaderConfig(size=32, channels=16, blocks=(1, 2))
    model = KeypointReader(cfg)
    wrong_kind = tmp_path / "kind.safetensors"
    save_checkpoint(wrong_kind, "agm", cfg, {"reader": model})
    with pytest.raises(CheckpointError, match="holds a 'agm' model"):
        load_reader(wrong_kind)
    mismatch = tmp_path / "mismatch.safetensors"
    save_checkpoint(mismatch, "tbm_reader", dataclasses.replace(cfg, channels=8), {"reader": model})
    with pytest.raises(CheckpointError, match="do not match"):
        load_reader(mismatch)
    corrupt = tmp_path / "corrupt.safetensors"
    corrupt.write_bytes(b"\x00" * 64)
    with pytest.raises(CheckpointError, match="not a readable safetensors"):
        load_reader(corrupt)
    with pytest.raises(CheckpointError, match="not found"):
        load_reader(tmp_path / "missing.safetensors")


def test_reader_config_of_an_earlier_version_loads_without_its_retired_training_keys():
    from axispose_core.config import ConfigError, config_from_dict

    old = {"size": 32, "channels": 16, "blocks": [1, 2], "steps": 3000, "batch": 32, "lr": 0.002, "degrade_prob": 0.7, "seed": 0}
    assert config_from_dict(ReaderConfig, old) == ReaderConfig(size=32, channels=16, blocks=(1, 2))
    with pytest.raises(ConfigError, match="unknown key"):
        config_from_dict(ReaderConfig, {"size": 32, "depth": 3})
