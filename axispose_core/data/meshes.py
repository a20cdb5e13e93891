"""Mesh files: the one module that reads them (PLY, OBJ) and writes them (PLY), and turns a BOP model into the
renderer's mesh. Lengths become metres here, as `data/bop.py` does for BOP's other files."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import plyfile

from axispose_core.data.bop import MM, BopFormatError, model_path
from axispose_core.data.synth.raster import RenderMesh, vertex_normals


@dataclass(frozen=True)
class Mesh:
    """A triangle mesh in metres; colours are per-vertex RGB uint8 when the file has them."""

    vertices: np.ndarray
    faces: np.ndarray
    colors: np.ndarray | None = None
    normals: np.ndarray | None = None


def load_ply(path: str | Path, units: float = MM) -> Mesh:
    """Read an ASCII or binary PLY; `units` is metres per file unit (BOP models are in mm)."""
    path = Path(path)
    try:
        ply = plyfile.PlyData.read(str(path))
    except (OSError, plyfile.PlyParseError, ValueError) as err:
        raise BopFormatError(f"{path}: cannot read PLY ({err})") from err
    try:
        v = ply["vertex"].data
        vertices = np.column_stack([v["x"], v["y"], v["z"]]).astype(np.float64) * units
    except (KeyError, ValueError) as err:
        raise BopFormatError(f"{path}: PLY needs a 'vertex' element with x, y, z ({err})") from err
    names = v.dtype.names or ()
    colors = np.column_stack([v["red"], v["green"], v["blue"]]).astype(np.uint8) if "red" in names else None
    normals = np.column_stack([v["nx"], v["ny"], v["nz"]]).astype(np.float64) if "nx" in names else None
    faces = np.zeros((0, 3), dtype=np.int64)
    if "face" in ply:
        idx = ply["face"].data.dtype.names[0]
        polys = ply["face"].data[idx]
        if len(polys) and any(len(p) != 3 for p in polys):
            raise BopFormatError(f"{path}: only triangle faces are supported")
        faces = np.asarray(np.stack(polys) if len(polys) else faces, dtype=np.int64)
    if not np.all(np.isfinite(vertices)) or (faces.size and (faces.min() < 0 or faces.max() >= len(vertices))):
        raise BopFormatError(f"{path}: non-finite vertices or face indices out of range")
    return Mesh(vertices, faces, colors, normals)


def ply_vertex_properties(path: str | Path) -> tuple[str, ...]:
    """The vertex properties a PLY header declares (x, y, z, red, ...), read without parsing the body."""
    names, in_vertex = [], False
    try:
        with open(path, "rb") as f:
            for raw in f:
                words = raw.decode("ascii", "replace").split()
                if not words or words[0] == "end_header":
                    if words:
                        break
                    continue
                if words[0] == "element":
                    in_vertex = len(words) > 1 and words[1] == "vertex"
                elif words[0] == "property" and in_vertex:
                    names.append(words[-1])
    except OSError as err:
        raise BopFormatError(f"{path}: cannot read PLY ({err})") from err
    return tuple(names)


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


def load_render_mesh(models_dir: str | Path, obj_id: int, cache_dir: str | Path | None = None) -> RenderMesh:
    """A BOP model as a RenderMesh (metres, colours in [0,1]); cached as .npz because ASCII PLY parsing is slow."""
    src = model_path(models_dir, obj_id)
    cache = Path(cache_dir) / f"{src.stem}.npz" if cache_dir else None
    stamp = np.array([src.stat().st_size, src.stat().st_mtime_ns], dtype=np.int64)
    if cache is not None and cache.exists():
        data = np.load(cache)
        if np.array_equal(data["stamp"], stamp):
            return RenderMesh(data["vertices"], data["faces"], data["colors"], data["normals"])
    mesh = load_ply(src)
    colors = mesh.colors / 255.0 if mesh.colors is not None else np.full((len(mesh.vertices), 3), 0.6)
    normals = mesh.normals if mesh.normals is not None else vertex_normals(mesh.vertices, mesh.faces)
    normals = normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    rm = RenderMesh(mesh.vertices, mesh.faces, colors, normals)
    if cache is not None:
        cache.parent.mkdir(parents=True, exist_ok=True)
        tmp = cache.with_suffix(".tmp.npz")
        np.savez(tmp, vertices=rm.vertices, faces=rm.faces, colors=rm.colors, normals=rm.normals, stamp=stamp)
        tmp.replace(cache)
    return rm
