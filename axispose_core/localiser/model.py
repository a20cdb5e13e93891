"""The 2D localiser: a small CenterNet (centre heatmap per object, box size, centre offset) in plain PyTorch.

A trunk (`axispose_core/trunks`: the from-scratch BatchNorm residual one, or a pretrained EfficientNet-Lite0)
gives features at strides 8, 16 and optionally 32; the coarser ones are upsampled and fused into the stride-8 map
that three small heads read. The frame is resized to `input_size` (the shipped localiser: 384x288 for a 640x480
camera); boxes come back in the frame's own pixels.
"""

from __future__ import annotations

from copy import deepcopy
from dataclasses import dataclass, field

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch import nn
from torch.nn.utils.fusion import fuse_conv_bn_eval

from axispose_core.localiser.decode import Detection, decode
from axispose_core.trunks import Trunk, TrunkConfig, build_trunk
from axispose_core.trunks.residual import BNResidual, ResidualBNConfig, conv_bn_act

STRIDE = 8


@dataclass(frozen=True)
class LocaliserConfig:
    kind: str = "centernet"
    """Which localiser class this configures (LOCALISERS); a new localiser registers its own."""
    obj_ids: tuple[int, ...] = ()
    input_size: tuple[int, int] = (320, 240)
    """(width, height) the frame is resized to; both multiples of 16."""
    trunk: TrunkConfig = field(default_factory=ResidualBNConfig)
    """Its stages at strides 2..16, and optionally 32: a fifth stage's context (an object's surroundings and whole
    silhouette, which tell look-alike objects apart) is fused back into stride 16."""
    neck: int | None = None
    """Channels of the fused stride-8 map and the heads (None: the trunk's stride-8 width)."""
    neck_blocks: int = 1
    """Residual blocks on the fused stride-8 map before the heads: the layers that learn, where the trunk is frozen."""
    threshold: float = 0.3
    """Default score threshold of `detect`."""
    max_per_object: int = 3

    @staticmethod
    def upgrade_config(data: dict) -> dict:
        """A localiser written before it had a trunk: its `channels` were the BatchNorm residual trunk's widths."""
        if "channels" not in data:
            return data
        data = dict(data)
        data["trunk"] = {"kind": "residual_bn", "widths": data.pop("channels")}
        return data


PARTS = ("fuse32", "fuse", "heat", "size", "offset")
"""The localiser's parts after its trunk: the stride-32 fusion (a 5-stage trunk only), the neck, the heatmap, the box
size and the centre offset heads."""


class Localiser(nn.Module):
    """RGB frames (B,3,H,W) uint8 at `input_size` -> heatmap (B,C,H/8,W/8), log size (B,2,..), offset (B,2,..)."""

    def __init__(self, config: LocaliserConfig) -> None:
        super().__init__()
        w, h = config.input_size
        self.trunk: Trunk = build_trunk(config.trunk)
        widths = self.trunk.widths
        if len(widths) not in (4, 5):
            raise ValueError(f"a localiser's trunk has 4 or 5 stages (strides 2..16 or 2..32), got widths {widths}")
        if not config.obj_ids or w % 16 or h % 16:
            raise ValueError(f"a localiser needs object ids and an input size in multiples of 16, got {config}")
        self.config = config
        c8, c16 = widths[2], widths[3]
        neck = config.neck or c8
        if len(widths) == 5:
            self.fuse32 = conv_bn_act(c16 + widths[4], c16, 1)
        self.fuse = nn.Sequential(conv_bn_act(c8 + c16, neck, 1), *[BNResidual(neck) for _ in range(config.neck_blocks)])
        self.heat = nn.Sequential(conv_bn_act(neck, neck, 1), nn.Conv2d(neck, len(config.obj_ids), 1))
        self.size = nn.Sequential(conv_bn_act(neck, neck, 1), nn.Conv2d(neck, 2, 1))
        self.offset = nn.Sequential(conv_bn_act(neck, neck, 1), nn.Conv2d(neck, 2, 1))
        self.frozen_parts: tuple[str, ...] = ()
        nn.init.constant_(self.heat[-1].bias, -2.19)  # CenterNet's prior: sigmoid(-2.19) = 0.1

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        feats = self.trunk(self.trunk.normalise(x))
        f8, f16 = feats[2], feats[3]
        if len(feats) == 5:
            f16 = self.fuse32(torch.cat([f16, F.interpolate(feats[4], size=f16.shape[-2:], mode="nearest")], dim=1))
        f = self.fuse(torch.cat([f8, F.interpolate(f16, size=f8.shape[-2:], mode="nearest")], dim=1))
        with torch.autocast(f.device.type, enabled=False):  # bfloat16 rounds the heatmap to 1, and the focal loss's log to -inf
            f = f.float()
            return torch.sigmoid(self.heat(f)), self.size(f), self.offset(f)

    def freeze_parts(self, parts: tuple[str, ...]) -> None:
        """Keep these parts after the trunk (of `PARTS` it has) as they are while the rest trains: no gradients,
        BatchNorm statistics not updated. The neck and the heatmap frozen, the box heads train on without moving what
        finds the objects."""
        have = [name for name in PARTS if hasattr(self, name)]
        if unknown := [name for name in parts if name not in have]:
            raise ValueError(f"a localiser's parts are {', '.join(have)}; got {', '.join(unknown)}")
        self.frozen_parts = tuple(parts)
        for name in parts:
            getattr(self, name).requires_grad_(False)
        self.train(self.training)

    def train(self, mode: bool = True) -> Localiser:
        super().train(mode)
        for name in self.frozen_parts:
            getattr(self, name).eval()
        return self

    @staticmethod
    def upgrade_state(state: dict[str, torch.Tensor], prefix: str) -> None:
        """Weights saved before the localiser had a trunk (stem, s4, s8, s16, s32) under the trunk's names
        (`checkpoint.upgrade_state`)."""
        stages = {"stem": "trunk.stages.0.0", **{f"s{2 ** (i + 1)}": f"trunk.stages.{i}" for i in range(1, 5)}}
        for key in [k for k in state if k.startswith(prefix) and k[len(prefix) :].split(".")[0] in stages]:
            part, rest = key[len(prefix) :].split(".", 1)
            state[f"{prefix}{stages[part]}.{rest}"] = state.pop(key)

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
        """(1,3,H,W) uint8 input of an RGB uint8 frame of any size."""
        w, h = self.config.input_size
        small = cv2.resize(image_rgb, (w, h), interpolation=cv2.INTER_AREA)
        return torch.from_numpy(small).permute(2, 0, 1)[None]

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
