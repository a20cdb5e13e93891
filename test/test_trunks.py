"""Trunks: the registry's stages and widths, the normalisation each owns, EfficientNet-Lite0's ImageNet weights
(proved by classifying photographs), legacy weight names, freezing and learning-rate groups in training, and style
mixing between stages."""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
import pytest
import skimage.data
import torch
import torch.nn.functional as F
from conftest import TINY_ENCODER
from torch import nn

from axispose_core.agm.denoiser import CropEncoder, DenoiserConfig, EncoderConfig
from axispose_core.agm.model import AGMConfig, AxisGenerator
from axispose_core.agm.sampler import sample
from axispose_core.checkpoint import load_state
from axispose_core.config import config_from_dict
from axispose_core.localiser.model import Localiser, LocaliserConfig
from axispose_core.train.loop import OptimConfig, RunOptions, TrainJob, fit, param_groups, start_pretrained
from axispose_core.trunks import TRUNKS, EfficientNetLiteConfig, ResidualBNConfig, ResidualGNConfig, build_trunk
from axispose_core.trunks.efficientnet_lite import EfficientNetLiteClassifier, SamePad, imagenet_state, key_map, weights_file
from axispose_core.trunks.style_mix import StyleMix, StyleMixConfig

LITE = EfficientNetLiteConfig(weights="none")


def _images(n: int, size: int) -> torch.Tensor:
    return torch.randint(0, 256, (n, 3, size, size), dtype=torch.uint8, generator=torch.Generator().manual_seed(0))


