"""The Axis Generation Module: encoder + denoiser + DDIM schedule, its training loss and its sampler."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from axispose_core.agm.denoiser import Denoiser, DenoiserConfig, Encoding
from axispose_core.agm.guidance import AxisGeometry, axis_geometry, guided_eps
from axispose_core.agm.scheduler import DDIMScheduler, SchedulerConfig

VERSION = 2
"""The AGM's network generation: 2 is the object-conditioned encoder with dense and depth heads; checkpoints
without it were made by an earlier AxisPose, whose networks this one cannot run."""


def log_depth_target(K: torch.Tensor, t: torch.Tensor, scale: torch.Tensor, size: int) -> torch.Tensor:
    """The encoder's depth target log(z S / (f λ_O)) for crop intrinsics K (B,3,3), translations t (B,3) and object
    scales λ_O (B,): f is the crop's mean focal length in px, S its side."""
    f = 0.5 * (K[:, 0, 0] + K[:, 1, 1])
    return torch.log(t[:, 2] * size / (f * scale)).float()


def depth_from_log(log_depth: float, K: np.ndarray, scale: float, size: int) -> float:
    """Inverse of `log_depth_target` for one crop: metres, linear in λ_O."""
    return math.exp(log_depth) * 0.5 * float(K[0, 0] + K[1, 1]) * scale / size


