"""Image trunks: the convolutional stages a network's heads read, chosen by the `kind` of their config, for the AGM's
crop encoder and the localiser alike (`build_trunk`).

A trunk owns its input normalisation: networks take images as uint8 tensors (B,3,H,W), as a camera gives them, and
the trunk maps them to what its weights expect (ImageNet weights expect their own statistics; a network trained
from scratch, [-1, 1]). Stage i works at stride 2^(i+1); `Trunk.forward` returns every stage's output.
"""

from __future__ import annotations

from axispose_core.trunks.base import Trunk
from axispose_core.trunks.efficientnet_lite import EfficientNetLite, EfficientNetLiteConfig
from axispose_core.trunks.residual import ResidualBN, ResidualBNConfig, ResidualGN, ResidualGNConfig

TrunkConfig = ResidualGNConfig | ResidualBNConfig | EfficientNetLiteConfig
"""Every trunk's config class; a field of this type picks one by its `kind`."""

TRUNKS: dict[str, type[Trunk]] = {"residual_gn": ResidualGN, "residual_bn": ResidualBN, "efficientnet_lite0": EfficientNetLite}
"""Trunk classes by the `kind` of their config: a new one is registered here and its config class added to
TrunkConfig."""


def build_trunk(config: TrunkConfig) -> Trunk:
    """The trunk `config` describes, randomly initialised (`Trunk.load_pretrained` loads what its config names)."""
    return TRUNKS[config.kind](config)


__all__ = ["TRUNKS", "EfficientNetLiteConfig", "ResidualBNConfig", "ResidualGNConfig", "Trunk", "TrunkConfig", "build_trunk"]