@pytest.mark.parametrize("config", [ResidualGNConfig(), ResidualBNConfig(), LITE, EfficientNetLiteConfig(stages=5, weights="none")])
def test_every_trunk_gives_its_widths_at_halving_strides(config):
    trunk = build_trunk(config).eval()
    assert type(trunk) is TRUNKS[config.kind]
    with torch.no_grad():
        feats = trunk(trunk.normalise(_images(2, 64)))
    assert [f.shape for f in feats] == [(2, w, 64 // 2 ** (i + 1), 64 // 2 ** (i + 1)) for i, w in enumerate(trunk.widths)]


def test_a_trunk_takes_uint8_images_and_normalises_them_as_its_weights_expect():
    for config in (ResidualGNConfig(), ResidualBNConfig(), LITE):
        trunk = build_trunk(config)
        with pytest.raises(TypeError, match="uint8"):
            trunk.normalise(torch.zeros(1, 3, 8, 8))
        x = trunk.normalise(torch.tensor([0, 255], dtype=torch.uint8).view(1, 1, 1, 2).expand(1, 3, 1, 2))
        torch.testing.assert_close(x[0, :, 0], torch.tensor([[-1.0, 1.0]] * 3))  # all three: [-1, 1] (Lite: TF's (x-127.5)/127.5)


def test_same_padding_is_tensorflows():
    for size, k, s, pads in ((8, 3, 2, (0, 1)), (8, 5, 2, (1, 2)), (7, 3, 2, (1, 1)), (9, 5, 1, (2, 2)), (6, 1, 2, (0, 0))):
        x = torch.ones(1, 1, size, size)
        padded = SamePad(k, s)(x)
        assert padded.shape[-1] == size + sum(pads)
        assert padded[0, 0, pads[0], pads[0]] == 1 and (pads[0] == 0 or padded[0, 0, 0, 0] == 0)
        assert F.conv2d(padded, torch.ones(1, 1, k, k), stride=s).shape[-1] == -(-size // s)


def test_efficientnet_lite0_classifies_photographs_with_its_imagenet_weights():
    """The key map and the TF padding are right where the classifier names what the photographs show, with the
    confidence the original network gives them (lukemelas' implementation: 0.78 and 0.91)."""
    source = torch.load(weights_file(), map_location="cpu", weights_only=True)
    model = EfficientNetLiteClassifier()
    mapped = key_map()
    assert set(mapped) == set(source) and len(set(mapped.values())) == len(mapped)
    assert {k if not k.startswith("stages.") else f"trunk.{k}" for k in mapped.values()} == set(model.state_dict())
    model.load_imagenet()
    model.eval()
    photos = [cv2.resize(getattr(skimage.data, n)()[..., :3], (224, 224), interpolation=cv2.INTER_AREA) for n in ("chelsea", "coffee")]
    with torch.no_grad():
        p = model(torch.from_numpy(np.stack(photos)).permute(0, 3, 1, 2)).softmax(dim=1)
    assert p.argmax(dim=1).tolist() == [285, 967]  # Egyptian cat, espresso
    assert p[0, 285] > 0.7 and p[1, 967] > 0.85
    trunk = build_trunk(EfficientNetLiteConfig())
    trunk.load_pretrained()
    state = imagenet_state()
    assert all(torch.equal(v, state[k]) for k, v in trunk.state_dict().items())


def test_weights_saved_before_the_trunks_load_under_their_new_names():
    encoder = CropEncoder(TINY_ENCODER, 64)
    legacy = {}
    for key, value in encoder.state_dict().items():
        if key.startswith("trunk.stages."):
            stage, pos, rest = key[len("trunk.stages.") :].split(".", 2)
            key = (f"stem.{rest}" if pos == "0" else f"stages.0.{int(pos) - 1}.{rest}") if stage == "0" else (
                f"down.{stage}.{rest}" if pos == "0" else f"stages.{stage}.{int(pos) - 1}.{rest}")  # fmt: skip
        legacy[key] = value.clone() + 1
    fresh = CropEncoder(TINY_ENCODER, 64)
    load_state(fresh, legacy, "legacy encoder")
    assert all(torch.equal(v, encoder.state_dict()[k] + 1) for k, v in fresh.state_dict().items())
    old = {"widths": [8, 8, 8, 8], "blocks": [1, 1, 1, 1], "embed": 8, "context": 16, "dense": 8, "groups": 4}
    assert config_from_dict(EncoderConfig, old) == TINY_ENCODER

    config = LocaliserConfig(obj_ids=(1,), input_size=(64, 64), trunk=ResidualBNConfig(widths=(8, 8, 8, 8, 8)))
    localiser = Localiser(config)
    names = {"0": "stem", "1": "s4", "2": "s8", "3": "s16", "4": "s32"}
    legacy = {}
    for key, value in localiser.state_dict().items():
        if key.startswith("trunk.stages."):
            stage, rest = key[len("trunk.stages.") :].split(".", 1)
            key = f"stem.{rest.split('.', 1)[1]}" if stage == "0" else f"{names[stage]}.{rest}"
        legacy[key] = value.clone()
    fresh = Localiser(config)
    load_state(fresh, legacy, "legacy localiser")
    assert all(torch.equal(v, localiser.state_dict()[k]) for k, v in fresh.state_dict().items())
    assert config_from_dict(LocaliserConfig, {"obj_ids": [1], "input_size": [64, 64], "channels": [8, 8, 8, 8, 8]}) == config


def test_the_agm_and_the_localiser_run_on_a_pretrained_trunk():
    encoder = EncoderConfig(trunk=LITE, embed=8, context=16, dense=8, groups=4)
    agm = AxisGenerator(AGMConfig(denoiser=DenoiserConfig(channels=8, multipliers=(1, 2), groups=4, encoder=encoder))).eval()
    crops = _images(2, 64)
    enc = agm.encode(crops, torch.tensor([0, 1]))
    assert [m.shape[1] for m in enc.maps] == [8, 24, 40, 112] and enc.points.shape == (2, 3, 32, 32)
    assert sample(agm, enc, 2, generator=torch.Generator().manual_seed(0)).shape == (2, 3, 64, 64)
    config = LocaliserConfig(obj_ids=(1, 5), input_size=(160, 128), trunk=EfficientNetLiteConfig(stages=5, weights="none"), neck=32)
    localiser = Localiser(config).eval()
    frame = _images(1, 128).expand(1, 3, 128, 128)
    frame = torch.cat([frame, frame[..., :32]], dim=-1)
    with torch.no_grad():
        heat, size, offset = localiser(frame)
        fused = localiser.fused()(frame.contiguous(memory_format=torch.channels_last))
    assert heat.shape == (1, 2, 16, 20) and size.shape == offset.shape == (1, 2, 16, 20)
    for a, b in zip((heat, size, offset), fused, strict=True):  # BatchNorm folds into the trunk's convolutions too
        torch.testing.assert_close(a, b, atol=1e-4, rtol=1e-4)


class _Net(nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.trunk = build_trunk(EfficientNetLiteConfig(stages=3))
        self.head = nn.Conv2d(40, 1, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.head(self.trunk(self.trunk.normalise(x))[-1])


@dataclass(frozen=True)
class _Config:
    optim: OptimConfig = field(default_factory=lambda: OptimConfig(steps=3, batch=2, lr=1e-2, warmup=1, trunk_lr=0.1, freeze_trunk=2))


def _train_three_steps(net: _Net, cfg: _Config, tmp_path) -> None:
    """`fit` on one batch of two images, from ImageNet weights, the squared output as the loss."""
    start_pretrained(net)
    images = _images(2, 32)

    def batches(step: int):
        while True:
            yield {"image": images}

    fit(TrainJob(cfg, net, batches, lambda model, batch, _: (model(batch["image"]) ** 2).mean(), tmp_path / "net.safetensors",
                 lambda *a: None), RunOptions(progress=False))  # fmt: skip


def test_a_pretrained_trunk_starts_from_imagenet_with_its_first_stages_frozen_and_the_rest_slowed(tmp_path):
    torch.manual_seed(0)
    net, cfg = _Net(), _Config()
    _train_three_steps(net, cfg, tmp_path)
    state = imagenet_state()
    after = net.trunk.state_dict()
    frozen = [k for k in after if k.startswith(("stages.0.", "stages.1."))]
    assert frozen and all(torch.equal(after[k], state[k]) for k in frozen)  # weights and BatchNorm statistics
    assert any(not torch.equal(after[k], state[k]) for k in after if k.startswith("stages.2.") and "running" not in k)
    groups = param_groups(net, cfg.optim)
    assert [g["lr"] for g in groups] == [1e-2, 1e-3]
    assert {id(p) for p in groups[1]["params"]} == {id(p) for p in net.trunk.stages[2].parameters()}
    assert not any(p.requires_grad for p in net.trunk.stages[:2].parameters())
    net.train()
    assert not net.trunk.stages[0].training and net.trunk.stages[2].training


def test_style_mixing_keeps_each_samples_content_and_gives_it_a_mix_of_two_styles():
    torch.manual_seed(0)
    x = (torch.randn(6, 4, 5, 5) * (0.5 + 3 * torch.rand(6, 4, 1, 1)) + torch.randn(6, 4, 1, 1)).double()
    mix = StyleMix(StyleMixConfig(prob=1.0, alpha=0.3))
    assert torch.equal(mix.eval()(x), x)  # the identity outside training
    y = mix.train()(x)

    def stats(t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return t.mean((2, 3)), (t.var((2, 3)) + 1e-6).sqrt()

    (mu, sigma), (mu_y, sigma_y) = stats(x), stats(y)
    assert not torch.allclose(mu_y, mu, atol=1e-3)
    standard = lambda t, m, s: (t - m[..., None, None]) / s[..., None, None]  # noqa: E731
    torch.testing.assert_close(standard(y, mu_y, sigma_y), standard(x, mu, sigma), atol=1e-4, rtol=1e-4)
    # each sample's new statistics lie between its own and one other sample's, with one weight for mean and spread
    for i in range(6):
        fits = []
        for j in range(6):
            w = ((mu_y[i] - mu[j]) / (mu[i] - mu[j])).median() if j != i else torch.tensor(1.0)
            fits.append(torch.allclose(mu_y[i], w * mu[i] + (1 - w) * mu[j], atol=1e-4)
                        and torch.allclose(sigma_y[i], w * sigma[i] + (1 - w) * sigma[j], atol=1e-4) and 0 <= w <= 1)  # fmt: skip
        assert any(fits), i
    assert torch.equal(StyleMix(StyleMixConfig(prob=0.0)).train()(x), x)


def test_style_mixing_is_seeded_carries_no_weights_and_goes_only_between_stages():
    trunk = build_trunk(LITE)
    plain = set(trunk.state_dict())
    trunk.mix_styles(StyleMixConfig(prob=1.0, after=(1, 2)))
    assert set(trunk.state_dict()) == plain
    images = trunk.normalise(_images(4, 64))
    runs = []
    for _ in range(2):
        torch.manual_seed(3)
        runs.append(trunk.train()(images))
    assert all(torch.equal(a, b) for a, b in zip(runs[0], runs[1], strict=True))
    with torch.no_grad():
        mixed = trunk(images)
        trunk.mix_styles(StyleMixConfig(prob=0.0))
        unmixed = trunk(images)
    assert torch.equal(mixed[0], unmixed[0]) and not torch.equal(mixed[1], unmixed[1])
    with pytest.raises(ValueError, match="between stages"):
        trunk.mix_styles(StyleMixConfig(prob=1.0, after=(3,)))
    with pytest.raises(ValueError, match="probability"):
        StyleMix(StyleMixConfig(prob=1.5))


def test_a_trunk_may_keep_every_stages_batchnorm_statistics_while_its_later_stages_learn(tmp_path):
    torch.manual_seed(0)
    net = _Net()
    cfg = _Config(OptimConfig(steps=3, batch=2, lr=1e-2, warmup=1, freeze_trunk=1, freeze_trunk_batchnorm=True))
    _train_three_steps(net, cfg, tmp_path)
    state, after = imagenet_state(), net.trunk.state_dict()
    statistics = [k for k in after if k.startswith(("stages.1.", "stages.2.")) and "running" in k]
    weights = [k for k in after if k.startswith(("stages.1.", "stages.2.")) and "running" not in k and "num_batches" not in k]
    assert statistics and all(torch.equal(after[k], state[k]) for k in statistics)
    assert any(not torch.equal(after[k], state[k]) for k in weights)
    net.train()
    assert net.trunk.stages[2].training and not any(m.training for m in net.trunk.modules() if isinstance(m, nn.BatchNorm2d))
