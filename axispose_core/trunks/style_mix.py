"""Feature-statistics mixing (MixStyle, Zhou et al., ICLR 2021) between a trunk's stages while it trains.

A convolutional feature map's per-channel mean and spread carry much of an image's "style" (colour response,
contrast, surface finish) and little of where things are. Mixing them between the batch's samples shows the layers
after a stage the same content in styles no renderer draws, so they learn to ignore style: a domain-generalisation
regulariser with no data of the target domain. It has no weights and is the identity outside training.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn


@dataclass(frozen=True)
class StyleMixConfig:
    prob: float = 0.0
    """Chance that a batch's features are mixed after each of `after` (0: off)."""
    alpha: float = 0.1
    """Beta(alpha, alpha) draws each sample's weight on its own statistics: small alpha keeps most mixes near one
    style or the other."""
    after: tuple[int, ...] = (1, 2, 3)
    """Trunk stages (0 = the first, stride 2) whose output is mixed: the middle ones, below the semantic last."""
    eps: float = 1e-6


class StyleMix(nn.Module):
    """Each sample's per-channel mean and standard deviation replaced by a Beta-weighted mix of its own and another
    sample's (a random pairing of the batch); statistics detached, as in the paper, so gradients see content only."""

    def __init__(self, config: StyleMixConfig) -> None:
        super().__init__()
        if not 0 <= config.prob <= 1 or config.alpha <= 0:
            raise ValueError(f"style mixing needs a probability in [0, 1] and alpha > 0, got {config}")
        self.config = config

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b = x.shape[0]
        if not self.training or b < 2 or torch.rand(()) >= self.config.prob:
            return x
        dims = tuple(range(2, x.dim()))
        mu = x.mean(dims, keepdim=True).detach()
        sigma = (x.var(dims, keepdim=True) + self.config.eps).sqrt().detach()
        weight = torch.distributions.Beta(self.config.alpha, self.config.alpha).sample((b,) + (1,) * (x.dim() - 1))
        weight = weight.to(x.device, x.dtype)
        other = torch.randperm(b, device=x.device)
        mixed_mu = weight * mu + (1 - weight) * mu[other]
        mixed_sigma = weight * sigma + (1 - weight) * sigma[other]
        return (x - mu) / sigma * mixed_sigma + mixed_mu
