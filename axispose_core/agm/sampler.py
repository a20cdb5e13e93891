"""Sampling the AGM (diffusers' pipeline side): DDIM from x_T to an axis image, each row's start scaled (0: the
prior's mode), with run-time guidance injected into the noise estimate, cancellable between steps."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

from axispose_core.agm.denoiser import Encoding
from axispose_core.agm.guidance import AxisGeometry, guided_eps
from axispose_core.agm.model import AxisGenerator


class Cancelled(Exception):
    """Sampling was stopped between DDIM steps by its `cancelled` callback."""


@dataclass(frozen=True)
class Guidance:
    """Run-time guidance for `sample`: the measurement and its weight travel together, as neither means anything
    alone. `target(x̂0) -> g` supplies the measurement; `scale` weighs it (0: off)."""

    target: Callable[[torch.Tensor], AxisGeometry]
    scale: float


@torch.no_grad()
def sample(
    agm: AxisGenerator,
    enc: Encoding,
    steps: int,
    eta: float = 0.0,
    generator: torch.Generator | None = None,
    guidance: Guidance | None = None,
    cancelled: Callable[[], bool] | None = None,
    noise_scale: torch.Tensor | None = None,
) -> torch.Tensor:
    """One axis image (B,3,S,S) in [-1,1] per row of `enc` (`Encoding.repeat` for several per crop), with run-time
    `guidance` where given (None or scale 0: off). `cancelled()` is asked before every step; True raises
    `Cancelled` (a node shutting down mid-frame). `noise_scale` (one factor per row) scales the starting noise x_T:
    0 starts the deterministic (eta = 0) path from the mode of N(0, I)."""
    sched = agm.scheduler
    sched.set_timesteps(steps)
    S = agm.config.denoiser.size
    ref = enc.context
    x = torch.randn((ref.shape[0], 3, S, S), generator=generator, dtype=ref.dtype).to(ref.device)
    if noise_scale is not None:
        x = x * noise_scale.to(x).view(-1, 1, 1, 1)
    for t in sched.timesteps.tolist():
        if cancelled is not None and cancelled():
            raise Cancelled("sampling cancelled")
        out = agm.denoiser(x, torch.full((x.shape[0],), t, device=x.device), enc)
        eps_override = None
        if guidance is not None and guidance.scale > 0:
            eps, x0 = sched.to_eps_x0(out, t, x)
            abar = sched.alphas_cumprod[t].to(x.dtype)
            sigma = agm.config.guidance_sigma / guidance.scale**0.5
            eps_override = guided_eps(eps, x, abar, guidance.target(x0), sigma, create_graph=False)
        x, x0 = sched.step(out, t, x, eta=eta, generator=generator, eps_override=eps_override)
    return x0
