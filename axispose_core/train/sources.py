"""Where a crop trainer (the AGM, the direct baseline) takes its samples from: the annotated crops of BOP folders,
or else the crop stream over a models folder; and the held-out crops it validates on."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from axispose_core.data.bop_models import model_path
from axispose_core.data.meshes import load_ply
from axispose_core.data.synth.config import StreamConfig
from axispose_core.data.synth.stream import CropStream, CropStreamDataset
from axispose_core.evaluation.records import object_symmetries
from axispose_core.metrics import Symmetry
from axispose_core.objects import ObjectSpec, dataset_objects
from axispose_core.train.dataset import AxisCropDataset

VAL_MIN_VISIB = 0.3
"""Held-out instances of BOP folders are at least this visible."""


@dataclass(frozen=True)
class CropSources:
    data: tuple[str | Path, ...] = ()
    """Annotated BOP folders to train on; none: the crop stream."""
    val: tuple[str | Path, ...] = ()
    """Held-out BOP folders; none: the stream's held-out crops when training on the stream, else no validation."""
    models: str | Path | None = None
    """The BOP models folder the crop stream renders."""

    def models_folder(self) -> Path | None:
        """The BOP models folder with the objects' meshes: the stream's, else a data folder's `models/` (as `axispose
        synth` writes for imported meshes); None where the data names none."""
        if self.models is not None:
            return Path(self.models)
        return next((Path(d) / "models" for d in self.data if (Path(d) / "models" / "models_info.json").is_file()), None)

    def describe(self) -> list[str]:
        """The run's data, as its training record names it."""
        return [str(d) for d in self.data] or [f"crop stream of {self.models}"]

    def training(
        self, dataset: type[AxisCropDataset], stream: StreamConfig, size: int, min_visib: float, seed: int
    ) -> tuple[list[ObjectSpec], AxisCropDataset | None, CropStream | None]:
        """The objects and either the BOP folders' crops (a `dataset`, instances at least `min_visib` visible) or
        the crop stream of `stream`; its crops must be `size` px, the network's."""
        if self.data:
            objects = dataset_objects(list(self.data))
            train_set = dataset(list(self.data), objects, size, min_visib, seed=seed)
            if not len(train_set):
                raise ValueError(f"no training instances with visib_fract >= {min_visib} in {list(self.data)}")
            return objects, train_set, None
        if self.models is None:
            raise ValueError("give BOP folders to train on, or the object models for the crop stream")
        if stream.size != size:
            raise ValueError(f"the crop stream renders {stream.size}px crops; the network is configured for {size}px")
        crops = CropStream(stream, self.models)
        return crops.objects, None, crops

    def held_out(
        self, dataset: type[AxisCropDataset], objects: list[ObjectSpec], stream: StreamConfig, val_seed: int, size: int, n: int, seed: int
    ) -> list[dict[str, torch.Tensor]]:
        """Up to `n` held-out crops: spread evenly over the `val` folders' instances (centred, no colour
        augmentation), or the first `n` of the stream with seed `val_seed` (the same crops in every run of that
        stream configuration); none when training on BOP folders without `val`."""
        if self.val:
            val_set = dataset(list(self.val), objects, size, VAL_MIN_VISIB, jitter=None, color_aug=False, seed=seed)
            return [val_set[int(i)] for i in np.linspace(0, len(val_set) - 1, min(n, len(val_set))).astype(int)]
        if self.data:
            return []
        crops = CropStreamDataset(CropStream(dataclasses.replace(stream, seed=val_seed), self.models))
        return [crops[i] for i in range(n)]

    def symmetries(self, objects: list[ObjectSpec]) -> dict[int, list[Symmetry]]:
        """Each symmetric object's equivalent poses (by object id) from the models folder's points, so that the
        held-out rotation errors are taken up to symmetry as eval takes them; none without a models folder."""
        if self.models is None:
            return {}
        points = {o.obj_id: load_ply(model_path(self.models, o.obj_id)).vertices for o in objects if o.symmetric}
        return object_symmetries(objects, points)