def encoder_losses(enc: Encoding, batch: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """The encoder's dense and depth losses on the targets the batch has: "points" (L1 over the visible pixels, in
    object radii), "mask" (binary cross-entropy), "depth" (L1 on log depth); and "unused", 0 times every head, so
    that a head without its target still enters the graph (DistributedDataParallel wants every parameter used)."""
    parts = {"unused": 0.0 * (enc.points.sum() + enc.mask.sum() + enc.log_depth.sum()).float()}
    if "points" in batch:
        m = batch["mask_visib"]
        parts["points"] = (m * (enc.points.float() - batch["points"]).abs()).sum() / (3 * m.sum() + 1)
        parts["mask"] = F.binary_cross_entropy_with_logits(enc.mask.float(), m)
    if "log_depth" in batch:
        parts["depth"] = (enc.log_depth.float() - batch["log_depth"]).abs().mean()
    return parts


@dataclass(frozen=True)
class EncoderLossConfig:
    """Weights of the crop encoder's auxiliary losses (`encoder_losses`), one section for every network built on
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


class Cancelled(Exception):
    """Sampling was stopped between DDIM steps by its `cancelled` callback."""


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
    """Crop (B,3,S,S) in [-1,1] and object index (B,) -> axis image (B,3,S,S) in [-1,1] by DDIM."""

    def __init__(self, config: AGMConfig) -> None:
        super().__init__()
        if config.version != VERSION:
            raise ValueError(f"AGM version {config.version} is not this AxisPose's ({VERSION})")
        self.config = config
        self.denoiser = DENOISERS[config.denoiser.kind](config.denoiser)
        self.scheduler = DDIMScheduler(config.scheduler)

    def encode(self, crops: torch.Tensor, objects: torch.Tensor) -> Encoding:
        return self.denoiser.encode(crops, objects)

    def losses(self, batch: dict[str, torch.Tensor], generator: torch.Generator | None = None) -> dict[str, torch.Tensor]:
        """The training losses of a batch (crop, object, axes; points + mask_visib and log_depth where known):
        "diffusion" at random timesteps (with train_guidance, the guided estimate ε' is what it sees), the
        encoder's "points", "mask" and "depth", and their weighted "total"."""
        crops, x0 = batch["crop"], batch["axes"]
        cfg, sched = self.config, self.scheduler
        b = x0.shape[0]
        t = torch.randint(0, sched.config.num_train_timesteps, (b,), generator=generator).to(x0.device)
        noise = torch.randn(x0.shape, generator=generator).to(x0.device)
        x_t = sched.add_noise(x0, noise, t)
        enc = self.encode(crops, batch["object"])
        out = self.denoiser(x_t, t, enc)
        if cfg.train_guidance:
            abar = sched.alphas_cumprod.to(x0.device)[t].to(x0.dtype).view(-1, 1, 1, 1)
            eps, _ = sched.to_eps_x0(out, t, x_t, clip=False)
            eps_g = guided_eps(eps, x_t, abar, axis_geometry(x0), cfg.guidance_sigma, create_graph=True)
            # ε-prediction: the ε-loss sees ε' (the paper). Other parametrisations: ε' is mapped back with x̂0
            # clamped to the image range, as sampling does: unclamped, the 1/√ᾱ_t factors blow up at large t.
            out = sched.from_eps(eps_g, t, x_t, clip=sched.config.prediction_type != "epsilon")
        weight = 1 + cfg.line_weight * (x0 > -1).any(dim=1, keepdim=True).to(x0.dtype)
        parts = {"diffusion": (weight * (out.float() - sched.target(x0, noise, t)) ** 2).mean(), **encoder_losses(enc, batch)}
        parts["total"] = cfg.encoder_loss.total(parts, "diffusion")
        return parts

    def forward(self, batch: dict[str, torch.Tensor], generator: torch.Generator | None = None) -> torch.Tensor:
        """The total training loss (so that DistributedDataParallel wraps it)."""
        return self.losses(batch, generator)["total"]

    @torch.no_grad()
    def sample(
        self,
        enc: Encoding,
        steps: int,
        eta: float = 0.0,
        generator: torch.Generator | None = None,
        guidance: Callable[[torch.Tensor], AxisGeometry] | None = None,
        guidance_scale: float = 0.0,
        cancelled: Callable[[], bool] | None = None,
        noise_scale: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Generate one axis image per row of `enc` (`Encoding.repeat` for several per crop); `guidance(x̂0) -> g`
        supplies the measurement for run-time guidance. `cancelled()` is asked before every step; True raises
        `Cancelled` (a node shutting down mid-frame). `noise_scale` (one factor per row) scales the starting noise
        x_T: 0 starts the deterministic (eta = 0) path from the mode of the prior N(0, I)."""
        sched = self.scheduler
        sched.set_timesteps(steps)
        S = self.config.denoiser.size
        ref = enc.context
        x = torch.randn((ref.shape[0], 3, S, S), generator=generator, dtype=ref.dtype).to(ref.device)
        if noise_scale is not None:
            x = x * noise_scale.to(x).view(-1, 1, 1, 1)
        for t in sched.timesteps.tolist():
            if cancelled is not None and cancelled():
                raise Cancelled("sampling cancelled")
            out = self.denoiser(x, torch.full((x.shape[0],), t, device=x.device), enc)
            eps_override = None
            if guidance is not None and guidance_scale > 0:
                eps, x0 = sched.to_eps_x0(out, t, x)
                abar = sched.alphas_cumprod[t].to(x.dtype)
                sigma = self.config.guidance_sigma / guidance_scale**0.5
                eps_override = guided_eps(eps, x, abar, guidance(x0), sigma, create_graph=False)
            x, x0 = sched.step(out, t, x, eta=eta, generator=generator, eps_override=eps_override)
        return x0


def grow_into(model: AxisGenerator, start: AxisGenerator) -> list[str]:
    """Load `start`'s weights into `model`: the same network (its training settings, e.g. loss weights, may
    differ), or one whose encoder has more residual blocks per stage; returns the names of the blocks added (none
    for the same network). The added blocks start as the identity (their last convolution zeroed), so the grown
    network computes what `start` did and training goes on from its weights with more capacity."""
    old, new = start.config, model.config
    oe, ne = old.denoiser.encoder, new.denoiser.encoder
    same = replace(new.denoiser, encoder=replace(ne, blocks=oe.blocks))
    if same != old.denoiser or len(ne.blocks) != len(oe.blocks) or any(n < o for n, o in zip(ne.blocks, oe.blocks, strict=True)):
        raise ValueError(f"cannot grow an AGM {old.denoiser} into {new.denoiser}: only the encoder's blocks per stage may grow")
    added = [f"denoiser.encoder.stages.{s}.{b}" for s, (o, n) in enumerate(zip(oe.blocks, ne.blocks, strict=True)) for b in range(o, n)]
    missing, unexpected = model.load_state_dict(start.state_dict(), strict=False)
    if unexpected or any(not any(k.startswith(a + ".") for a in added) for k in missing):
        raise ValueError(f"weights do not match the grown network: missing {missing}, unexpected {unexpected}")
    for name in added:
        conv = model.get_submodule(name).conv2
        nn.init.zeros_(conv.weight)
        nn.init.zeros_(conv.bias)
    return added
