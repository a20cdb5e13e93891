"""The Axis Generation Module: encoder + denoiser + DDIM schedule, the weights and their configuration (diffusers'
model side). Sampling lives in `agm/sampler.py`, the training losses in `train/losses.py`."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
import torch
from torch import nn

from axispose_core.agm.denoiser import Denoiser, DenoiserConfig, Encoding
from axispose_core.agm.scheduler import DDIMScheduler, SchedulerConfig
from axispose_core.trunks import EfficientNetLiteConfig, ResidualGNConfig, TrunkConfig

VERSION = 2
"""The AGM's network generation: 2 is the object-conditioned encoder with dense and depth heads; checkpoints
without it were made by an earlier AxisPose, whose networks this one cannot run."""

TRUNK = "denoiser.encoder.trunk."
"""The prefix of the encoder's trunk's tensors in an AGM's state."""


def depth_from_log(log_depth: float, K: np.ndarray, scale: float, size: int) -> float:
    """The encoder's depth for one crop in metres, linear in λ_O (the inverse of `train/losses.py`'s
    `log_depth_target`: log_depth = log(z S / (f λ_O)), f the crop's mean focal length in px, S its side)."""
    return math.exp(log_depth) * 0.5 * float(K[0, 0] + K[1, 1]) * scale / size


@dataclass(frozen=True)
class EncoderLossConfig:
    """Weights of the crop encoder's auxiliary losses (`train/losses.py`'s `encoder_losses`), one section for every network built on
    the encoder (the AGM, the direct baseline), so that all learn from the same signal."""

    points_weight: float = 1.0
    """The dense surface-coordinate loss (L1 over the visible pixels), where samples have it."""
    mask_weight: float = 0.5
    """The visible-mask loss (binary cross-entropy)."""
    depth_weight: float = 1.0
    """The scale-invariant depth loss (L1 on the log)."""

    def total(self, parts: dict[str, torch.Tensor], main: str) -> torch.Tensor:
        """parts[main] + the encoder's losses the batch had, weighted."""
        total = parts[main] + parts["unused"]
        for name, w in (("points", self.points_weight), ("mask", self.mask_weight), ("depth", self.depth_weight)):
            if name in parts:
                total = total + w * parts[name]
        return total


DENOISERS: dict[str, type[nn.Module]] = {"unet": Denoiser}
"""Denoiser classes by the `kind` of their config: a new one is registered here, its config class added to the
type of AGMConfig.denoiser with its own `kind` (checkpoints name it, `config_from_dict` picks by it)."""


@dataclass(frozen=True)
class AGMConfig:
    version: int = VERSION
    denoiser: DenoiserConfig = field(default_factory=DenoiserConfig)
    scheduler: SchedulerConfig = field(default_factory=lambda: SchedulerConfig(prediction_type="sample"))
    train_guidance: bool = False
    """Inject the L_geo gradient into the noise estimate during training (the paper's method; see `losses`). Off
    by default, as the shipped model was trained (config/recipes/axispose_lmo.yaml)."""
    guidance_sigma: float = 1.0
    """σ of the measurement model g = H(x0) + n: the injection's step size is 1/σ²."""
    line_weight: float = 10.0
    """Extra loss weight on the pixels the target's axes cover (~5 % of a 64 px image): without it the loss is
    met by an all-background image, which is what an unweighted run converged to."""
    encoder_loss: EncoderLossConfig = field(default_factory=EncoderLossConfig)


class AxisGenerator(nn.Module):
    """Crop (B,3,S,S) uint8 and object index (B,) -> axis image (B,3,S,S) in [-1,1] by DDIM."""

    def __init__(self, config: AGMConfig) -> None:
        super().__init__()
        if config.version != VERSION:
            raise ValueError(f"AGM version {config.version} is not this AxisPose's ({VERSION})")
        self.config = config
        self.denoiser = DENOISERS[config.denoiser.kind](config.denoiser)
        self.scheduler = DDIMScheduler(config.scheduler)

    def encode(self, crops: torch.Tensor, objects: torch.Tensor) -> Encoding:
        return self.denoiser.encode(crops, objects)


def grows(old: TrunkConfig, new: TrunkConfig) -> bool:
    """Whether a trunk `new` holds `old`'s weights: the same, or a residual one with more blocks per stage."""
    if isinstance(old, ResidualGNConfig) and isinstance(new, ResidualGNConfig):
        more = len(new.blocks) == len(old.blocks) and all(n >= o for n, o in zip(new.blocks, old.blocks, strict=True))
        return more and replace(new, blocks=old.blocks) == old
    return new == old


