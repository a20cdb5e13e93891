"""The Axis Generation Module: denoiser + DDIM schedule, its training loss and its sampler."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import torch
from torch import nn

from axispose_core.agm.denoiser import Denoiser, DenoiserConfig
from axispose_core.agm.guidance import AxisGeometry, axis_geometry, guided_eps
from axispose_core.agm.scheduler import DDIMScheduler, SchedulerConfig


class Cancelled(Exception):
    """Sampling was stopped between DDIM steps by its `cancelled` callback."""


@dataclass(frozen=True)
class AGMConfig:
    denoiser: DenoiserConfig = field(default_factory=DenoiserConfig)
    scheduler: SchedulerConfig = field(default_factory=lambda: SchedulerConfig(prediction_type="sample"))
    train_guidance: bool = True
    """Inject the L_geo gradient into the noise estimate during training (the paper's method; see `loss`)."""
    guidance_sigma: float = 1.0
    """σ of the measurement model g = H(x0) + n: the injection's step size is 1/σ²."""
    line_weight: float = 10.0
    """Extra loss weight on the pixels the target's axes cover (~5 % of a 64 px image): without it the loss is
    met by an all-background image, which is what an unweighted run converged to."""


class AxisGenerator(nn.Module):
    """Crop (B,3,S,S) in [-1,1] -> axis image (B,3,S,S) in [-1,1] by DDIM."""

    def __init__(self, config: AGMConfig) -> None:
        super().__init__()
        self.config = config
        self.denoiser = Denoiser(config.denoiser)
        self.scheduler = DDIMScheduler(config.scheduler)

    def loss(self, crops: torch.Tensor, x0: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
        """Diffusion loss at random timesteps; with train_guidance the guided estimate ε' is what the loss sees."""
        b = x0.shape[0]
        sched = self.scheduler
        t = torch.randint(0, sched.config.num_train_timesteps, (b,), generator=generator).to(x0.device)
        noise = torch.randn(x0.shape, generator=generator).to(x0.device)
        x_t = sched.add_noise(x0, noise, t)
        out = self.denoiser(x_t, t, self.denoiser.encode(crops))
        if self.config.train_guidance:
            abar = sched.alphas_cumprod.to(x0.device)[t].to(x0.dtype).view(-1, 1, 1, 1)
            eps, _ = sched.to_eps_x0(out, t, x_t, clip=False)
            eps_g = guided_eps(eps, x_t, abar, axis_geometry(x0), self.config.guidance_sigma, create_graph=True)
            # ε-prediction: the ε-loss sees ε' (the paper). Other parametrisations: ε' is mapped back with x̂0
            # clamped to the image range, as sampling does: unclamped, the 1/√ᾱ_t factors blow up at large t.
            out = sched.from_eps(eps_g, t, x_t, clip=sched.config.prediction_type != "epsilon")
        weight = 1 + self.config.line_weight * (x0 > -1).any(dim=1, keepdim=True).to(x0.dtype)
        return (weight * (out - sched.target(x0, noise, t)) ** 2).mean()

    def forward(self, crops: torch.Tensor, x0: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
        """The training loss (so that DistributedDataParallel wraps it)."""
        return self.loss(crops, x0, generator)

    @torch.no_grad()
    def sample(
        self,
        crops: torch.Tensor,
        steps: int,
        eta: float = 0.0,
        generator: torch.Generator | None = None,
        guidance: Callable[[torch.Tensor], AxisGeometry] | None = None,
        guidance_scale: float = 0.0,
        cancelled: Callable[[], bool] | None = None,
    ) -> torch.Tensor:
        """Generate axis images; `guidance(x̂0) -> g` supplies the measurement for run-time guidance.
        `cancelled()` is asked before every step; True raises `Cancelled` (a node shutting down mid-frame)."""
        sched = self.scheduler
        sched.set_timesteps(steps)
        x = torch.randn(crops.shape, generator=generator, dtype=crops.dtype).to(crops.device)
        cond = self.denoiser.encode(crops)
        for t in sched.timesteps.tolist():
            if cancelled is not None and cancelled():
                raise Cancelled("sampling cancelled")
            out = self.denoiser(x, torch.full((x.shape[0],), t, device=x.device), cond)
            eps_override = None
            if guidance is not None and guidance_scale > 0:
                eps, x0 = sched.to_eps_x0(out, t, x)
                abar = sched.alphas_cumprod[t].to(x.dtype)
                sigma = self.config.guidance_sigma / guidance_scale**0.5
                eps_override = guided_eps(eps, x, abar, guidance(x0), sigma, create_graph=False)
            x, x0 = sched.step(out, t, x, eta=eta, generator=generator, eps_override=eps_override)
        return x0
