"""AGM: scheduler maths, sampler determinism, guidance gradient, training behaviour, checkpoint round trip."""

import json
import math
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import TINY_AGM
from safetensors import safe_open
from safetensors.torch import load_file, save_file

from axispose_core.agm.guidance import AxisGeometry, axis_geometry, geo_loss, guided_eps, inject
from axispose_core.agm.model import AGMConfig, AxisGenerator, EncoderLossConfig, depth_from_log, fresh_trunk, grow_into, transplant
from axispose_core.agm.sampler import sample
from axispose_core.agm.scheduler import DDIMScheduler, SchedulerConfig
from axispose_core.axis_image import axis_keypoints, render_axis_keypoints
from axispose_core.camera import crop_intrinsics
from axispose_core.checkpoint import CheckpointError, save_checkpoint
from axispose_core.estimator import EstimateOptions, Estimator
from axispose_core.estimator_checkpoint import EstimatorConfig
from axispose_core.estimator_stages import fuse_depth
from axispose_core.lmo import LMO_K
from axispose_core.objects import lmo_objects
from axispose_core.pose_sampling import sample_patch
from axispose_core.tbm.reader import SHIPPED_READER, load_reader
from axispose_core.train.losses import AGMObjective, log_depth_target
from axispose_core.trunks import EfficientNetLiteConfig

TINY = TINY_AGM.denoiser


def test_schedule_and_timesteps_are_validated():
    s = DDIMScheduler()
    with pytest.raises(ValueError, match="num_inference_steps"):
        s.set_timesteps(0)
    with pytest.raises(ValueError, match="num_inference_steps"):
        s.set_timesteps(1001)
    with pytest.raises(RuntimeError, match="set_timesteps"):
        DDIMScheduler().step(torch.zeros(1, 3, 4, 4), 999, torch.zeros(1, 3, 4, 4))
    s.set_timesteps(10)
    with pytest.raises(ValueError, match="eta"):
        s.step(torch.zeros(1, 3, 4, 4), int(s.timesteps[0]), torch.zeros(1, 3, 4, 4), eta=1.5)
    with pytest.raises(ValueError, match="prediction_type"):
        DDIMScheduler(SchedulerConfig(prediction_type="x"))
    for n in (1, 2, 4, 50, 1000):
        s.set_timesteps(n)
        assert len(s.timesteps) == n and int(s.timesteps[0]) == 999 and int(s.timesteps[-1]) >= 0
        assert s.previous_timestep(int(s.timesteps[-1])) < 0
    s.set_timesteps(4)  # trailing spacing, as the docstring says
    assert s.timesteps.tolist() == [999, 749, 499, 249]
    s.set_timesteps(1)
    assert s.timesteps.tolist() == [999]


@pytest.mark.parametrize("eta", [0.0, 0.7])
def test_step_matches_the_ddim_closed_form(eta):
    s = DDIMScheduler(SchedulerConfig(clip_sample=False))
    s.set_timesteps(10)
    g = torch.Generator().manual_seed(0)
    x = torch.randn(2, 3, 8, 8, generator=g, dtype=torch.float64)
    eps = torch.randn(2, 3, 8, 8, generator=g, dtype=torch.float64)
    t, prev = int(s.timesteps[3]), int(s.timesteps[4])
    a_t, a_p = s.alphas_cumprod[t], s.alphas_cumprod[prev]
    x0 = (x - (1 - a_t).sqrt() * eps) / a_t.sqrt()
    sigma = eta * ((1 - a_p) / (1 - a_t) * (1 - a_t / a_p)).sqrt()
    noise = torch.randn(x.shape, generator=torch.Generator().manual_seed(5), dtype=torch.float64)
    expected = a_p.sqrt() * x0 + (1 - a_p - sigma**2).sqrt() * eps + sigma * noise
    out = s.step(eps, t, x, eta=eta, generator=torch.Generator().manual_seed(5))
    torch.testing.assert_close(out.prev_sample, expected)
    torch.testing.assert_close(out.pred_original_sample, x0)


