"""What every trunk is: stages at strides 2, 4, 8, ..., their widths, its input normalisation, and what training may
do to it (freeze a pretrained one's first stages or its BatchNorm statistics, mix feature statistics between stages)."""

from __future__ import annotations

import torch
from torch import nn

from axispose_core.trunks.style_mix import StyleMix, StyleMixConfig

MINUS_ONE_TO_ONE = ((0.5, 0.5, 0.5), (0.5, 0.5, 0.5))
"""(mean, std) of [0, 1] pixels that map them to [-1, 1]: what the from-scratch networks were trained on."""


class Trunk(nn.Module):
    """Subclasses fill `stages` (stage i at stride 2^(i+1)) and `widths`, and set `mean`/`std` (per channel, of
    pixels in [0, 1]) to the statistics their weights expect."""

    widths: tuple[int, ...]
    mean: tuple[float, float, float] = MINUS_ONE_TO_ONE[0]
    std: tuple[float, float, float] = MINUS_ONE_TO_ONE[1]

    def __init__(self) -> None:
        super().__init__()
        self.stages = nn.ModuleList()
        self.frozen = 0
        self.batchnorm_frozen = False
        self.style_mix: StyleMix | None = None

    @property
    def pretrained(self) -> bool:
        """Whether training starts these stages from learned weights (`load_pretrained`) rather than at random."""
        return False

    def load_pretrained(self) -> None:
        """Load the weights the config names; nothing for a trunk trained from scratch."""

    def normalise(self, images: torch.Tensor) -> torch.Tensor:
        """uint8 images (B,3,H,W) -> float32 input of the first stage."""
        if images.dtype != torch.uint8:
            raise TypeError(f"a trunk takes uint8 images (B,3,H,W), got {images.dtype}: networks normalise their own input")
        mean = torch.tensor(self.mean, device=images.device).view(1, 3, 1, 1)
        std = torch.tensor(self.std, device=images.device).view(1, 3, 1, 1)
        return images.float() / (255 * std) - mean / std  # [-1, 1]: x / 127.5 - 1, as the from-scratch networks were trained

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        """Every stage's output for a normalised input."""
        feats = []
        for k, stage in enumerate(self.stages):
            x = stage(x)
            if self.style_mix is not None and k in self.style_mix.config.after:
                x = self.style_mix(x)
            feats.append(x)
        return feats

    def freeze(self, stages: int, batchnorm: bool = False) -> None:
        """Keep the first `stages` stages as they are: no gradients, BatchNorm statistics not updated (they stay in
        eval mode whatever `train()` says). `batchnorm`: keep every stage's BatchNorm statistics as loaded, the
        trainable stages' included, so that their features stay normalised as on the photographs they came from."""
        if not 0 <= stages <= len(self.stages):
            raise ValueError(f"cannot freeze {stages} of the trunk's {len(self.stages)} stages")
        self.frozen, self.batchnorm_frozen = stages, batchnorm
        for k, stage in enumerate(self.stages):
            stage.requires_grad_(k >= stages)
        self.train(self.training)

    def train(self, mode: bool = True) -> Trunk:
        super().train(mode)
        for stage in list(self.stages)[: self.frozen]:
            stage.eval()
        if self.batchnorm_frozen:
            for norm in self.stages.modules():
                if isinstance(norm, nn.modules.batchnorm._BatchNorm):
                    norm.eval()
        return self

    def mix_styles(self, config: StyleMixConfig) -> None:
        """Mix feature statistics after the stages `config.after` names while training (`StyleMix`); no weights, so
        checkpoints and inference are unchanged."""
        if config.prob > 0 and any(not 0 <= k < len(self.stages) - 1 for k in config.after):
            raise ValueError(f"style mixing goes between stages: after one of 0..{len(self.stages) - 2}, got {config.after}")
        self.style_mix = StyleMix(config) if config.prob > 0 else None
