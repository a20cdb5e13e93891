"""Mesh files: the one module that reads them (PLY, OBJ) and writes them (PLY), and turns a BOP model into the
renderer's mesh. Lengths become metres here, as `data/bop.py` does for BOP's other files."""

from __future__ import annotations

import functools
import logging
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import plyfile

from axispose_core.data.bop import MM, BopFormatError
from axispose_core.data.bop_models import model_path
from axispose_core.data.synth.raster import RenderMesh, decimate, vertex_normals

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Mesh:
    """A triangle mesh in metres; colours are per-vertex RGB uint8 when the file has them."""

    vertices: np.ndarray
    faces: np.ndarray
    colors: np.ndarray | None = None
    normals: np.ndarray | None = None


def load_ply(path: str | Path, units: float = MM) -> Mesh:
    """Read an ASCII or binary PLY; `units` is metres per file unit (BOP models are in mm). A file read before in
    this process (same size and modification time) is not parsed again: an ASCII model takes about a second, and a
    run's stages (labels, crops, stream, validation) each load every model. The arrays are the caller's own copies."""
    path = Path(path)
    try:
        stat = path.stat()
    except OSError as err:
        raise BopFormatError(f"{path}: cannot read PLY ({err})") from err
    mesh = _parsed(str(path.resolve()), stat.st_size, stat.st_mtime_ns, units)
    return Mesh(*(None if a is None else a.copy() for a in (mesh.vertices, mesh.faces, mesh.colors, mesh.normals)))


@functools.lru_cache(maxsize=64)
def _parsed(path_name: str, size: int, mtime_ns: int, units: float) -> Mesh:
    """`load_ply`'s parse of one version of a file (the size and time key the version)."""
    path = Path(path_name)
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
    texture = next((c.split(None, 1)[1] for c in ply.comments if c.lower().startswith("texturefile") and len(c.split()) > 1), None)
    uv_names = next((uv for uv in (("texture_u", "texture_v"), ("s", "t"), ("u", "v")) if set(uv) <= set(names)), None)
    if texture is not None and faces.size:  # a textured PLY: UVs per vertex, or per face corner ("texcoord")
        material = _Material(texture=_read_texture(path.parent / texture.strip()))
        if uv_names is not None:
            corner_uv = np.column_stack([v[uv_names[0]], v[uv_names[1]]]).astype(np.float64)[faces]
        elif "texcoord" in (ply["face"].data.dtype.names or ()):
            corner_uv = np.asarray(np.stack(ply["face"].data["texcoord"]), dtype=np.float64).reshape(-1, 3, 2)
        else:
            raise BopFormatError(f"{path}: names a TextureFile but has no texture coordinates")
        return _textured_mesh(vertices, faces, corner_uv, np.zeros(len(faces), dtype=np.int64), [material], colors)
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


GREY = 0.6
"""The colour (in [0, 1]) of a mesh, or a part of one, that brings none of its own."""
TEXELS_PER_EDGE = 8.0
"""A textured face is split until none of its edges spans more texels than this, so the texture's detail survives
as vertex colours (what the renderer interpolates)."""
FACE_BUDGET = 200_000
"""Splitting stops before a mesh would have more faces than this."""


@dataclass
class _Material:
    kd: np.ndarray | None = None
    """Diffuse colour in [0, 1]."""
    texture: np.ndarray | None = None
    """Diffuse texture, H x W x 3 float RGB in [0, 1] (map_Kd, or a PLY's TextureFile)."""


def _read_texture(path: Path) -> np.ndarray:
    import cv2

    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise BopFormatError(f"{path}: unreadable texture image")
    image = image[..., None] if image.ndim == 2 else image
    image = np.repeat(image, 3, axis=2) if image.shape[2] == 1 else image[..., 2::-1]  # BGR(A) -> RGB
    return image.astype(np.float64) / (65535.0 if image.dtype == np.uint16 else 255.0)


