"""Objects whose surfaces look other than their meshes say: the same geometry, other colours. A stand-in for a
user's objects whose scanned colours are wrong (LM-O's real eggbox is reddish brown, its mesh light grey), so that
adapting to the real look can be measured on renders with ground truth."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np

from axispose_core.data.bop_models import load_models_info, model_path
from axispose_core.data.meshes import Mesh, load_ply, write_ply


def recolour(colors: np.ndarray, vertices: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Vertex colours (N,3 uint8) turned 90-270 degrees in hue, scaled 0.6-1.4 in brightness and 0.5-1.5 in
    saturation, under a smooth pattern over the surface (a few blobs, +-25 % brightness)."""
    hsv = cv2.cvtColor(colors.reshape(-1, 1, 3).astype(np.uint8), cv2.COLOR_RGB2HSV).reshape(-1, 3).astype(np.float64)
    hsv[:, 0] = (hsv[:, 0] + rng.uniform(45, 135)) % 180  # OpenCV's hue runs 0-180
    hsv[:, 1] = np.clip(hsv[:, 1] * rng.uniform(0.5, 1.5) + rng.uniform(0, 40), 0, 255)
    centres = vertices[rng.choice(len(vertices), size=4)]
    scale = 0.25 * float(np.ptp(vertices, axis=0).max())
    blobs = sum(rng.uniform(-1, 1) * np.exp(-np.sum((vertices - c) ** 2, axis=1) / (2 * scale**2)) for c in centres)
    hsv[:, 2] = np.clip(hsv[:, 2] * rng.uniform(0.6, 1.4) * (1 + 0.25 * np.clip(blobs, -1, 1)), 0, 255)
    return cv2.cvtColor(hsv.astype(np.uint8).reshape(-1, 1, 3), cv2.COLOR_HSV2RGB).reshape(-1, 3)


def recoloured_models(models: str | Path, out: str | Path, seed: int) -> Path:
    """A BOP models folder OUT with every model of `models` recoloured (`recolour`, each object its own draw of
    `seed`) and the same models_info.json; returns OUT."""
    models, out = Path(models), Path(out)
    out.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(models / "models_info.json", out / "models_info.json")
    for name in ("names.json",):
        if (models / name).is_file():
            shutil.copyfile(models / name, out / name)
    for obj_id in sorted(load_models_info(models / "models_info.json")):
        mesh = load_ply(model_path(models, obj_id))
        colors = mesh.colors if mesh.colors is not None else np.full((len(mesh.vertices), 3), 160, np.uint8)
        rng = np.random.default_rng([seed, obj_id])
        write_ply(model_path(out, obj_id), Mesh(mesh.vertices, mesh.faces, recolour(colors, mesh.vertices, rng), mesh.normals))
    return out
