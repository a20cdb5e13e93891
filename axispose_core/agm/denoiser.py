"""The AGM's conditional UNet: noisy axis image + object crop + timestep -> ε, x0 or v.

Two ways to see the crop (`DenoiserConfig.conditioning`):
- "concat": the paper's — the RGB crop is concatenated to the noisy axis image at the input, so every DDIM
  step re-reads the crop;
- "encoder": a crop encoder runs once per object and its features are added at every UNet scale, so each
  further DDIM step costs only the denoiser.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn


@dataclass(frozen=True)
class DenoiserConfig:
    size: int = 64
    channels: int = 32
    multipliers: tuple[int, ...] = (1, 2, 4)
    blocks_per_level: int = 1
    conditioning: str = "encoder"
    groups: int = 8


def timestep_embedding(t: torch.Tensor, dim: int) -> torch.Tensor:
    """Sinusoidal embedding of integer timesteps (B,) -> (B, dim)."""
    half = dim // 2
    freqs = torch.exp(-math.log(10000.0) * torch.arange(half, device=t.device, dtype=torch.float32) / half)
    args = t.float()[:, None] * freqs[None]
    return torch.cat([torch.sin(args), torch.cos(args)], dim=1)


class ResBlock(nn.Module):
    """GroupNorm-SiLU-conv twice, with the time embedding added in between."""

    def __init__(self, cin: int, cout: int, tdim: int, groups: int) -> None:
        super().__init__()
        self.norm1 = nn.GroupNorm(groups, cin)
        self.conv1 = nn.Conv2d(cin, cout, 3, padding=1)
        self.temb = nn.Linear(tdim, cout)
        self.norm2 = nn.GroupNorm(groups, cout)
        self.conv2 = nn.Conv2d(cout, cout, 3, padding=1)
        self.skip = nn.Conv2d(cin, cout, 1) if cin != cout else nn.Identity()

    def forward(self, x: torch.Tensor, temb: torch.Tensor) -> torch.Tensor:
        h = self.conv1(F.silu(self.norm1(x)))
        h = h + self.temb(temb)[:, :, None, None]
        h = self.conv2(F.silu(self.norm2(h)))
        return self.skip(x) + h


class CropEncoder(nn.Module):
    """Crop -> one feature map per UNet level (full, 1/2, 1/4, ... resolution)."""

    def __init__(self, config: DenoiserConfig) -> None:
        super().__init__()
        ch = [config.channels * m for m in config.multipliers]
        self.stem = nn.Sequential(nn.Conv2d(3, ch[0], 3, padding=1), nn.GroupNorm(config.groups, ch[0]), nn.SiLU())
        self.levels = nn.ModuleList()
        cin = ch[0]
        for i, c in enumerate(ch):
            stride = 1 if i == 0 else 2
            self.levels.append(
                nn.Sequential(
                    nn.Conv2d(cin, c, 3, stride=stride, padding=1), nn.GroupNorm(config.groups, c), nn.SiLU(),
                    nn.Conv2d(c, c, 3, padding=1), nn.GroupNorm(config.groups, c), nn.SiLU(),
                )
            )  # fmt: skip
            cin = c

    def forward(self, crop: torch.Tensor) -> list[torch.Tensor]:
        h = self.stem(crop)
        feats = []
        for level in self.levels:
            h = level(h)
            feats.append(h)
        return feats


class Denoiser(nn.Module):
    """UNet over the axis image; `encode(crop)` once, then `forward(x_t, t, cond)` per step."""

    def __init__(self, config: DenoiserConfig) -> None:
        super().__init__()
        if config.conditioning not in ("concat", "encoder"):
            raise ValueError(f"conditioning must be 'concat' or 'encoder', got {config.conditioning!r}")
        if config.size % (2 ** (len(config.multipliers) - 1)):
            raise ValueError(f"size {config.size} must be divisible by {2 ** (len(config.multipliers) - 1)}")
        self.config = config
        ch = [config.channels * m for m in config.multipliers]
        tdim = 4 * config.channels
        self.time_mlp = nn.Sequential(nn.Linear(config.channels, tdim), nn.SiLU(), nn.Linear(tdim, tdim))
        cin = 6 if config.conditioning == "concat" else 3
        self.inp = nn.Conv2d(cin, ch[0], 3, padding=1)
        self.encoder = CropEncoder(config) if config.conditioning == "encoder" else None
        self.inject = nn.ModuleList([nn.Conv2d(c, c, 1) for c in ch]) if self.encoder is not None else None
        self.down = nn.ModuleList()
        self.downsample = nn.ModuleList()
        c_prev = ch[0]
        for i, c in enumerate(ch):
            blocks = nn.ModuleList()
            for _ in range(config.blocks_per_level):
                blocks.append(ResBlock(c_prev, c, tdim, config.groups))
                c_prev = c
            self.down.append(blocks)
            self.downsample.append(nn.Conv2d(c, c, 3, stride=2, padding=1) if i < len(ch) - 1 else nn.Identity())
        self.mid = ResBlock(c_prev, c_prev, tdim, config.groups)
        self.up = nn.ModuleList()
        self.upsample = nn.ModuleList()
        for i in reversed(range(len(ch))):
            # The first block of a level also reads that level's skip connection.
            blocks = nn.ModuleList([ResBlock(c_prev + ch[i], ch[i], tdim, config.groups)])
            blocks.extend(ResBlock(ch[i], ch[i], tdim, config.groups) for _ in range(config.blocks_per_level - 1))
            self.up.append(blocks)
            self.upsample.append(nn.ConvTranspose2d(ch[i], ch[i - 1], 2, stride=2) if i > 0 else nn.Identity())
            c_prev = ch[max(i - 1, 0)]
        self.out = nn.Sequential(nn.GroupNorm(config.groups, ch[0]), nn.SiLU(), nn.Conv2d(ch[0], 3, 3, padding=1))
        nn.init.zeros_(self.out[-1].weight)
        nn.init.zeros_(self.out[-1].bias)

    def encode(self, crop: torch.Tensor) -> torch.Tensor | list[torch.Tensor]:
        """Per-object conditioning, computed once: encoder features, or the crop itself for "concat"."""
        return self.encoder(crop) if self.encoder is not None else crop

    def forward(self, x: torch.Tensor, t: torch.Tensor, cond: torch.Tensor | list[torch.Tensor]) -> torch.Tensor:
        temb = self.time_mlp(timestep_embedding(t.expand(x.shape[0]) if t.ndim == 0 else t, self.config.channels))
        h = self.inp(torch.cat([x, cond], dim=1) if self.encoder is None else x)
        skips = []
        for i, (blocks, down) in enumerate(zip(self.down, self.downsample, strict=True)):
            for block in blocks:
                h = block(h, temb)
            if self.inject is not None:
                h = h + self.inject[i](cond[i])
            skips.append(h)
            h = down(h)
        h = self.mid(h, temb)
        for blocks, up in zip(self.up, self.upsample, strict=True):
            h = torch.cat([h, skips.pop()], dim=1)
            for block in blocks:
                h = block(h, temb)
            h = up(h)
        return self.out(h)
