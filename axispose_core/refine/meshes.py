"""The refiner's object geometry: decimated meshes, carried in the estimator's checkpoint as buffers, from which
each object's viewpoint model is built where the checkpoint is used."""

from __future__ import annotations

import logging
from collections.abc import Iterable, Mapping
from pathlib import Path

import numpy as np
import torch

from axispose_core.data.bop import model_path
from axispose_core.data.meshes import load_ply
from axispose_core.data.synth.raster import RenderMesh, decimate

log = logging.getLogger(__name__)

MAX_FACES = 25_000
"""Most faces a carried mesh keeps: enough for a silhouette within a fraction of a pixel, few enough that eight
objects add about 1.5 MB to a checkpoint."""

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


def models_meshes(models_dir: str | Path, obj_ids: Iterable[int]) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """The objects' meshes for the refiner from a BOP models folder: BOP's decimated `models_eval` beside it where
    there is one, else the models themselves; a mesh with more than MAX_FACES faces is decimated (vertex
    clustering, finer cells until it fits)."""
    models_dir = Path(models_dir)
    eval_dir = models_dir.parent / "models_eval"
    out = {}
    for obj_id in obj_ids:
        src = model_path(eval_dir, obj_id) if model_path(eval_dir, obj_id).exists() else model_path(models_dir, obj_id)
        mesh = load_ply(src)
        v, f = mesh.vertices, mesh.faces
        if len(f) > MAX_FACES:
            extent = float(np.ptp(v, axis=0).max())
            cell = extent / 400
            render = RenderMesh(v, f, np.zeros_like(v), np.zeros_like(v))
            while len(f) > MAX_FACES:
                small = decimate(render, cell)
                v, f = small.vertices, small.faces
                cell *= 1.5
            log.info("object %d: %s decimated to %d faces for the refiner", obj_id, src, len(f))
        out[obj_id] = (v, f)
    return out
