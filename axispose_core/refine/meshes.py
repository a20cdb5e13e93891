"""The refiner's object geometry: decimated meshes (`data.meshes.refiner_meshes` reads them from a models folder),
carried in the estimator's checkpoint as buffers, from which each object's viewpoint model is built where the
checkpoint is used."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import torch

Meshes = Mapping[int, tuple[np.ndarray, np.ndarray]]
"""Object id -> (vertices (M,3) in metres, faces (F,3))."""


class ObjectMeshes(torch.nn.Module):
    """The meshes as buffers `vertices_<id>`, `faces_<id>`, so `save_checkpoint` writes them with the weights."""

    def __init__(self, meshes: Meshes) -> None:
        super().__init__()
        for obj_id, (v, f) in sorted(meshes.items()):
            self.register_buffer(f"vertices_{obj_id}", torch.as_tensor(np.asarray(v, dtype=np.float32)))
            self.register_buffer(f"faces_{obj_id}", torch.as_tensor(np.asarray(f, dtype=np.int32)))

    @classmethod
    def from_state(cls, state: Mapping[str, torch.Tensor]) -> ObjectMeshes:
        """The meshes a checkpoint's `refine.*` tensors hold; ValueError where they do not pair up."""
        ids = {int(k.split("_", 1)[1]) for k in state}
        missing = [i for i in ids if f"vertices_{i}" not in state or f"faces_{i}" not in state]
        if missing or any(not k.startswith(("vertices_", "faces_")) for k in state):
            raise ValueError(f"refiner meshes: expected vertices_<id> and faces_<id> for each object, got {sorted(state)}")
        return cls({i: (state[f"vertices_{i}"].float().numpy(), state[f"faces_{i}"].long().numpy()) for i in ids})

    def meshes(self) -> dict[int, tuple[np.ndarray, np.ndarray]]:
        out = {}
        for name, buf in self.named_buffers():
            kind, obj_id = name.split("_", 1)
            out.setdefault(int(obj_id), {})[kind] = buf
        return {i: (d["vertices"].double().numpy(), d["faces"].long().numpy()) for i, d in sorted(out.items())}
