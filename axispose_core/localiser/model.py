"""The 2D localiser: a small CenterNet (centre heatmap per object, box size, centre offset) in plain PyTorch.

torchvision cannot be installed beside the pinned torch here, so the backbone is written out: a stride-16
residual encoder whose stride-16 features are upsampled and fused with the stride-8 ones, read by three 1x1
heads at stride 8. The frame is resized to `input_size` (the shipped localiser: 384x288 for a 640x480 camera,
20 ms on two cores through `fused`, inside the 30 ms budget); boxes come back in the frame's own pixels.
"""

from __future__ import annotations

from copy import deepcopy
from dataclasses import dataclass

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch import nn
from torch.nn.utils.fusion import fuse_conv_bn_eval

from axispose_core.localiser.decode import Detection, decode

STRIDE = 8


@dataclass(frozen=True)
class LocaliserConfig:
    kind: str = "centernet"
    """Which localiser class this configures (LOCALISERS); a new localiser registers its own."""
    obj_ids: tuple[int, ...] = ()
    input_size: tuple[int, int] = (320, 240)
    """(width, height) the frame is resized to; both multiples of 16."""
    channels: tuple[int, ...] = (16, 32, 64, 96)
    """Widths at strides 2, 4, 8, 16, and optionally 32: a fifth width adds a stride-32 stage whose context (an
    object's surroundings and whole silhouette, which tell look-alike objects apart) is fused back into stride 16."""
    threshold: float = 0.3
    """Default score threshold of `detect`."""
    max_per_object: int = 3


def _block(c_in: int, c_out: int, stride: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(c_in, c_out, 3, stride, 1, bias=False), nn.BatchNorm2d(c_out), nn.SiLU(inplace=True))


class _Residual(nn.Module):
    def __init__(self, c: int) -> None:
        super().__init__()
        self.body = nn.Sequential(_block(c, c, 1), nn.Conv2d(c, c, 3, 1, 1, bias=False), nn.BatchNorm2d(c))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.silu(x + self.body(x))


class Localiser(nn.Module):
    """RGB frames (B,3,H,W) in [-1,1] at `input_size` -> heatmap (B,C,H/8,W/8), log size (B,2,..), offset (B,2,..)."""

    def __init__(self, config: LocaliserConfig) -> None:
        super().__init__()
        w, h = config.input_size
        if not config.obj_ids or w % 16 or h % 16:
            raise ValueError(f"a localiser needs object ids and an input size in multiples of 16, got {config}")
        self.config = config
        if len(config.channels) not in (4, 5):
            raise ValueError(f"localiser channels are 4 or 5 widths (strides 2..16 or 2..32), got {config.channels}")
        c2, c4, c8, c16 = config.channels[:4]
        self.stem = _block(3, c2, 2)
        self.s4 = nn.Sequential(_block(c2, c4, 2), _Residual(c4))
        self.s8 = nn.Sequential(_block(c4, c8, 2), _Residual(c8))
        self.s16 = nn.Sequential(_block(c8, c16, 2), _Residual(c16), _Residual(c16))
        if len(config.channels) == 5:
            c32 = config.channels[4]
            self.s32 = nn.Sequential(_block(c16, c32, 2), _Residual(c32), _Residual(c32))
            self.fuse32 = _block(c16 + c32, c16, 1)
        self.fuse = nn.Sequential(_block(c8 + c16, c8, 1), _Residual(c8))
        self.heat = nn.Sequential(_block(c8, c8, 1), nn.Conv2d(c8, len(config.obj_ids), 1))
        self.size = nn.Sequential(_block(c8, c8, 1), nn.Conv2d(c8, 2, 1))
        self.offset = nn.Sequential(_block(c8, c8, 1), nn.Conv2d(c8, 2, 1))
        nn.init.constant_(self.heat[-1].bias, -2.19)  # CenterNet's prior: sigmoid(-2.19) = 0.1

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        f8 = self.s8(self.s4(self.stem(x)))
        f16 = self.s16(f8)
        if hasattr(self, "s32"):
            f16 = self.fuse32(torch.cat([f16, F.interpolate(self.s32(f16), size=f16.shape[-2:], mode="nearest")], dim=1))
        f = self.fuse(torch.cat([f8, F.interpolate(f16, size=f8.shape[-2:], mode="nearest")], dim=1))
        return torch.sigmoid(self.heat(f)), self.size(f), self.offset(f)

    def fused(self) -> Localiser:
        """An inference copy with every BatchNorm folded into the convolution before it, in channels-last memory:
        the same outputs (to float rounding) in less time on the CPU (docs/BENCHMARKS.md). Its layers no longer
        have the trainable layout, so it serves `detect`; train and save the original."""
        copy = deepcopy(self).eval()
        for seq in [m for m in copy.modules() if isinstance(m, nn.Sequential)]:
            for k in range(len(seq) - 1):
                if isinstance(seq[k], nn.Conv2d) and isinstance(seq[k + 1], nn.BatchNorm2d):
                    seq[k], seq[k + 1] = fuse_conv_bn_eval(seq[k], seq[k + 1]), nn.Identity()
        return copy.to(memory_format=torch.channels_last)

    def prepare(self, image_rgb: np.ndarray) -> torch.Tensor:
        """(1,3,H,W) input tensor of an RGB uint8 frame of any size."""
        w, h = self.config.input_size
        small = cv2.resize(image_rgb, (w, h), interpolation=cv2.INTER_AREA)
        return torch.from_numpy(small).permute(2, 0, 1)[None].float() / 127.5 - 1

    @torch.inference_mode()
    def detect(self, image_rgb: np.ndarray, threshold: float | None = None) -> list[Detection]:
        """Detections in the frame's pixels, best first; none (not an error) when nothing scores above threshold."""
        if image_rgb.ndim != 3 or image_rgb.shape[2] != 3 or image_rgb.dtype != np.uint8:
            raise ValueError(f"detect takes an HxWx3 uint8 RGB image, got {image_rgb.shape} {image_rgb.dtype}")
        dev = next(self.parameters()).device
        heat, size, offset = self(self.prepare(image_rgb).to(dev, memory_format=torch.channels_last))
        w, h = self.config.input_size
        sx, sy = image_rgb.shape[1] / w, image_rgb.shape[0] / h
        thr = self.config.threshold if threshold is None else threshold
        dets = decode(heat.cpu(), size.cpu(), offset.cpu(), list(self.config.obj_ids), STRIDE, thr, self.config.max_per_object)[0]
        return [Detection(d.obj_id, d.score, (d.center[0] * sx, d.center[1] * sy), (d.size[0] * sx, d.size[1] * sy)) for d in dets]


LOCALISERS: dict[str, type[Localiser]] = {"centernet": Localiser}
"""Localiser classes by the `kind` of their config: a new one (same `detect` interface) is registered here, its
config class added to the type of EstimatorConfig.localiser with its own `kind`."""


def build_localiser(config: LocaliserConfig) -> Localiser:
    """The localiser network `config` describes (untrained)."""
    return LOCALISERS[config.kind](config)