def _sample(texture: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear texture colours at UVs (N, 2), v up, repeating outside [0, 1] as OBJ viewers do."""
    h, w = texture.shape[:2]
    x = np.mod(uv[:, 0], 1.0) * w - 0.5
    y = np.mod(1.0 - uv[:, 1], 1.0) * h - 0.5
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    c = [texture[np.mod(y0 + dy, h), np.mod(x0 + dx, w)] for dy in (0, 1) for dx in (0, 1)]
    return (c[0] * (1 - fx) + c[1] * fx) * (1 - fy) + (c[2] * (1 - fx) + c[3] * fx) * fy


def _textured_mesh(positions: np.ndarray, corner_v: np.ndarray, corner_uv: np.ndarray, face_mat: np.ndarray,
                   materials: list[_Material], vertex_colors: np.ndarray | None) -> Mesh:  # fmt: skip
    """A mesh whose colours come from materials: every distinct (vertex, UV, material) corner becomes a vertex of
    its own (UV seams and material borders keep their colours), textured faces are split down to
    TEXELS_PER_EDGE, and each vertex takes its texture's colour at its UV, else its material's Kd, else the file's
    vertex colour, else grey. `corner_uv` holds NaN where a corner has no UV; `face_mat` -1 for no material."""
    F = len(corner_v)
    mat = np.repeat(face_mat, 3)
    keys = np.column_stack([corner_v.ravel(), np.nan_to_num(corner_uv.reshape(-1, 2), nan=-1e9), mat])
    uniq, inverse = np.unique(keys, axis=0, return_inverse=True)
    src = uniq[:, 0].astype(int)
    pos = positions[src]
    uv = np.where(uniq[:, 1:3] < -1e8, np.nan, uniq[:, 1:3])
    vmat = uniq[:, 3].astype(int)
    faces = inverse.reshape(-1).reshape(F, 3).astype(np.int64)
    tex_size = np.array([max(m.texture.shape[:2]) if m.texture is not None else 0 for m in materials] + [0], dtype=float)
    while True:
        fm = vmat[faces[:, 0]]
        textured = (tex_size[fm] > 0) & ~np.isnan(uv[faces]).any(axis=(1, 2))
        span = np.max([np.abs(uv[faces[:, k]] - uv[faces[:, (k + 1) % 3]]).max(axis=1) for k in range(3)], axis=0)
        big = textured & (np.nan_to_num(span) * tex_size[fm] > TEXELS_PER_EDGE)
        if not big.any() or len(faces) + 3 * int(big.sum()) > FACE_BUDGET:
            break
        tri = faces[big]
        edges = np.sort(np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]]), axis=1)
        pairs, which = np.unique(edges, axis=0, return_inverse=True)
        mid = len(pos) + which.reshape(-1).reshape(3, -1)  # ab, bc, ca of each split face
        pos = np.concatenate([pos, 0.5 * (pos[pairs[:, 0]] + pos[pairs[:, 1]])])
        uv = np.concatenate([uv, 0.5 * (uv[pairs[:, 0]] + uv[pairs[:, 1]])])
        vmat, src = np.concatenate([vmat, vmat[pairs[:, 0]]]), np.concatenate([src, src[pairs[:, 0]]])
        a, b, c = tri.T
        ab, bc, ca = mid
        split = np.concatenate([np.stack(t, axis=1) for t in ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))])
        faces = np.concatenate([faces[~big], split])
    colors = np.full((len(pos), 3), GREY)
    if vertex_colors is not None:
        colors = vertex_colors[src].astype(np.float64) / 255.0
    for k, m in enumerate(materials):
        own = vmat == k
        if m.kd is not None:
            colors[own] = m.kd
        if m.texture is not None:
            hit = own & ~np.isnan(uv).any(axis=1)
            colors[hit] = _sample(m.texture, uv[hit])
    return Mesh(pos, faces, (np.clip(colors, 0, 1) * 255).round().astype(np.uint8))


def _statements(lines: list[str]) -> Iterator[tuple[int, list[str]]]:
    """(line number, words) of an OBJ or MTL file's non-blank lines."""
    for n, line in enumerate(lines, 1):
        if parts := line.split():
            yield n, parts


def _read_mtl(path: Path) -> dict[str, _Material]:
    """The materials of an MTL file by name: Kd and the map_Kd texture (relative to the MTL file)."""
    try:
        lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
    except OSError as err:  # as viewers do: the mesh without those materials
        log.warning("%s: cannot read the OBJ's material file (%s); its materials are left out", path, err)
        return {}
    out: dict[str, _Material] = {}
    current: _Material | None = None
    for n, parts in _statements(lines):
        try:
            if parts[0] == "newmtl":
                current = out.setdefault(" ".join(parts[1:]), _Material())
            elif parts[0] == "Kd" and current is not None:
                current.kd = np.clip([float(v) for v in parts[1:4]], 0, 1)
            elif parts[0] == "map_Kd" and current is not None:
                texture = path.parent / parts[-1]  # options (-s, -o ...) come before the name
                if texture.is_file():
                    current.texture = _read_texture(texture)
                else:
                    log.warning("%s:%d: texture %s not found; the material's Kd stands in", path, n, texture)
        except BopFormatError:
            raise
        except (ValueError, IndexError) as err:
            raise BopFormatError(f"{path}:{n}: malformed '{parts[0]}' line") from err
    return out


def load_obj(path: str | Path, units: float = MM) -> Mesh:
    """Wavefront OBJ: `v x y z [r g b]` vertices (colours in [0,1]), `vt` texture coordinates and polygon faces
    (fan-triangulated), coloured by their MTL materials (`mtllib`, `usemtl`: the map_Kd texture where a face has
    UVs, else Kd); without materials, by the vertex colours."""
    path = Path(path)
    verts, cols, uvs, corners, corner_uv, face_mat = [], [], [], [], [], []
    materials: dict[str, _Material] = {}
    order: list[str] = []
    current = -1
    try:
        lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
    except OSError as err:
        raise BopFormatError(f"{path}: cannot read OBJ ({err})") from err
    for n, parts in _statements(lines):
        try:
            if parts[0] == "v":
                if len(parts) < 4:
                    raise ValueError("a vertex needs x y z")
                verts.append([float(v) for v in parts[1:4]])
                if len(parts) >= 7:
                    cols.append([float(c) for c in parts[4:7]])
            elif parts[0] == "vt":
                uvs.append([float(parts[1]), float(parts[2]) if len(parts) > 2 else 0.0])
            elif parts[0] == "f":
                refs = [p.split("/") for p in parts[1:]]
                idx = [int(r[0]) for r in refs]
                idx = [i - 1 if i > 0 else len(verts) + i for i in idx]
                tex = [int(r[1]) if len(r) > 1 and r[1] else 0 for r in refs]
                tex = [t - 1 if t > 0 else (len(uvs) + t if t < 0 else -1) for t in tex]
                for k in range(1, len(idx) - 1):
                    corners.append((idx[0], idx[k], idx[k + 1]))
                    corner_uv.append((tex[0], tex[k], tex[k + 1]))
                    face_mat.append(current)
            elif parts[0] == "mtllib":
                for name in parts[1:]:  # none named: nothing to read
                    for mat_name, m in _read_mtl(path.parent / name).items():
                        materials[mat_name] = m
            elif parts[0] == "usemtl":
                name = " ".join(parts[1:])
                if name not in order:
                    order.append(name)
                current = order.index(name)
        except BopFormatError:
            raise
        except (ValueError, IndexError) as err:
            raise BopFormatError(f"{path}:{n}: malformed '{parts[0]}' line") from err
    if not verts or not corners:
        raise BopFormatError(f"{path}: no vertices or faces")
    vertices = np.asarray(verts, dtype=np.float64) * units
    f = np.asarray(corners, dtype=np.int64)
    t = np.asarray(corner_uv, dtype=np.int64)
    if f.min() < 0 or f.max() >= len(vertices) or t.max() >= len(uvs):
        raise BopFormatError(f"{path}: face index out of range")
    colors = (np.clip(np.asarray(cols), 0, 1) * 255).astype(np.uint8) if len(cols) == len(verts) else None
    used = [materials.get(name, _Material()) for name in order]
    if not any(m.kd is not None or m.texture is not None for m in used):
        return Mesh(vertices, f, colors)
    uv_table = np.concatenate([np.asarray(uvs, dtype=np.float64).reshape(-1, 2), np.full((1, 2), np.nan)])
    return _textured_mesh(vertices, f, uv_table[t], np.asarray(face_mat), used, colors)


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
    colors = mesh.colors / 255.0 if mesh.colors is not None else np.full((len(mesh.vertices), 3), GREY)
    normals = mesh.normals if mesh.normals is not None else vertex_normals(mesh.vertices, mesh.faces)
    normals = normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    rm = RenderMesh(mesh.vertices, mesh.faces, colors, normals)
    if cache is not None:
        cache.parent.mkdir(parents=True, exist_ok=True)
        tmp = cache.with_suffix(".tmp.npz")
        np.savez(tmp, vertices=rm.vertices, faces=rm.faces, colors=rm.colors, normals=rm.normals, stamp=stamp)
        tmp.replace(cache)
    return rm


REFINER_FACES = 25_000
"""Most faces a mesh the contour refiner carries keeps: a silhouette within a fraction of a pixel, and eight objects
add about 1.5 MB to a checkpoint."""


def refiner_meshes(models_dir: str | Path, obj_ids: Iterable[int]) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """The objects' meshes for the refiner from a BOP models folder: BOP's decimated `models_eval` beside it where
    there is one, else the models themselves; a mesh with more than REFINER_FACES faces is decimated (vertex
    clustering, finer cells until it fits)."""
    models_dir = Path(models_dir)
    eval_dir = models_dir.parent / "models_eval"
    out = {}
    for obj_id in obj_ids:
        src = model_path(eval_dir, obj_id) if model_path(eval_dir, obj_id).exists() else model_path(models_dir, obj_id)
        mesh = load_ply(src)
        v, f = mesh.vertices, mesh.faces
        if len(f) > REFINER_FACES:
            extent = float(np.ptp(v, axis=0).max())
            cell = extent / 400
            render = RenderMesh(v, f, np.zeros_like(v), np.zeros_like(v))
            while len(f) > REFINER_FACES:
                small = decimate(render, cell)
                v, f = small.vertices, small.faces
                cell *= 1.5
            log.info("object %d: %s decimated to %d faces for the refiner", obj_id, src, len(f))
        out[obj_id] = (v, f)
    return out