def test_ten_step_loop_matches_an_independent_implementation():
    """The whole DDIM loop with a dummy model (ε = 0.1 x) against a NumPy re-derivation."""
    s = DDIMScheduler(SchedulerConfig(clip_sample=False))
    s.set_timesteps(10)
    x = torch.randn(1, 3, 4, 4, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    ref = x.numpy().copy()
    abar = s.alphas_cumprod.numpy()
    for t in s.timesteps.tolist():
        x = s.step(0.1 * x, t, x).prev_sample
        prev = t - 100
        e = 0.1 * ref
        x0 = (ref - np.sqrt(1 - abar[t]) * e) / np.sqrt(abar[t])
        a_p = abar[prev] if prev >= 0 else 1.0
        ref = np.sqrt(a_p) * x0 + np.sqrt(1 - a_p) * e
    np.testing.assert_allclose(x.numpy(), ref, rtol=1e-10)


@pytest.mark.parametrize("kind", ["epsilon", "sample", "v_prediction"])
def test_parametrisations_convert_both_ways(kind):
    s = DDIMScheduler(SchedulerConfig(prediction_type=kind, clip_sample=False))
    g = torch.Generator().manual_seed(2)
    x0 = torch.rand(2, 3, 4, 4, generator=g, dtype=torch.float64) * 2 - 1
    noise = torch.randn(2, 3, 4, 4, generator=g, dtype=torch.float64)
    t = torch.tensor([10, 700])
    x_t = s.add_noise(x0, noise, t)
    eps, x0_hat = s.to_eps_x0(s.target(x0, noise, t), t, x_t)
    torch.testing.assert_close(eps, noise)
    torch.testing.assert_close(x0_hat, x0)
    torch.testing.assert_close(s.from_eps(noise, t, x_t), s.target(x0, noise, t))


def test_cosine_schedule_is_monotone():
    a = DDIMScheduler(SchedulerConfig(beta_schedule="cosine")).alphas_cumprod
    assert torch.all(a[1:] < a[:-1]) and a[0] < 1 and a[-1] > 0


def _gt_axis_image(rng, size=64):
    ps = sample_patch(rng, 0.05, size)
    kp = axis_keypoints(ps.K_patch, ps.R, ps.t, np.full(3, 0.05))
    return torch.from_numpy(render_axis_keypoints(kp, size) * 2 - 1).permute(2, 0, 1)[None].double(), kp


def test_operator_h_reads_origin_and_directions(rng):
    for _ in range(10):
        img, kp = _gt_axis_image(rng)
        geo = axis_geometry(img)
        origin_px = (geo.origin[0].numpy() + 1) / 2 * 64 - 0.5
        assert np.linalg.norm(origin_px - kp[0]) < 1.5
        for i in range(3):
            leg = kp[i + 1] - kp[0]
            if np.linalg.norm(leg) > 8:
                assert geo.directions[0, i].numpy() @ (leg / np.linalg.norm(leg)) > 0.95


def exact_gradient(x_t: torch.Tensor, x0_of_xt, target: AxisGeometry) -> torch.Tensor:
    """∇_{x_t} L_geo(x̂0(x_t)) through an arbitrary differentiable map x̂0(x_t), by autograd."""
    xt = x_t.detach().requires_grad_(True)
    (grad,) = torch.autograd.grad(geo_loss(axis_geometry(x0_of_xt(xt)), target).sum(), xt)
    return grad


def test_guidance_gradient_matches_finite_differences(rng):
    img, _ = _gt_axis_image(rng)
    target = axis_geometry(img)
    g = torch.Generator().manual_seed(3)
    eps = torch.randn(img.shape, generator=g, dtype=torch.float64)
    abar = torch.tensor(0.6, dtype=torch.float64)
    x_t = abar.sqrt() * (img * 0.7) + (1 - abar).sqrt() * eps

    def x0_of(x):  # the toy operator: x̂0 at fixed ε
        return (x - (1 - abar).sqrt() * eps) / abar.sqrt()

    grad = exact_gradient(x_t, x0_of, target)
    for _ in range(6):
        idx = tuple(int(v) for v in (0, rng.integers(3), rng.integers(64), rng.integers(64)))
        h = 1e-6
        plus, minus = x_t.clone(), x_t.clone()
        plus[idx] += h
        minus[idx] -= h
        fd = (geo_loss(axis_geometry(x0_of(plus)), target) - geo_loss(axis_geometry(x0_of(minus)), target)).item() / (2 * h)
        assert grad[idx].item() == pytest.approx(fd, rel=1e-4, abs=1e-9)
    # The injection is the paper's formula with that gradient.
    eps_g = guided_eps(eps, x_t, abar, target, sigma=0.5, create_graph=False)
    x0 = x0_of(x_t)
    assert x0.abs().max() <= 1  # inside the clamp, so guided_eps and exact_gradient see the same x̂0
    torch.testing.assert_close(eps_g, inject(eps, grad, abar, 0.5))
    torch.testing.assert_close(eps_g, eps + 4.0 * (1 - abar).sqrt() * grad)


def test_sampler_is_deterministic_under_a_seed():
    torch.manual_seed(0)
    agm = AxisGenerator(AGMConfig(denoiser=TINY))
    for p in agm.parameters():  # a non-trivial network: zero-initialised output layers would hide differences
        p.data.normal_(0, 0.05)
    crops = torch.randint(0, 256, (2, 3, 64, 64), dtype=torch.uint8)
    enc = agm.encode(crops, torch.tensor([0, 1]))
    a = sample(agm, enc, 4, generator=torch.Generator().manual_seed(7))
    b = sample(agm, enc, 4, generator=torch.Generator().manual_seed(7))
    c = sample(agm, enc, 4, generator=torch.Generator().manual_seed(8))
    assert a.shape == (2, 3, 64, 64) and torch.equal(a, b) and not torch.equal(a, c)
    # the object conditions the generation: the same crop told another object draws another image
    other = sample(agm, agm.encode(crops, torch.tensor([2, 1])), 4, generator=torch.Generator().manual_seed(7))
    assert not torch.equal(other[0], a[0]) and torch.equal(other[1], a[1])
    # hypotheses share the crop's encoding
    assert torch.equal(enc.repeat(3).context[3:6], enc.context[1:2].expand(3, -1))
    assert a.min() >= -1 and a.max() <= 1
    # a row started from the prior's mode (x_T = 0) is the same under every seed; the others still follow it
    z = torch.tensor([0.0, 1.0])
    m7 = sample(agm, enc, 4, generator=torch.Generator().manual_seed(7), noise_scale=z)
    m8 = sample(agm, enc, 4, generator=torch.Generator().manual_seed(8), noise_scale=z)
    assert torch.equal(m7[0], m8[0]) and not torch.equal(m7[0], a[0])
    assert torch.equal(m7[1], a[1]) and not torch.equal(m8[1], m7[1])


@pytest.mark.slow
@pytest.mark.parametrize("guided", [False, True])
def test_loss_falls_on_a_tiny_set(guided, rng):
    torch.manual_seed(0)
    targets = torch.cat([_gt_axis_image(rng)[0] for _ in range(4)]).float()
    crops = ((targets + 1) * 127.5).round().to(torch.uint8)  # a crop that shows its answer: only whether learning happens is tested
    agm = AxisGenerator(AGMConfig(denoiser=TINY, train_guidance=guided))
    objective = AGMObjective(agm)
    opt = torch.optim.Adam(agm.parameters(), lr=2e-3)
    losses = []
    batch = {"crop": crops, "axes": targets, "object": torch.arange(4)}
    for i in range(120):
        loss = objective(batch, torch.Generator().manual_seed(i % 8))
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert np.isfinite(losses).all()
    assert np.mean(losses[-15:]) < 0.5 * np.mean(losses[:15])


def test_estimator_checkpoint_round_trip(tmp_path):
    reader = load_reader(SHIPPED_READER)
    cfg = EstimatorConfig(
        agm=AGMConfig(denoiser=TINY), reader=reader.config, objects=tuple(lmo_objects()[:2]), ddim_steps=2, head_offaxis=(0.01, -0.2)
    )
    est = Estimator(cfg, AxisGenerator(cfg.agm), reader)
    est.save(tmp_path / "est.safetensors")
    again = Estimator.load(tmp_path / "est.safetensors")
    assert again.config == cfg
    image = (np.random.default_rng(0).uniform(0, 255, (480, 640, 3))).astype(np.uint8)
    K = np.array([[572.4, 0, 325.3], [0, 573.6, 242.0], [0, 0, 1]])
    a = est.estimate(image, K, [(1, (300, 200, 60, 70))])
    b = again.estimate(image, K, [(1, (300, 200, 60, 70))])
    np.testing.assert_array_equal(a[0].axis_image, b[0].axis_image)
    assert a[0].ok == b[0].ok and (a[0].ok or a[0].reason)
    with pytest.raises(ValueError, match="not in this checkpoint"):
        est.estimate(image, K, [(99, (0, 0, 10, 10))])
    save_checkpoint(tmp_path / "reader.safetensors", "tbm_reader", reader.config, {"reader": reader})
    with pytest.raises(CheckpointError, match="expected 'estimator'"):
        Estimator.load(tmp_path / "reader.safetensors")


def test_bfloat16_runs_the_agm_in_bfloat16_but_keeps_depth_and_poses_in_float32():
    reader = load_reader(SHIPPED_READER)
    cfg = EstimatorConfig(agm=AGMConfig(denoiser=TINY), reader=reader.config, objects=tuple(lmo_objects()[:2]), ddim_steps=2)
    est = Estimator(cfg, AxisGenerator(cfg.agm), reader)
    assert est.set_precision("float32") == "float32" and not est.bf16
    assert est.set_precision("bfloat16") == "bfloat16" and est.bf16
    with pytest.raises(ValueError, match="precision must be one of"):
        est.set_precision("half")
    with torch.autocast("cpu", dtype=torch.bfloat16):
        enc = est.agm.encode(torch.zeros(2, 3, 64, 64, dtype=torch.uint8), torch.tensor([0, 1]))
    assert enc.context.dtype == torch.bfloat16 and enc.log_depth.dtype == torch.float32  # bf16 would cost ~0.5 % of depth
    image = (np.random.default_rng(0).uniform(0, 255, (480, 640, 3))).astype(np.uint8)
    K = np.array([[572.4, 0, 325.3], [0, 573.6, 242.0], [0, 0, 1]])
    (pose,) = est.estimate(image, K, [(1, (300, 200, 60, 70))], EstimateOptions(hypotheses=2))
    assert pose.axis_image.dtype == np.float32 and np.isfinite(pose.head_depth)


def test_guided_estimates_give_poses_with_the_encoders_depth():
    """Run-time guidance samples outside inference mode, so the encoder's outputs carry gradients there."""
    reader = load_reader(SHIPPED_READER)
    cfg = EstimatorConfig(agm=AGMConfig(denoiser=TINY), reader=reader.config, objects=tuple(lmo_objects()[:2]), ddim_steps=2)
    est = Estimator(cfg, AxisGenerator(cfg.agm), reader)
    image = (np.random.default_rng(0).uniform(0, 255, (480, 640, 3))).astype(np.uint8)
    K = np.array([[572.4, 0, 325.3], [0, 573.6, 242.0], [0, 0, 1]])
    poses = est.estimate(image, K, [(1, (300, 200, 60, 70)), (5, (100, 100, 80, 80))], EstimateOptions(guidance_scale=1.0, hypotheses=2))
    assert len(poses) == 2 and all(np.isfinite(p.head_depth) for p in poses)


def _saved_with_config_edited(path: Path, edit: Callable[[dict], None]) -> Path:
    """A tiny estimator saved at `path`, its config metadata then changed in place by `edit`."""
    reader = load_reader(SHIPPED_READER)
    cfg = EstimatorConfig(agm=AGMConfig(denoiser=TINY), reader=reader.config, objects=tuple(lmo_objects()[:1]))
    Estimator(cfg, AxisGenerator(cfg.agm), reader).save(path)
    meta = dict(safe_open(str(path), framework="pt").metadata())
    config = json.loads(meta["config"])
    edit(config)
    save_file(load_file(str(path)), str(path), metadata=meta | {"config": json.dumps(config)})
    return path


def test_a_checkpoint_of_the_earlier_agm_is_refused_in_one_line(tmp_path):
    """An estimator saved before the AGM's version 2 (no `version`, the old denoiser fields) says what it is."""

    def v1(config: dict) -> None:
        del config["agm"]["version"]
        config["agm"]["denoiser"] = {"size": 64, "channels": 32, "multipliers": [1, 2, 4], "blocks_per_level": 1, "conditioning": "encoder"}

    with pytest.raises(CheckpointError, match=r"made by an earlier AxisPose \(AGM version 1") as err:
        Estimator.load(_saved_with_config_edited(tmp_path / "old.safetensors", v1))
    assert "\n" not in str(err.value)


def test_a_checkpoint_whose_config_refuses_its_values_is_refused_in_one_line(tmp_path):
    def negative(config: dict) -> None:
        config["dense_fusion"]["covariance_scale"] = [-1.0, 1.0]

    with pytest.raises(CheckpointError, match="covariance_scale must be two positive factors") as err:
        Estimator.load(_saved_with_config_edited(tmp_path / "bad.safetensors", negative))
    assert "\n" not in str(err.value)


def test_a_checkpoint_with_an_unusable_off_axis_correction_is_refused_in_one_line(tmp_path):
    def one_number(config: dict) -> None:
        config["head_offaxis"] = [0.01]

    with pytest.raises(CheckpointError, match="head_offaxis must be two finite numbers") as err:
        Estimator.load(_saved_with_config_edited(tmp_path / "bad.safetensors", one_number))
    assert "\n" not in str(err.value)


def test_the_estimator_takes_the_off_axis_bias_off_the_encoders_depth():
    reader = load_reader(SHIPPED_READER)
    base = EstimatorConfig(agm=AGMConfig(denoiser=TINY), reader=reader.config, objects=tuple(lmo_objects()[:1]))
    plain = Estimator(base, AxisGenerator(base.agm), reader)
    c0, c1 = 0.0138, -0.2397
    corrected = Estimator(replace(base, head_offaxis=(c0, c1)), AxisGenerator(base.agm), reader)
    on_axis = crop_intrinsics(LMO_K, (LMO_K[0, 2], LMO_K[1, 2]), 100.0, 64)
    off = crop_intrinsics(LMO_K, (LMO_K[0, 2] + LMO_K[0, 0] * math.tan(math.radians(25)), LMO_K[1, 2]), 100.0, 64)
    for K in (on_axis, off):
        assert plain.head_depth(0.3, K, 0.05) == pytest.approx(depth_from_log(0.3, K, 0.05, 64))  # (0, 0): as the head says
    assert corrected.head_depth(0.3, on_axis, 0.05) == pytest.approx(plain.head_depth(0.3, on_axis, 0.05) * math.exp(-c0))
    x = 1 / math.cos(math.radians(25)) - 1
    assert corrected.head_depth(0.3, off, 0.05) == pytest.approx(plain.head_depth(0.3, off, 0.05) * math.exp(-c0 - c1 * x))
    assert corrected.head_depth(0.3, off, 0.10) == pytest.approx(2 * corrected.head_depth(0.3, off, 0.05))  # linear in λ_O


def test_depth_target_round_trip_and_fusion_scale_with_the_object_size():
    K = torch.tensor([[[300.0, 0, 32], [0, 310.0, 30], [0, 0, 1]]], dtype=torch.float64)
    t = torch.tensor([[0.05, -0.02, 0.8]], dtype=torch.float64)
    log_depth = log_depth_target(K, t, torch.tensor([0.05], dtype=torch.float64), 64)
    assert depth_from_log(float(log_depth[0]), K[0].numpy(), 0.05, 64) == pytest.approx(0.8)
    assert depth_from_log(float(log_depth[0]), K[0].numpy(), 0.10, 64) == pytest.approx(1.6)  # linear in λ_O
    tbm = np.array([0.1, 0.0, 1.0])
    head = math.log(0.81 * 64 / (305.0 * 0.05))  # the encoder says 0.81 m, the TBM 1.0 m
    fused = fuse_depth(tbm, depth_from_log(head, K[0].numpy(), 0.05, 64), 0.5)
    assert fused[2] == pytest.approx(0.9) and np.allclose(fused / fused[2], tbm / tbm[2])  # geometric mean, same ray
    np.testing.assert_allclose(fuse_depth(2 * tbm, depth_from_log(head, K[0].numpy(), 0.10, 64), 0.5), 2 * fused)  # λ_O x2: t x2


def test_geo_loss_is_zero_on_target(rng):
    img, _ = _gt_axis_image(rng)
    g = axis_geometry(img)
    assert geo_loss(g, AxisGeometry(g.origin.clone(), g.directions.clone())).item() == 0.0


def test_a_grown_encoder_starts_as_the_network_it_grew_from():
    torch.manual_seed(0)
    small = AxisGenerator(AGMConfig(denoiser=TINY))
    for p in small.parameters():  # a non-trivial network: zero-initialised output layers would hide differences
        p.data.normal_(0, 0.05)
    trunk = TINY.encoder.trunk
    blocks = trunk.blocks
    deeper = replace(TINY, encoder=replace(TINY.encoder, trunk=replace(trunk, blocks=tuple(b + 1 for b in blocks))))
    big = AxisGenerator(AGMConfig(denoiser=deeper))
    added = grow_into(big, small)
    assert len(added) == len(blocks)
    crops, objects = torch.randint(0, 256, (2, 3, 64, 64), dtype=torch.uint8), torch.tensor([0, 1])
    a, b = small.encode(crops, objects), big.encode(crops, objects)
    torch.testing.assert_close(a.context, b.context)
    torch.testing.assert_close(a.points, b.points)
    x_t, t = torch.rand(2, 3, 64, 64) * 2 - 1, torch.tensor([10, 900])
    torch.testing.assert_close(small.denoiser(x_t, t, a), big.denoiser(x_t, t, b))
    # the same network is a plain copy, also under other training settings (loss weights are not the network)
    same = AxisGenerator(AGMConfig(denoiser=TINY, encoder_loss=EncoderLossConfig(depth_weight=2.0), train_guidance=False))
    assert grow_into(same, small) == []
    assert all(torch.equal(v, small.state_dict()[k]) for k, v in same.state_dict().items())
    # more objects: the known rows are kept, a new object's starts as their mean
    wider_table = AxisGenerator(AGMConfig(denoiser=replace(TINY, encoder=replace(TINY.encoder, objects=TINY.encoder.objects + 2))))
    assert grow_into(wider_table, small) == []
    rows, old = wider_table.denoiser.encoder.embedding.weight, small.denoiser.encoder.embedding.weight
    torch.testing.assert_close(rows[: len(old)], old)
    torch.testing.assert_close(rows[len(old) :], old.mean(dim=0, keepdim=True).expand(2, -1))
    # only blocks may be added: another width, or fewer blocks, is refused
    wider = replace(TINY, encoder=replace(TINY.encoder, trunk=replace(trunk, widths=tuple(2 * w for w in trunk.widths))))
    fewer = replace(TINY, encoder=replace(TINY.encoder, trunk=replace(trunk, blocks=tuple(max(b - 1, 0) for b in blocks))))
    for other in (wider, fewer):
        with pytest.raises(ValueError, match="only the residual trunk's blocks per stage and the objects may grow"):
            grow_into(AxisGenerator(AGMConfig(denoiser=other)), small)


def test_a_transplant_keeps_the_new_trunk_and_takes_the_rest_that_fits():
    """Another trunk under a trained denoiser: the trunk keeps its own weights, every tensor outside it of the
    same name and shape is copied, and just the layers that read the trunk's widths start fresh."""
    torch.manual_seed(0)
    trained = AxisGenerator(AGMConfig(denoiser=TINY))
    for p in trained.parameters():
        p.data.normal_(0, 0.05)
    lite = replace(TINY, encoder=replace(TINY.encoder, trunk=EfficientNetLiteConfig(stages=4, weights="none")))
    model = AxisGenerator(AGMConfig(denoiser=lite))
    own_trunk = {k: v.clone() for k, v in model.denoiser.encoder.trunk.state_dict().items()}
    fresh = transplant(model, trained)
    assert all(torch.equal(v, own_trunk[k]) for k, v in model.denoiser.encoder.trunk.state_dict().items())
    new, old = model.state_dict(), trained.state_dict()
    outside = [k for k in new if not k.startswith("denoiser.encoder.trunk.")]
    assert set(fresh) == {k for k in outside if k not in old or old[k].shape != new[k].shape}
    assert all(torch.equal(new[k], old[k]) for k in outside if k not in fresh)
    assert any(k.startswith("denoiser.encoder.film.") for k in fresh) and "denoiser.encoder.context.1.weight" in fresh
    assert "denoiser.out.2.weight" not in fresh and "denoiser.encoder.depth.1.weight" not in fresh
    # only the trunk may differ: another denoiser width is refused
    with pytest.raises(ValueError, match="only the encoder's trunk may differ"):
        transplant(AxisGenerator(AGMConfig(denoiser=replace(lite, channels=2 * lite.channels))), trained)


def test_a_fresh_trunk_is_a_new_networks_under_the_trained_denoiser():
    """The trunk and the layers that read its widths go back to a new network's initial weights, drawn from torch's
    state (the same seed, the same weights); every other tensor keeps its trained value."""
    torch.manual_seed(0)
    trained = AxisGenerator(AGMConfig(denoiser=TINY))
    for p in trained.parameters():
        p.data.normal_(0, 0.05)
    old = {k: v.clone() for k, v in trained.state_dict().items()}
    torch.manual_seed(3)
    reset = fresh_trunk(trained)
    new = trained.state_dict()
    assert {k for k in new if k.startswith("denoiser.encoder.trunk.")} <= set(reset)
    assert any(k.startswith("denoiser.encoder.film.") for k in reset) and "denoiser.encoder.context.1.weight" in reset
    assert all(not torch.equal(new[k], old[k]) for k in reset if k.endswith(".weight"))
    assert all(torch.equal(new[k], old[k]) for k in new if k not in reset)
    assert "denoiser.out.2.weight" not in reset and "denoiser.encoder.depth.1.weight" not in reset
    again = AxisGenerator(AGMConfig(denoiser=TINY))
    again.load_state_dict(old)
    torch.manual_seed(3)
    fresh_trunk(again)
    assert all(torch.equal(v, new[k]) for k, v in again.state_dict().items())


def test_max_boxes_poses_a_frame_in_batches_of_that_many(monkeypatch):
    """A call with more boxes than `max_boxes` runs batches of at most that many, in order, each as a call with
    just its boxes would: the caller's memory and batch shapes stay bounded."""
    reader = load_reader(SHIPPED_READER)
    cfg = EstimatorConfig(agm=AGMConfig(denoiser=TINY), reader=reader.config, objects=tuple(lmo_objects()[:2]), ddim_steps=2)
    est = Estimator(cfg, AxisGenerator(cfg.agm), reader)
    image = (np.random.default_rng(0).uniform(0, 255, (480, 640, 3))).astype(np.uint8)
    K = np.array([[572.4, 0, 325.3], [0, 573.6, 242.0], [0, 0, 1]])
    boxes = [(1 + 4 * (k % 2), (60.0 + 90 * k, 150.0, 70.0, 80.0)) for k in range(5)]
    sizes, real = [], est.reader.read
    monkeypatch.setattr(est.reader, "read", lambda images: sizes.append(len(images)) or real(images))
    options = EstimateOptions(hypotheses=2, max_boxes=2)
    poses = est.estimate(image, K, boxes, options)
    assert sizes == [4, 4, 2] and [p.obj_id for p in poses] == [o for o, _ in boxes]
    alone = est.estimate(image, K, boxes[2:4], options)
    for a, b in zip(poses[2:4], alone, strict=True):
        np.testing.assert_array_equal(a.axis_image, b.axis_image)
    assert est.estimate(image, K, [], options) == []
    with pytest.raises(ValueError, match="max_boxes"):
        EstimateOptions(max_boxes=0)
