"""Object crops and their axis-image targets from BOP folders, for training and evaluating the AGM."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset

from axispose_core.axis_image import DEFAULT_LINE_WIDTH, render_axis_image
from axispose_core.camera import CropJitter, InstanceCrop, instance_crop
from axispose_core.data.bop_scene import BopScene, bop_frames
from axispose_core.data.visibility import gt_info_from_models
from axispose_core.objects import ObjectSpec

DEFAULT_JITTER = CropJitter()


@dataclass(frozen=True)
class InstanceRef:
    scene: Path
    im_id: int
    index: int
    obj_id: int
    box: tuple[int, int, int, int]
    visib_fract: float


class AxisCropDataset(Dataset):
    """(crop, axis image, object index, K', R, t) per annotated instance with visib_fract >= min_visib.

    Crops are jittered like a detector's boxes when `jitter` is given (training), centred otherwise; crops are
    uint8, channels first (the network normalises them), axis images in [-1, 1]. The sample's randomness depends
    only on (seed, epoch, index). Scenes without scene_gt_info.json need `models_dir` (`bop_frames`).
    """

    def __init__(
        self,
        roots: list[str | Path],
        objects: list[ObjectSpec],
        size: int,
        min_visib: float = 0.1,
        jitter: CropJitter | None = DEFAULT_JITTER,
        color_aug: bool = True,
        seed: int = 0,
        models_dir: str | Path | None = None,
    ) -> None:
        self.objects = {o.obj_id: k for k, o in enumerate(objects)}
        self.specs = objects
        self.size, self.jitter, self.color_aug, self.seed = size, jitter, color_aug, seed
        self.epoch = 0
        self.items: list[InstanceRef] = []
        self.scenes: dict[Path, BopScene] = {}
        for scene, im_id in bop_frames(roots, gt_info_from_models(models_dir)):
            self.scenes[scene.root] = scene
            for k, (g, info) in enumerate(scene.instances(im_id)):
                if g.obj_id in self.objects and info.visib_fract >= min_visib:
                    self.items.append(InstanceRef(scene.root, im_id, k, g.obj_id, info.bbox_obj, info.visib_fract))

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        ref = self.items[i]
        scene = self.scenes[ref.scene]
        rng = np.random.default_rng([self.seed, self.epoch, i])
        rgb = scene.rgb(ref.im_id)
        K = scene.cameras[ref.im_id]
        g = scene.gt[ref.im_id][ref.index]
        crop = instance_crop(rgb, K, ref.box, self.size, rng if self.jitter else None, self.jitter or DEFAULT_JITTER)
        patch = crop.patch.astype(np.float32) / 255.0
        if self.color_aug:
            patch = np.clip(patch * rng.uniform(0.8, 1.2, 3) + rng.uniform(-0.08, 0.08), 0, 1).astype(np.float32)
        spec = self.specs[self.objects[ref.obj_id]]
        target = axis_target(crop, g.R, g.t, spec.axes.lengths, self.size)
        return {
            "crop": torch.from_numpy(np.round(patch * 255).astype(np.uint8)).permute(2, 0, 1),
            "axes": torch.from_numpy(target * 2 - 1).permute(2, 0, 1),
            "object": torch.tensor(self.objects[ref.obj_id]),
            "K": torch.from_numpy(crop.K_patch),
            "R": torch.from_numpy(g.R),
            "t": torch.from_numpy(g.t),
        }


def axis_target(
    crop: InstanceCrop, R: np.ndarray, t: np.ndarray, lengths: np.ndarray, size: int, line_width: float = DEFAULT_LINE_WIDTH
) -> np.ndarray:
    """The axis image (size x size x 3 in [0,1]) of the GT pose in this crop."""
    return render_axis_image(crop.K_patch, R, t, lengths, size, line_width)
