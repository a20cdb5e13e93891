"""The direct-regression baseline: the AGM's crop encoder regresses the origin and three axis endpoints from its
context vector in one forward pass (no diffusion, no axis image), and the same TBM back-projection turns them
into a pose. It is trained with the same auxiliary heads (surface points, mask, depth) as the AGM's encoder.

It answers the question the benchmark asks of the method: with the same backbone, data and training budget,
is generating an axis image worth its cost over regressing the four keypoints it encodes?
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import nn

from axispose_core.agm.denoiser import CropEncoder, EncoderConfig
from axispose_core.agm.model import EncoderLossConfig
from axispose_core.checkpoint import load_state, read_checkpoint, save_checkpoint
from axispose_core.estimator_stages import crop_batch
from axispose_core.objects import ObjectSpec
from axispose_core.tbm.backproject import Backprojection, backproject

KIND = "direct_regressor"
Box = tuple[int, tuple[float, float, float, float]]


@dataclass(frozen=True)
class DirectConfig:
    encoder: EncoderConfig = field(default_factory=EncoderConfig)
    """The backbone: the AGM's crop encoder."""
    size: int = 64
    objects: tuple[ObjectSpec, ...] = ()
    crop_pad: float = 1.25
    encoder_loss: EncoderLossConfig = field(default_factory=EncoderLossConfig)


class DirectRegressor(nn.Module):
    """Crop (B,3,S,S) uint8 + object index (B,) -> keypoints (B,4,2): origin, end X, end Y, end Z."""

    def __init__(self, config: DirectConfig) -> None:
        super().__init__()
        self.config = config
        self.encoder = CropEncoder(config.encoder, config.size)
        self.head = nn.Sequential(nn.SiLU(), nn.Linear(config.encoder.context, 8))

    def forward(self, crops: torch.Tensor, objects: torch.Tensor) -> torch.Tensor:
        """Keypoints in normalised crop coordinates (-1, 1 at the crop's edges), (B,4,2)."""
        return self.head(self.encoder(crops, objects).context).view(-1, 4, 2)

    def keypoints(self, crops: torch.Tensor, objects: torch.Tensor) -> torch.Tensor:
        """Keypoints in crop pixels (pixel centres at integers), (B,4,2)."""
        return (self(crops, objects) + 1) * 0.5 * self.config.size - 0.5


def keypoints_to_normalised(kp: torch.Tensor, size: int) -> torch.Tensor:
    """Crop pixels -> the regressor's output units (inverse of `DirectRegressor.keypoints`)."""
    return (kp + 0.5) / size * 2 - 1


class DirectEstimator:
    """`estimate(image, K, boxes)` like `Estimator.estimate`, with the regressor in place of AGM + reader."""

    def __init__(self, model: DirectRegressor) -> None:
        self.model = model.eval()
        self.objects = {o.obj_id: o for o in model.config.objects}

    @classmethod
    def load(cls, path: str | Path) -> DirectEstimator:
        config, states, _ = read_checkpoint(path, KIND, DirectConfig)
        model = DirectRegressor(config)
        load_state(model, states.get("regressor", {}), str(path))
        return cls(model)

    def save(self, path: str | Path, extra: dict | None = None) -> None:
        save_checkpoint(path, KIND, self.model.config, {"regressor": self.model}, extra=extra)

    @torch.inference_mode()
    def estimate(self, image_rgb: np.ndarray, K: np.ndarray, boxes: list[Box]) -> list[Backprojection]:
        """One pose per (obj_id, (x, y, w, h)) box; a refused one says why in `reason`, as the TBM's do."""
        cuts, x = crop_batch(image_rgb, K, boxes, self.objects, self.model.config.size, self.model.config.crop_pad)
        if not boxes:
            return []
        index = {o.obj_id: k for k, o in enumerate(self.model.config.objects)}
        kps = self.model.keypoints(x, torch.tensor([index[obj_id] for obj_id, _ in boxes])).double().numpy()
        return [
            backproject(cut.K_patch, kp[0], kp[1:], self.objects[obj_id].axes.lengths, refine=True)
            for (obj_id, _), cut, kp in zip(boxes, cuts, kps, strict=True)
        ]
