"""The TBM's regression network: axis image -> origin and three endpoints, robust to what a diffusion model draws.

Four heatmaps (origin, end X, end Y, end Z) at half resolution are read by soft-argmax, which keeps the
prediction sub-pixel and translation-equivariant. Dilated residual blocks at quarter resolution see the whole
axis, which is what tells a segment's far end from its origin. It is trained on rendered, degraded axis images
(train/reader.py).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from axispose_core.axis_image import DEFAULT_LINE_WIDTH
from axispose_core.checkpoint import load_state, read_checkpoint
from axispose_core.tbm.keypoints import AxisKeypoints

KIND = "tbm_reader"
SHIPPED_READER = Path(__file__).resolve().parents[1] / "models" / "tbm_reader.safetensors"
"""The reader trained by `axispose train-reader` (train/reader.py's defaults), installed with the package."""


@dataclass(frozen=True)
class ReaderConfig:
    """The keypoint reader's network; saved inside its checkpoint (training: train/reader.py)."""

    RETIRED: ClassVar[frozenset[str]] = frozenset({"steps", "batch", "lr", "degrade_prob", "seed"})
    """Training settings that checkpoints of earlier versions kept here."""

    size: int = 64
    channels: int = 32
    blocks: tuple[int, ...] = (1, 2, 4, 8, 1)
    line_width: float = DEFAULT_LINE_WIDTH


class _DilatedBlock(nn.Module):
    def __init__(self, ch: int, dilation: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(ch, ch, 3, padding=dilation, dilation=dilation)
        self.norm1 = nn.GroupNorm(8, ch)
        self.conv2 = nn.Conv2d(ch, ch, 3, padding=1)
        self.norm2 = nn.GroupNorm(8, ch)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h = F.silu(self.norm1(self.conv1(x)))
        return F.silu(x + self.norm2(self.conv2(h)))


class KeypointReader(nn.Module):
    """(B,3,S,S) axis images in [0,1] -> (B,4,2) keypoints in patch pixels (origin, end X, end Y, end Z)."""

    def __init__(self, config: ReaderConfig) -> None:
        super().__init__()
        self.config = config
        ch = config.channels
        self.stem = nn.Sequential(
            nn.Conv2d(3, ch, 3, stride=2, padding=1),
            nn.GroupNorm(8, ch),
            nn.SiLU(),
            nn.Conv2d(ch, ch, 3, padding=1),
            nn.GroupNorm(8, ch),
            nn.SiLU(),
        )
        self.down = nn.Sequential(nn.Conv2d(ch, ch, 3, stride=2, padding=1), nn.GroupNorm(8, ch), nn.SiLU())
        self.context = nn.Sequential(*[_DilatedBlock(ch, d) for d in config.blocks])
        self.fuse = nn.Sequential(nn.Conv2d(2 * ch, ch, 3, padding=1), nn.GroupNorm(8, ch), nn.SiLU())
        self.head = nn.Conv2d(ch, 4, 1)

    def heatmaps(self, x: torch.Tensor) -> torch.Tensor:
        """Logits (B,4,S/2,S/2)."""
        skip = self.stem(x)
        ctx = self.context(self.down(skip))
        up = F.interpolate(ctx, size=skip.shape[-2:], mode="bilinear", align_corners=False)
        return self.head(self.fuse(torch.cat([skip, up], dim=1)))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        logits = self.heatmaps(x)
        b, k, h, w = logits.shape
        prob = logits.flatten(2).softmax(-1).view(b, k, h, w)
        scale = x.shape[-1] / w
        # Half-resolution cell i covers patch pixels [i*scale - 0.5, (i+1)*scale - 0.5]; its centre:
        gx = (torch.arange(w, device=x.device, dtype=x.dtype) + 0.5) * scale - 0.5
        gy = (torch.arange(h, device=x.device, dtype=x.dtype) + 0.5) * scale - 0.5
        u = (prob.sum(2) * gx).sum(-1)
        v = (prob.sum(3) * gy).sum(-1)
        return torch.stack([u, v], dim=-1)

    def read(self, images: np.ndarray | torch.Tensor) -> list[AxisKeypoints]:
        """Keypoints of HxWx3 (or BxHxWx3) NumPy axis images, or a (B,3,H,W) tensor."""
        x = torch.as_tensor(images, dtype=torch.float32)
        if x.ndim == 3:
            x = x[None]
        if x.shape[-1] == 3 and x.shape[1] != 3:
            x = x.permute(0, 3, 1, 2)
        if x.shape[-1] != self.config.size or x.shape[-2] != self.config.size:
            raise ValueError(f"reader expects {self.config.size}x{self.config.size} axis images, got {tuple(x.shape[-2:])}")
        with torch.inference_mode():
            kp = self(x.to(next(self.parameters()).device)).cpu().numpy().astype(np.float64)
        return [AxisKeypoints(k[0], k[1:]) for k in kp]


def load_reader(path: str | Path, device: str = "cpu") -> KeypointReader:
    """A trained reader from its checkpoint (config included), in eval mode."""
    config, states, _ = read_checkpoint(path, KIND, ReaderConfig)
    model = KeypointReader(config)
    load_state(model, states.get("reader", {}), str(path))
    return model.to(device).eval()
