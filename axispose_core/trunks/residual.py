"""The from-scratch trunks: residual stages with GroupNorm (the AGM's crop encoder, whose batches mix objects and
crop scales) and with BatchNorm (the localiser, which folds it into its convolutions for inference)."""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from axispose_core.trunks.base import Trunk


@dataclass(frozen=True)
class ResidualGNConfig:
    kind: str = "residual_gn"
    widths: tuple[int, ...] = (32, 64, 128, 256)
    """Channels of the stages at strides 2, 4, 8, 16, ... (a 64 px crop: 32, 16, 8 and 4 px)."""
    blocks: tuple[int, ...] = (1, 2, 2, 1)
    """Residual blocks per stage."""
    groups: int = 8


@dataclass(frozen=True)
class ResidualBNConfig:
    kind: str = "residual_bn"
    widths: tuple[int, ...] = (16, 32, 64, 96)
    """Channels of the stages at strides 2, 4, 8, 16 and optionally 32; the stages after the first hold 1, 1, 2 and
    2 residual blocks."""


class ResBlock(nn.Module):
    """GroupNorm-SiLU-conv twice, with an embedding (time, context) added in between when given."""

    def __init__(self, cin: int, cout: int, groups: int, edim: int = 0) -> None:
        super().__init__()
        self.norm1 = nn.GroupNorm(groups, cin)
        self.conv1 = nn.Conv2d(cin, cout, 3, padding=1)
        self.emb = nn.Linear(edim, cout) if edim else None
        self.norm2 = nn.GroupNorm(groups, cout)
        self.conv2 = nn.Conv2d(cout, cout, 3, padding=1)
        self.skip = nn.Conv2d(cin, cout, 1) if cin != cout else nn.Identity()

    def forward(self, x: torch.Tensor, emb: torch.Tensor | None = None) -> torch.Tensor:
        h = self.conv1(F.silu(self.norm1(x)))
        if self.emb is not None and emb is not None:
            h = h + self.emb(emb)[:, :, None, None]
        h = self.conv2(F.silu(self.norm2(h)))
        return self.skip(x) + h


class ResidualGN(Trunk):
    """Stage 0: a stride-2 convolution, GroupNorm, SiLU, then its blocks; stage i > 0: a stride-2 convolution, then
    its blocks (`ResBlock`)."""

    def __init__(self, config: ResidualGNConfig) -> None:
        super().__init__()
        if len(config.blocks) != len(config.widths) or not config.widths:
            raise ValueError(f"the residual trunk needs one block count per stage, got {config}")
        self.config = config
        w, g = config.widths, config.groups
        self.widths = tuple(w)
        for i, (c, b) in enumerate(zip(w, config.blocks, strict=True)):
            entry = (
                nn.Sequential(nn.Conv2d(3, c, 3, stride=2, padding=1), nn.GroupNorm(g, c), nn.SiLU())
                if i == 0
                else nn.Conv2d(w[i - 1], c, 3, stride=2, padding=1)
            )
            self.stages.append(nn.Sequential(entry, *(ResBlock(c, c, g) for _ in range(b))))


def conv_bn_act(c_in: int, c_out: int, stride: int) -> nn.Sequential:
    """3x3 convolution, BatchNorm, SiLU (a Sequential, so that `fuse_conv_bn_eval` can fold the pair)."""
    return nn.Sequential(nn.Conv2d(c_in, c_out, 3, stride, 1, bias=False), nn.BatchNorm2d(c_out), nn.SiLU(inplace=True))


class BNResidual(nn.Module):
    def __init__(self, c: int) -> None:
        super().__init__()
        self.body = nn.Sequential(conv_bn_act(c, c, 1), nn.Conv2d(c, c, 3, 1, 1, bias=False), nn.BatchNorm2d(c))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.silu(x + self.body(x))


RESIDUALS_BN = (0, 1, 1, 2, 2)
"""Residual blocks after each stage's strided convolution (ResidualBN)."""


class ResidualBN(Trunk):
    """Each stage: a stride-2 conv_bn_act, then its residual blocks (RESIDUALS_BN)."""

    def __init__(self, config: ResidualBNConfig) -> None:
        super().__init__()
        if not 1 <= len(config.widths) <= len(RESIDUALS_BN):
            raise ValueError(f"the BatchNorm residual trunk has 1 to {len(RESIDUALS_BN)} stages, got widths {config.widths}")
        self.config = config
        self.widths = tuple(config.widths)
        c_prev = 3
        for c, n in zip(config.widths, RESIDUALS_BN, strict=False):
            self.stages.append(nn.Sequential(conv_bn_act(c_prev, c, 2), *(BNResidual(c) for _ in range(n))))
            c_prev = c
