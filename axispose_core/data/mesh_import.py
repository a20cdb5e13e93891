"""Bring your own objects: PLY or OBJ meshes into a BOP models folder (obj_XXXXXX.ply + models_info.json).

Everything downstream (synthesis, metrics, training) then reads the folder like the LM-O models.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy.spatial.distance import pdist
from scipy.spatial.transform import Rotation

from axispose_core.camera import hull_points
from axispose_core.data.bop import MM, BopFormatError
from axispose_core.data.bop_models import ObjectInfo, model_path, write_models_info
from axispose_core.data.meshes import Mesh, load_mesh, write_ply
from axispose_core.objects import NAMES_FILE, object_name


def object_info(obj_id: int, mesh: Mesh) -> ObjectInfo:
    """Diameter (largest vertex distance, over the convex hull) and axis-aligned box, in metres."""
    pts = mesh.vertices
    hull = hull_points(pts)
    diameter = float(pdist(hull).max()) if len(hull) > 1 else 0.0
    if diameter <= 0:
        raise BopFormatError(f"object {obj_id}: mesh has no extent")
    return ObjectInfo(obj_id, diameter, pts.min(axis=0), np.ptp(pts, axis=0))


AXES = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0)}


def symmetry(spec: str) -> tuple[tuple[np.ndarray, ...], tuple[dict, ...]]:
    """models_info.json symmetries from a declaration about an axis of the mesh's own frame through its origin:
    "continuous-z" (a body of revolution about z), or "N-z" (N-fold: turns by 360°/N, e.g. "2-x" for a box that
    looks the same turned half-way about x). Returns (discrete 4 x 4 transforms, continuous entries)."""
    kind, _, axis = spec.partition("-")
    if axis not in AXES or not (kind == "continuous" or (kind.isdigit() and int(kind) >= 2)):
        raise BopFormatError(f"symmetry {spec!r}: expected continuous-AXIS or N-AXIS (N >= 2, AXIS x, y or z)")
    if kind == "continuous":
        return (), ({"axis": np.array(AXES[axis]), "offset": np.zeros(3)},)
    turns = []
    for k in range(1, int(kind)):
        T = np.eye(4)
        T[:3, :3] = Rotation.from_rotvec(np.array(AXES[axis]) * 2 * np.pi * k / int(kind)).as_matrix()
        turns.append(T)
    return tuple(turns), ()


def import_meshes(paths: list[str | Path], out_dir: str | Path, units: float = MM, first_id: int = 1,
                  symmetries: dict[str, str] | None = None) -> dict[int, Path]:  # fmt: skip
    """Write each mesh as obj_<id>.ply (ids from `first_id`, in the given order) plus models_info.json and the
    objects' names (from the file names, `object_name`; a repeated one gets its id appended) into out_dir.
    `symmetries`: an object's declared symmetry (`symmetry`) by its name, which makes the metrics and ADD-S
    treat the poses it cannot tell apart as one."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    infos, ids, names = {}, {}, {}
    for k, p in enumerate(paths):
        obj_id = first_id + k
        mesh = load_mesh(p, units)
        write_ply(model_path(out_dir, obj_id), mesh)
        infos[obj_id] = object_info(obj_id, mesh)
        ids[obj_id] = Path(p)
        name = object_name(Path(p).stem, obj_id)
        names[obj_id] = name if name not in names.values() else f"{name}_{obj_id}"
    unknown = sorted(set(symmetries or {}) - set(names.values()))
    if unknown:
        raise BopFormatError(f"symmetry declared for {unknown}, not among the imported objects {sorted(names.values())}")
    for obj_id, name in names.items():
        if name in (symmetries or {}):
            discrete, continuous = symmetry(symmetries[name])
            infos[obj_id] = replace(infos[obj_id], symmetries_discrete=discrete, symmetries_continuous=continuous)
    write_models_info(out_dir / "models_info.json", infos)
    (out_dir / NAMES_FILE).write_text(json.dumps({str(i): n for i, n in names.items()}, indent=2) + "\n")
    return ids
