"""The AGM's networks: a crop encoder that runs once per object, and a light denoiser that runs per DDIM step.

The encoder carries the perception. It sees the whole crop (a trunk's strided stages down to 1/16 of it, then the
4 x 4 layout flattened into one context vector) and is told which object it looks at (an embedding that scales and
shifts every stage). Besides the features the denoiser reads, it predicts what supervises it densely: the
visible surface's model coordinates and mask at half resolution (the correspondences of GDR-Net-style methods:
every pixel says something about the pose) and a scale-invariant depth (GDR-Net's SITE: depth relative to the
crop's focal length and the object's size λ_O, so λ_O scales the translation linearly).

The denoiser works at half the axis image's resolution (pixel-unshuffled), reads the encoder's maps at each of
its levels and the context vector with the timestep embedding, so that a DDIM step or one more hypothesis costs
a fraction of the encoder.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import nn

from axispose_core.trunks import Trunk, TrunkConfig, build_trunk
from axispose_core.trunks.residual import ResBlock, ResidualGNConfig


@dataclass(frozen=True)
class EncoderConfig:
    trunk: TrunkConfig = field(default_factory=ResidualGNConfig)
    """The stages the encoder is built on (`axispose_core/trunks`): strides 2, 4, 8, 16 (a 64 px crop: 32, 16, 8 and
    4 px), each told the object by FiLM."""
    objects: int = 8
    """Rows of the object embedding: the estimator's objects by their position in its list."""
    embed: int = 64
    context: int = 256
    """Length of the global context vector (the crop's layout at the last stage, flattened)."""
    dense: int = 64
    """Channels of the half-resolution map the dense head and the denoiser's first level read."""
    groups: int = 8
    """GroupNorm groups of the heads."""

    @staticmethod
    def upgrade_config(data: dict) -> dict:
        """An encoder written before it had a trunk: its widths and blocks were a GroupNorm residual trunk's, with
        the encoder's groups."""
        if "trunk" in data or not {"widths", "blocks"} & set(data):
            return data
        data = dict(data)
        legacy = {k: data.pop(k) for k in ("widths", "blocks") if k in data}
        data["trunk"] = {"kind": "residual_gn", **legacy, "groups": data.get("groups", 8)}
        return data


@dataclass(frozen=True)
class DenoiserConfig:
    kind: str = "unet"
    """Which denoiser class this configures (`agm/model.py`'s DENOISERS); a new denoiser registers its own."""
    size: int = 64
    """Side of the crop and of the axis image (px)."""
    channels: int = 32
    """Channels at the denoiser's first level (half the axis image's resolution)."""
    multipliers: tuple[int, ...] = (1, 2, 4)
    """Channel multipliers of its levels at 1/2, 1/4, 1/8 ...: at most as many as the encoder has stages."""
    groups: int = 8
    encoder: EncoderConfig = field(default_factory=EncoderConfig)


def timestep_embedding(t: torch.Tensor, dim: int) -> torch.Tensor:
    """Sinusoidal embedding of integer timesteps (B,) -> (B, dim)."""
    half = dim // 2
    freqs = torch.exp(-math.log(10000.0) * torch.arange(half, device=t.device, dtype=torch.float32) / half)
    args = t.float()[:, None] * freqs[None]
    return torch.cat([torch.sin(args), torch.cos(args)], dim=1)


class Encoding(NamedTuple):
    """What the encoder computes once per crop."""

    maps: list[torch.Tensor]
    """Feature maps for the denoiser's levels: the dense map at 1/2, then the stages at 1/4, 1/8, ..."""
    context: torch.Tensor
    """(B, context): the whole crop and the object in one vector."""
    points: torch.Tensor
    """(B, 3, S/2, S/2): the visible surface's model coordinates in units of the object's radius."""
    mask: torch.Tensor
    """(B, 1, S/2, S/2): logits of the object's visible mask."""
    log_depth: torch.Tensor
    """(B,): log(z S / (f λ_O)), the depth relative to the crop's focal length f (px) and the object's size."""

    def repeat(self, k: int) -> Encoding:
        """Each crop's encoding k times in a row (k hypotheses of one crop share its encoder pass)."""
        return Encoding(
            *([m.repeat_interleave(k, dim=0) for m in v] if isinstance(v, list) else v.repeat_interleave(k, dim=0) for v in self)
        )


