"""Bring your own objects: PLY or OBJ meshes into a BOP models folder (obj_XXXXXX.ply + models_info.json).

Everything downstream (synthesis, metrics, training) then reads the folder like the LM-O models.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import plyfile
from scipy.spatial import ConvexHull
from scipy.spatial.distance import pdist

from axispose_core.data.bop import MM, BopFormatError, Mesh, ObjectInfo, load_ply, model_path, write_models_info
from axispose_core.data.objects import NAMES_FILE, object_name


def load_obj(path: str | Path, units: float = MM) -> Mesh:
    """Wavefront OBJ: `v x y z [r g b]` vertices (colours in [0,1]) and polygon faces, fan-triangulated."""
    path = Path(path)
    verts, cols, faces = [], [], []
    try:
        lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
    except OSError as err:
        raise BopFormatError(f"{path}: cannot read OBJ ({err})") from err
    for n, line in enumerate(lines, 1):
        parts = line.split()
        if not parts:
            continue
        try:
            if parts[0] == "v":
                if len(parts) < 4:
                    raise ValueError("a vertex needs x y z")
                verts.append([float(v) for v in parts[1:4]])
                if len(parts) >= 7:
                    cols.append([float(c) for c in parts[4:7]])
            elif parts[0] == "f":
                idx = [int(p.split("/")[0]) for p in parts[1:]]
                idx = [i - 1 if i > 0 else len(verts) + i for i in idx]
                faces += [(idx[0], idx[k], idx[k + 1]) for k in range(1, len(idx) - 1)]
        except (ValueError, IndexError) as err:
            raise BopFormatError(f"{path}:{n}: malformed '{parts[0]}' line") from err
    if not verts or not faces:
        raise BopFormatError(f"{path}: no vertices or faces")
    vertices = np.asarray(verts, dtype=np.float64) * units
    f = np.asarray(faces, dtype=np.int64)
    if f.min() < 0 or f.max() >= len(vertices):
        raise BopFormatError(f"{path}: face index out of range")
    colors = (np.clip(np.asarray(cols), 0, 1) * 255).astype(np.uint8) if len(cols) == len(verts) else None
    return Mesh(vertices, f, colors)


def load_mesh(path: str | Path, units: float = MM) -> Mesh:
    """A PLY or OBJ file by its suffix; `units` is metres per file unit."""
    suffix = Path(path).suffix.lower()
    if suffix == ".ply":
        return load_ply(path, units)
    if suffix == ".obj":
        return load_obj(path, units)
    raise BopFormatError(f"{path}: unsupported mesh format '{suffix}' (PLY or OBJ)")


def write_ply(path: str | Path, mesh: Mesh) -> None:
    """Binary PLY in millimetres (BOP's unit), with vertex colours when the mesh has them."""
    props = [("x", "f4"), ("y", "f4"), ("z", "f4")]
    if mesh.colors is not None:
        props += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    v = np.empty(len(mesh.vertices), dtype=props)
    for i, a in enumerate("xyz"):
        v[a] = mesh.vertices[:, i] / MM
    if mesh.colors is not None:
        for i, a in enumerate(("red", "green", "blue")):
            v[a] = mesh.colors[:, i]
    f = np.empty(len(mesh.faces), dtype=[("vertex_indices", "i4", (3,))])
    f["vertex_indices"] = mesh.faces
    plyfile.PlyData([plyfile.PlyElement.describe(v, "vertex"), plyfile.PlyElement.describe(f, "face")]).write(str(path))


def object_info(obj_id: int, mesh: Mesh) -> ObjectInfo:
    """Diameter (largest vertex distance, over the convex hull) and axis-aligned box, in metres."""
    pts = mesh.vertices
    hull = pts[ConvexHull(pts).vertices] if len(pts) >= 4 else pts
    diameter = float(pdist(hull).max()) if len(hull) > 1 else 0.0
    if diameter <= 0:
        raise BopFormatError(f"object {obj_id}: mesh has no extent")
    return ObjectInfo(obj_id, diameter, pts.min(axis=0), np.ptp(pts, axis=0))


def import_meshes(paths: list[str | Path], out_dir: str | Path, units: float = MM, first_id: int = 1) -> dict[int, Path]:
    """Write each mesh as obj_<id>.ply (ids from `first_id`, in the given order) plus models_info.json and the
    objects' names (from the file names, `object_name`; a repeated one gets its id appended) into out_dir."""
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
    write_models_info(out_dir / "models_info.json", infos)
    (out_dir / NAMES_FILE).write_text(json.dumps({str(i): n for i, n in names.items()}, indent=2) + "\n")
    return ids
