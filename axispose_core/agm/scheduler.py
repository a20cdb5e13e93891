"""DDIM noise schedule and sampler step, with a diffusers-like API: `set_timesteps(n)` then `step(...)`.

The scheduler owns the schedule and nothing else. It converts between the three network parametrisations
(ε, x0 and v) so that the denoiser may predict whichever trains best while guidance and sampling work in one
place.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import torch

PREDICTIONS = ("epsilon", "sample", "v_prediction")


@dataclass(frozen=True)
class SchedulerConfig:
    num_train_timesteps: int = 1000
    beta_schedule: str = "linear"
    beta_start: float = 1e-4
    beta_end: float = 0.02
    prediction_type: str = "epsilon"
    clip_sample: bool = True
    """Clamp predicted x0 to [-1, 1] (axis images are bounded)."""


class StepOutput(NamedTuple):
    prev_sample: torch.Tensor
    pred_original_sample: torch.Tensor


class DDIMScheduler:
    """ᾱ_t over T training steps (linear betas as in the paper, or the cosine schedule) and the DDIM update."""

    def __init__(self, config: SchedulerConfig = SchedulerConfig()) -> None:
        if config.prediction_type not in PREDICTIONS:
            raise ValueError(f"prediction_type must be one of {PREDICTIONS}, got {config.prediction_type!r}")
        if config.num_train_timesteps < 1:
            raise ValueError("num_train_timesteps must be at least 1")
        self.config = config
        T = config.num_train_timesteps
        if config.beta_schedule == "linear":
            betas = torch.linspace(config.beta_start, config.beta_end, T, dtype=torch.float64)
        elif config.beta_schedule == "cosine":
            s = 0.008
            f = [math.cos(((i / T) + s) / (1 + s) * math.pi / 2) ** 2 for i in range(T + 1)]
            betas = torch.tensor([min(1 - f[i + 1] / f[i], 0.999) for i in range(T)], dtype=torch.float64)
        else:
            raise ValueError(f"beta_schedule must be 'linear' or 'cosine', got {config.beta_schedule!r}")
        self.alphas_cumprod = torch.cumprod(1.0 - betas, dim=0)
        self.timesteps = torch.arange(T - 1, -1, -1)

    def set_timesteps(self, num_inference_steps: int) -> None:
        """Evenly spaced timesteps from T-1 down in steps of T // n (diffusers' 'trailing' spacing: it starts at pure
        noise and stops short of 0, e.g. 999, 749, 499, 249 for 4 of 1000)."""
        T = self.config.num_train_timesteps
        if not 1 <= num_inference_steps <= T:
            raise ValueError(f"num_inference_steps must lie in [1, {T}], got {num_inference_steps}")
        ratio = T // num_inference_steps
        self.timesteps = (torch.arange(num_inference_steps - 1, -1, -1) * ratio + (T - 1 - (num_inference_steps - 1) * ratio)).long()
        self.num_inference_steps = num_inference_steps

    def _abar(self, t: torch.Tensor | int, like: torch.Tensor) -> torch.Tensor:
        a = self.alphas_cumprod.to(like.device)[torch.as_tensor(t, device=like.device).long()]
        return a.to(like.dtype).reshape(-1, *([1] * (like.ndim - 1))) if a.ndim else a.to(like.dtype)

    def add_noise(self, x0: torch.Tensor, noise: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """x_t = √ᾱ_t x0 + √(1-ᾱ_t) ε."""
        a = self._abar(t, x0)
        return a.sqrt() * x0 + (1 - a).sqrt() * noise

    def velocity(self, x0: torch.Tensor, noise: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """v = √ᾱ_t ε − √(1-ᾱ_t) x0, the v-prediction target."""
        a = self._abar(t, x0)
        return a.sqrt() * noise - (1 - a).sqrt() * x0

    def target(self, x0: torch.Tensor, noise: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """What the network is trained to output under the configured parametrisation."""
        kind = self.config.prediction_type
        return noise if kind == "epsilon" else x0 if kind == "sample" else self.velocity(x0, noise, t)

    def to_eps_x0(
        self, model_output: torch.Tensor, t: torch.Tensor | int, x: torch.Tensor, clip: bool | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """(ε̂, x̂0) from the network output at x_t, whatever it predicts; x̂0 clipped if `clip` (default: config)."""
        a = self._abar(t, x)
        kind = self.config.prediction_type
        if kind == "epsilon":
            eps = model_output
            x0 = (x - (1 - a).sqrt() * eps) / a.sqrt()
        elif kind == "sample":
            x0 = model_output
            eps = (x - a.sqrt() * x0) / (1 - a).sqrt()
        else:
            x0 = a.sqrt() * x - (1 - a).sqrt() * model_output
            eps = a.sqrt() * model_output + (1 - a).sqrt() * x
        if self.config.clip_sample if clip is None else clip:
            x0 = x0.clamp(-1, 1)
            eps = (x - a.sqrt() * x0) / (1 - a).sqrt()
        return eps, x0

    def from_eps(self, eps: torch.Tensor, t: torch.Tensor | int, x: torch.Tensor, clip: bool = False) -> torch.Tensor:
        """The network output that corresponds to the noise estimate ε at x_t (inverse of `to_eps_x0`).

        With `clip`, the implied x̂0 is clamped to [-1, 1] first, as the sampler does.
        """
        a = self._abar(t, x)
        x0 = (x - (1 - a).sqrt() * eps) / a.sqrt()
        if clip:
            x0 = x0.clamp(-1, 1)
            eps = (x - a.sqrt() * x0) / (1 - a).sqrt()
        kind = self.config.prediction_type
        return eps if kind == "epsilon" else x0 if kind == "sample" else a.sqrt() * eps - (1 - a).sqrt() * x0

    def previous_timestep(self, t: int) -> int:
        return t - self.config.num_train_timesteps // self.num_inference_steps

    def step(
        self,
        model_output: torch.Tensor,
        timestep: int,
        sample: torch.Tensor,
        eta: float = 0.0,
        generator: torch.Generator | None = None,
        eps_override: torch.Tensor | None = None,
    ) -> StepOutput:
        """One DDIM update x_t -> x_{t-1} (eq. 12 of Song et al.; the paper's update rule).

        `eps_override` replaces the model's noise estimate, which is how guidance injects ε' = ε + ...
        """
        if not 0.0 <= eta <= 1.0:
            raise ValueError(f"eta must lie in [0, 1], got {eta}")
        if not hasattr(self, "num_inference_steps"):
            raise RuntimeError("call set_timesteps(n) before step()")
        eps, x0 = self.to_eps_x0(model_output, timestep, sample)
        if eps_override is not None:
            eps = eps_override
            a_t = self._abar(timestep, sample)
            x0 = (sample - (1 - a_t).sqrt() * eps) / a_t.sqrt()
            if self.config.clip_sample:
                x0 = x0.clamp(-1, 1)
        prev_t = self.previous_timestep(timestep)
        a_t = self._abar(timestep, sample)
        a_prev = self._abar(prev_t, sample) if prev_t >= 0 else torch.ones((), dtype=sample.dtype, device=sample.device)
        sigma = eta * ((1 - a_prev) / (1 - a_t) * (1 - a_t / a_prev)).sqrt()
        direction = (1 - a_prev - sigma**2).clamp_min(0).sqrt() * eps
        prev = a_prev.sqrt() * x0 + direction
        if eta > 0:
            noise = torch.randn(sample.shape, generator=generator, dtype=sample.dtype, device="cpu").to(sample.device)
            prev = prev + sigma * noise
        return StepOutput(prev, x0)