class CropEncoder(nn.Module):
    """Crop (B,3,S,S) uint8 + object index (B,) -> `Encoding`."""

    def __init__(self, config: EncoderConfig, size: int) -> None:
        super().__init__()
        self.trunk: Trunk = build_trunk(config.trunk)
        w = self.widths = self.trunk.widths
        n = len(w)
        if n < 3 or size % 2**n:
            raise ValueError(f"the encoder needs at least 3 trunk stages and a crop size divisible by 2^stages, got {n} and {size}")
        if config.objects < 1:
            raise ValueError("the encoder needs at least one object")
        self.config = config
        self.embedding = nn.Embedding(config.objects, config.embed)
        # FiLM by the object: zero-initialised, so an untrained network starts as if unconditioned.
        self.film = nn.ModuleList(nn.Linear(config.embed, 2 * c) for c in w)
        for lin in self.film:
            nn.init.zeros_(lin.weight)
            nn.init.zeros_(lin.bias)
        last = size // 2**n
        self.context = nn.Sequential(
            nn.Flatten(),
            nn.Linear(w[-1] * last * last + config.embed, config.context),
            nn.SiLU(),
            nn.Linear(config.context, config.context),
        )
        self.lateral = nn.ModuleList(nn.Conv2d(c, config.dense, 1) for c in w[:3])
        self.dense = ResBlock(config.dense, config.dense, config.groups, config.context)
        self.dense_out = nn.Sequential(nn.GroupNorm(config.groups, config.dense), nn.SiLU(), nn.Conv2d(config.dense, 4, 1))
        self.depth = nn.Sequential(nn.SiLU(), nn.Linear(config.context, 1))

    def forward(self, crop: torch.Tensor, obj: torch.Tensor) -> Encoding:
        e = self.embedding(obj)
        h = self.trunk.normalise(crop)
        feats = []
        for stage, film in zip(self.trunk.stages, self.film, strict=True):
            h = stage(h)
            scale, shift = film(e)[:, :, None, None].chunk(2, dim=1)
            h = h * (1 + scale) + shift
            feats.append(h)
        context = self.context(torch.cat([h.flatten(1), e], dim=1))
        # The dense map: the first three stages brought to 1/2 resolution and summed, then told the context.
        top = feats[0].shape[-1]
        lat = sum(F.interpolate(lat(f), size=top, mode="nearest") if f.shape[-1] != top else lat(f)
                  for lat, f in zip(self.lateral, feats[:3], strict=True))  # fmt: skip
        dense = self.dense(lat, context)
        out = self.dense_out(dense)
        with torch.autocast(context.device.type, enabled=False):  # bfloat16's 3 digits would be ~0.5 % of depth
            log_depth = self.depth(context.float())[:, 0]
        return Encoding([dense, *feats[1:]], context, out[:, :3], out[:, 3:], log_depth)

    @staticmethod
    def upgrade_state(state: dict[str, torch.Tensor], prefix: str) -> None:
        """Weights saved before the encoder had a trunk (stem, down.i, stages.i.j) under the trunk's names
        (`checkpoint.upgrade_state`)."""
        for key in [k for k in state if k.startswith(prefix) and k[len(prefix) :].split(".")[0] in ("stem", "down", "stages")]:
            part, rest = key[len(prefix) :].split(".", 1)
            if part == "stem":
                new = f"trunk.stages.0.0.{rest}"
            elif part == "down":
                i, tail = rest.split(".", 1)
                new = f"trunk.stages.{i}.0.{tail}"  # stage 0's was an identity, without weights
            else:
                i, j, tail = rest.split(".", 2)
                new = f"trunk.stages.{i}.{int(j) + 1}.{tail}"
            state[prefix + new] = state.pop(key)


class Denoiser(nn.Module):
    """UNet over the pixel-unshuffled axis image; `encode(crop, obj)` once, then `forward(x_t, t, enc)` per step."""

    def __init__(self, config: DenoiserConfig) -> None:
        super().__init__()
        enc = config.encoder
        levels = len(config.multipliers)
        self.encoder = CropEncoder(enc, config.size)
        widths = self.encoder.widths
        if not 1 <= levels <= len(widths):
            raise ValueError(f"the denoiser's {levels} levels need as many encoder stages (it has {len(widths)})")
        if config.size % 2:
            raise ValueError(f"size {config.size} must be even")
        self.config = config
        ch = [config.channels * m for m in config.multipliers]
        edim = 4 * config.channels
        self.time_mlp = nn.Sequential(nn.Linear(config.channels, edim), nn.SiLU(), nn.Linear(edim, edim))
        self.context_proj = nn.Linear(enc.context, edim)
        self.inp = nn.Conv2d(12, ch[0], 3, padding=1)
        sources = [enc.dense, *widths[1:]]
        self.inject = nn.ModuleList(nn.Conv2d(sources[i], c, 1) for i, c in enumerate(ch))
        self.down = nn.ModuleList()
        self.downsample = nn.ModuleList()
        c_prev = ch[0]
        for i, c in enumerate(ch):
            self.down.append(ResBlock(c_prev, c, config.groups, edim))
            c_prev = c
            self.downsample.append(nn.Conv2d(c, c, 3, stride=2, padding=1) if i < levels - 1 else nn.Identity())
        self.mid = ResBlock(c_prev, c_prev, config.groups, edim)
        self.up = nn.ModuleList()
        self.upsample = nn.ModuleList()
        for i in reversed(range(levels)):
            self.up.append(ResBlock(c_prev + ch[i], ch[i], config.groups, edim))
            self.upsample.append(nn.ConvTranspose2d(ch[i], ch[i - 1], 2, stride=2) if i > 0 else nn.Identity())
            c_prev = ch[max(i - 1, 0)]
        self.out = nn.Sequential(nn.GroupNorm(config.groups, ch[0]), nn.SiLU(), nn.Conv2d(ch[0], 12, 3, padding=1))
        nn.init.zeros_(self.out[-1].weight)
        nn.init.zeros_(self.out[-1].bias)

    def encode(self, crop: torch.Tensor, obj: torch.Tensor) -> Encoding:
        """Per-object conditioning, computed once per crop (and shared by its hypotheses and DDIM steps)."""
        return self.encoder(crop, obj)

    def forward(self, x: torch.Tensor, t: torch.Tensor, enc: Encoding) -> torch.Tensor:
        t = t.expand(x.shape[0]) if t.ndim == 0 else t
        emb = self.time_mlp(timestep_embedding(t, self.config.channels)) + self.context_proj(enc.context)
        h = self.inp(F.pixel_unshuffle(x, 2))
        skips = []
        for i, (block, down) in enumerate(zip(self.down, self.downsample, strict=True)):
            h = block(h, emb) + self.inject[i](enc.maps[i])
            skips.append(h)
            h = down(h)
        h = self.mid(h, emb)
        for block, up in zip(self.up, self.upsample, strict=True):
            h = up(block(torch.cat([h, skips.pop()], dim=1), emb))
        return F.pixel_shuffle(self.out(h), 2)