def grow_into(model: AxisGenerator, start: AxisGenerator) -> list[str]:
    """Load `start`'s weights into `model`: the same network (its training settings, e.g. loss weights, may
    differ), or one whose residual trunk has more blocks per stage or whose encoder has more object rows; returns
    the names of the blocks added (none for the same network). The added blocks start as the identity (their last
    convolution zeroed), so the grown network computes what `start` did and training goes on from its weights with
    more capacity; an added object's embedding starts as the mean of the known ones'."""
    old, new = start.config, model.config
    oe, ne = old.denoiser.encoder, new.denoiser.encoder
    ot, nt = oe.trunk, ne.trunk
    nt_as_old = replace(nt, blocks=ot.blocks) if isinstance(ot, ResidualGNConfig) and isinstance(nt, ResidualGNConfig) else nt
    same = replace(new.denoiser, encoder=replace(ne, trunk=nt_as_old, objects=oe.objects))
    if same != old.denoiser or not grows(ot, nt) or ne.objects < oe.objects:
        raise ValueError(
            f"cannot grow an AGM {old.denoiser} into {new.denoiser}: only the residual trunk's blocks per stage and the objects may grow"
        )
    added = [] if nt_as_old is nt else [
        f"denoiser.encoder.trunk.stages.{s}.{b + 1}" for s, (o, n) in enumerate(zip(ot.blocks, nt.blocks, strict=True)) for b in range(o, n)
    ]  # fmt: skip
    state = start.state_dict()
    rows = state["denoiser.encoder.embedding.weight"]
    state["denoiser.encoder.embedding.weight"] = torch.cat([rows, rows.mean(dim=0, keepdim=True).expand(ne.objects - oe.objects, -1)])
    missing, unexpected = model.load_state_dict(state, strict=False)
    if unexpected or any(not any(k.startswith(a + ".") for a in added) for k in missing):
        raise ValueError(f"weights do not match the grown network: missing {missing}, unexpected {unexpected}")
    for name in added:
        conv = model.get_submodule(name).conv2
        nn.init.zeros_(conv.weight)
        nn.init.zeros_(conv.bias)
    return added


def transplant(model: AxisGenerator, start: AxisGenerator) -> list[str]:
    """Load `start`'s weights into `model` whose encoder stands on another trunk (e.g. an ImageNet one): the
    trunk keeps its own weights, every other tensor whose name and shape `start` has is copied (the denoiser, the
    dense and depth heads), and the layers that read the trunk's other widths (object FiLM, context input,
    laterals, the denoiser's injections) start fresh. Returns the names of the tensors left fresh outside the
    trunk, so a new trunk can be tried under a trained denoiser instead of from nothing."""
    old, new = start.config.denoiser, model.config.denoiser
    if replace(new, encoder=replace(new.encoder, trunk=old.encoder.trunk)) != old:
        raise ValueError(f"cannot transplant an AGM {old} into {new}: only the encoder's trunk may differ")
    own = model.state_dict()
    taken = {k: v for k, v in start.state_dict().items() if not k.startswith(TRUNK) and k in own and own[k].shape == v.shape}
    model.load_state_dict(taken, strict=False)
    return sorted(k for k in own if not k.startswith(TRUNK) and k not in taken)


def fresh_trunk(model: AxisGenerator) -> list[str]:
    """Set `model`'s trunk, and the layers that read its widths, to a new network's initial weights drawn from
    torch's random state, the rest (the denoiser, the heads) kept: a trunk trained anew under a trained denoiser.
    The layers that read the trunk are those a transplant onto another trunk leaves fresh (asked, not listed
    here). Returns the names of the tensors set."""
    agm = model.config
    encoder = replace(agm.denoiser.encoder, trunk=EfficientNetLiteConfig(weights="none"))
    other = AxisGenerator(replace(agm, denoiser=replace(agm.denoiser, encoder=encoder)))
    reading = {name.rsplit(".", 1)[0] for name in transplant(other, model)}
    initial, state = AxisGenerator(agm).state_dict(), model.state_dict()
    reset = [k for k in state if k.startswith(TRUNK) or k.rsplit(".", 1)[0] in reading]
    model.load_state_dict(state | {k: initial[k] for k in reset})
    return reset
