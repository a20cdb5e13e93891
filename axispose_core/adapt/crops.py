"""The recording's real crops at their pseudo-poses as AGM training samples, in the crop stream's form, and the
batches that mix them with the stream.

A pseudo-labelled frame is a BOP frame whose scene_gt.json holds the labels (`labels.write_labels`), so the crops
are cut as `AxisCropDataset` cuts annotated ones (a detector's jitter around the model's box); on top, what the
stream's samples carry: strong photometric augmentation on the student's input (Self6D++), and the surface
points and visible mask rendered at the pseudo-pose, the frame's other labelled objects in front masking it.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch

from axispose_core.camera import CropJitter
from axispose_core.data.meshes import load_render_mesh
from axispose_core.data.synth.appearance import photometric
from axispose_core.data.synth.config import PhotometricConfig
from axispose_core.data.synth.raster import Light, render
from axispose_core.data.synth.stream import CropStream, stream_loader
from axispose_core.objects import ObjectSpec
from axispose_core.train.dataset import AxisCropDataset

KEYS = ("crop", "axes", "object", "K", "R", "t", "visib", "points", "mask_visib")
"""What a training batch of the AGM holds (the stream's samples, the keypoints left out)."""
_FLAT = Light(np.array([0.0, 0.0, 1.0]), np.ones(3), 1.0)


class LabelledCrops(AxisCropDataset):
    """Crops of pseudo-labelled BOP frames (`roots`) with the stream's keys: photometric augmentation by `augment`,
    surface points (object radii) and visible mask rendered from the meshes of `models_dir` at the labels."""

    def __init__(
        self, roots: list[str | Path], objects: list[ObjectSpec], size: int, models_dir: str | Path, augment: PhotometricConfig,
        min_visib: float = 0.1, jitter: CropJitter | None = None, seed: int = 0,
    ) -> None:  # fmt: skip
        super().__init__(roots, objects, size, min_visib, jitter or CropJitter(), color_aug=True, seed=seed)
        self.augment = augment
        self.meshes = {o.obj_id: load_render_mesh(models_dir, o.obj_id) for o in objects}
        self.radius = {o.obj_id: 0.5 * o.diameter for o in objects}

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        item = super().__getitem__(i)
        ref = self.items[i]
        rng = np.random.default_rng([self.seed, self.epoch, i, 1])
        image, _ = photometric(rng, self.augment, item["crop"].permute(1, 2, 0).numpy().astype(np.float32) / 255)
        scene = self.scenes[ref.scene]
        labels = scene.gt[ref.im_id]
        K = item["K"].numpy()
        res = render([(self.meshes[g.obj_id], g.R, g.t) for g in labels], K, self.size, self.size, _FLAT)
        visible = res.instance == ref.index
        points = np.where(visible[..., None], res.points, np.float32(0)) / np.float32(self.radius[ref.obj_id])
        return item | {
            "crop": torch.from_numpy((np.clip(image, 0, 1) * 255 + 0.5).astype(np.uint8)).permute(2, 0, 1),
            "visib": torch.tensor(ref.visib_fract),
            "points": torch.from_numpy(points.astype(np.float32)).permute(2, 0, 1),
            "mask_visib": torch.from_numpy(visible.astype(np.float32))[None],
        }


def _stacked(items: list[dict[str, torch.Tensor]]) -> dict[str, torch.Tensor]:
    return {k: torch.stack([it[k] for it in items]) for k in KEYS}


def mixed_batches(
    real: LabelledCrops, stream: CropStream, batch: int, real_per_batch: int, step: int, seed: int, workers: int = 0
) -> Iterator[dict[str, torch.Tensor]]:
    """Endless training batches from `step` on: `real_per_batch` real crops (drawn by the step's own seed, the
    dataset's augmentation seeded by the step too) and the stream's next `batch - real_per_batch` samples (samples
    step * n ... of its endless order), so a resumed run continues where it stopped."""
    n = batch - real_per_batch
    loader = iter(stream_loader(stream, n, start=step * n, workers=workers)) if n > 0 else None
    while True:
        rng = np.random.default_rng([seed, step])
        real.epoch = step
        picks = rng.choice(len(real), size=real_per_batch, replace=len(real) < real_per_batch)
        parts = [_stacked([real[int(k)] for k in picks])] if real_per_batch else []
        if loader is not None:
            parts.append({k: v for k, v in next(loader).items() if k in KEYS})
        yield {k: torch.cat([p[k] for p in parts]) for k in KEYS}
        step += 1
