"""A CPU z-buffer renderer for vertex-coloured meshes by dense surface splatting, in NumPy.

Each front-facing triangle is sampled on a barycentric lattice fine enough (`SPACING` px between projected
samples) that every pixel it covers receives a sample; each sample is placed in 3D and projected, so depth is
exact and any K works (skew and off-centre principal points included). A sort on (pixel, depth) keeps the
nearest sample per pixel. One pass yields colour, depth, the instance seen at each pixel (visible masks) and
the pixels each instance covers (full masks). No OpenGL, no native state: nothing leaks across calls, and the
output is bit-identical for identical input.

Why not OpenGL: pyrender + OSMesa grew 3-15 MB per render here; pybullet's TinyRenderer ignores vertex colours.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

SPACING = 0.75
"""Largest distance (px) between neighbouring samples of a triangle's projection."""
NEAR = 0.05
"""Triangles with a vertex closer than this (m) are dropped."""
MAX_SUBDIV = 512


@dataclass(frozen=True)
class RenderMesh:
    """Geometry in model units of metres; colours float RGB in [0,1] per vertex; faces wound counter-clockwise outward."""

    vertices: np.ndarray
    faces: np.ndarray
    colors: np.ndarray
    normals: np.ndarray


@dataclass(frozen=True)
class Light:
    """A directional light (camera frame, pointing from the light towards the scene) plus ambient, and a
    Blinn-Phong highlight of strength `specular` (0: matte) and exponent `shininess`."""

    direction: np.ndarray
    color: np.ndarray
    ambient: float
    specular: float = 0.0
    shininess: float = 16.0


@dataclass
class RenderResult:
    """rgb float (H,W,3) in [0,1] (NaN-free; background pixels 0), depth (H,W) in m (inf on background),
    instance (H,W) int index of the visible instance (-1 background), full (N,H,W) bool coverage per instance,
    points (H,W,3) float32: the visible surface point in its own model's frame (m; 0 on background), the dense
    correspondences a pose network can be taught with."""

    rgb: np.ndarray
    depth: np.ndarray
    instance: np.ndarray
    full: np.ndarray
    points: np.ndarray


def decimate(mesh: RenderMesh, cell: float) -> RenderMesh:
    """Vertex clustering on a grid of `cell` metres: each occupied cell becomes one vertex, the one of its vertices
    nearest their mean (a mean would pull convex surfaces in and shrink silhouettes), with their mean colour and
    normal; faces that collapse are dropped, duplicates kept once. A cell of a pixel or two leaves the picture as
    it was while the per-face work of `render` shrinks with the face count."""
    if not cell > 0:
        raise ValueError(f"decimation cell must be positive, got {cell}")
    key = np.floor((mesh.vertices - mesh.vertices.min(axis=0)) / cell).astype(np.int64)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()

    def mean(values: np.ndarray) -> np.ndarray:
        out = np.zeros((len(counts), values.shape[1]))
        np.add.at(out, inverse, values)
        return out / counts[:, None]

    normals = mean(mesh.normals)
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    gap = np.linalg.norm(mesh.vertices - mean(mesh.vertices)[inverse], axis=1)
    order = np.lexsort((gap, inverse))
    nearest = order[np.r_[0, np.flatnonzero(np.diff(inverse[order])) + 1]]
    faces = inverse[mesh.faces]
    faces = faces[(faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])]
    _, first = np.unique(np.sort(faces, axis=1), axis=0, return_index=True)
    return RenderMesh(mesh.vertices[nearest], faces[np.sort(first)], mean(mesh.colors), normals)


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals of a triangle mesh."""
    v = vertices[faces]
    fn = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    n = np.zeros_like(vertices)
    for k in range(3):
        np.add.at(n, faces[:, k], fn)
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)


_LATTICES: dict[int, np.ndarray] = {}


def _lattice(k: int) -> np.ndarray:
    """Barycentric weights (P,3) of the points i/k, j/k with i + j <= k."""
    if k not in _LATTICES:
        i, j = np.meshgrid(np.arange(k + 1), np.arange(k + 1), indexing="ij")
        keep = (i + j) <= k
        a, b = i[keep] / k, j[keep] / k
        _LATTICES[k] = np.column_stack([1.0 - a - b, a, b])
    return _LATTICES[k]


@dataclass
class _Samples:
    """Samples of one posed mesh. `pix` is the flat pixel index (H*W for samples outside the image). Face and
    barycentric weights are kept per group, not per sample, and looked up only for the winners."""

    pix: np.ndarray
    depth: np.ndarray
    offsets: np.ndarray
    groups: list[tuple[np.ndarray, np.ndarray, bool]]
    """(faces, weights, per_sample): per sample, or faces x lattice with the lattice repeated per face."""
    _tables: tuple[np.ndarray, ...] | None = None

    def faces_and_weights(self, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Face index and barycentric weights (N,3) of the samples `idx`, every group at once."""
        if self._tables is None:
            faces = [f for f, _, _ in self.groups]
            weights = [w for _, w, _ in self.groups]
            self._tables = (
                np.concatenate(faces),
                np.concatenate(weights).astype(np.float32),
                np.cumsum([0] + [len(f) for f in faces[:-1]]),
                np.cumsum([0] + [len(w) for w in weights[:-1]]),
                np.array([1 if per_sample else len(w) for _, w, per_sample in self.groups]),
                np.array([per_sample for _, _, per_sample in self.groups]),
            )
        faces, weights, face_start, weight_start, lattice, per_sample = self._tables
        g = np.searchsorted(self.offsets, idx, side="right") - 1
        local = idx - self.offsets[g]
        # Per-sample groups index both tables by the sample; lattice groups by face x lattice point.
        face = faces[face_start[g] + local // lattice[g]]
        w = weights[weight_start[g] + np.where(per_sample[g], local, local % lattice[g])]
        return face, w


def _min3(a: np.ndarray) -> np.ndarray:
    return np.minimum(np.minimum(a[:, 0], a[:, 1]), a[:, 2])


def _max3(a: np.ndarray) -> np.ndarray:
    return np.maximum(np.maximum(a[:, 0], a[:, 1]), a[:, 2])


def _splat(mesh: RenderMesh, R: np.ndarray, t: np.ndarray, K: np.ndarray, width: int, height: int) -> _Samples | None:
    """Sample one posed mesh's front faces densely; positions are float32 (sub-micrometre at these depths)."""
    fx, skew, cx, fy, cy = (np.float32(v) for v in (K[0, 0], K[0, 1], K[0, 2], K[1, 1], K[1, 2]))
    cam = (mesh.vertices @ R.T + t).astype(np.float32)
    iz = 1.0 / np.maximum(cam[:, 2], 1e-9)
    u_v = (fx * cam[:, 0] + skew * cam[:, 1]) * iz + cx
    v_v = fy * cam[:, 1] * iz + cy
    f = mesh.faces
    tri = cam[f]
    u, v = u_v[f], v_v[f]
    face_n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    keep = (np.einsum("ij,ij->i", face_n, tri[:, 0]) < 0) & (_min3(tri[:, :, 2]) > NEAR)
    keep &= (_max3(u) >= -1) & (_min3(u) <= width) & (_max3(v) >= -1) & (_min3(v) <= height)
    face_ids = np.nonzero(keep)[0]
    if not len(face_ids):
        return None
    tri, u, v = tri[face_ids], u[face_ids], v[face_ids]
    du, dv = u - np.roll(u, 1, axis=1), v - np.roll(v, 1, axis=1)
    edge = np.sqrt(_max3(du * du + dv * dv))
    subdiv = np.clip(np.ceil(edge / SPACING), 1, MAX_SUBDIV).astype(np.int64)
    points, groups, offsets, n = [], [], [], 0
    for k in np.unique(subdiv):
        sel = np.nonzero(subdiv == k)[0]
        if k == 1:
            # Triangles smaller than the spacing: their vertices alone sample them, each shared vertex once.
            _, first = np.unique(f[face_ids[sel]].ravel(), return_index=True)
            points.append(tri[sel].reshape(-1, 3)[first])
            groups.append((face_ids[sel][first // 3], np.eye(3, dtype=np.float32)[first % 3], True))
        else:
            lattice = _lattice(int(k)).astype(np.float32)
            points.append(np.matmul(lattice[None], tri[sel]).reshape(-1, 3))
            groups.append((face_ids[sel], lattice, False))
        offsets.append(n)
        n += len(points[-1])
    p = np.concatenate(points)
    iz = 1.0 / p[:, 2]
    pu = np.floor((fx * p[:, 0] + skew * p[:, 1]) * iz + cx + 0.5).astype(np.int64)
    pv = np.floor(fy * p[:, 1] * iz + cy + 0.5).astype(np.int64)
    pix = pv * width + pu
    pix[(pu < 0) | (pu >= width) | (pv < 0) | (pv >= height)] = width * height
    return _Samples(pix, p[:, 2], np.asarray(offsets), groups)


def _highlight(light: Light, nor: np.ndarray, px: np.ndarray, K: np.ndarray, width: int) -> np.ndarray:
    """Blinn-Phong specular intensity at the pixels `px` (flat indices) with unit normals `nor` (camera frame),
    all facing the light."""
    v, u = np.divmod(px, width)
    y = ((v - K[1, 2]) / K[1, 1]).astype(np.float32)
    x = ((u - K[0, 2]) / K[0, 0]).astype(np.float32) - np.float32(K[0, 1] / K[0, 0]) * y
    inv = 1.0 / np.sqrt(x * x + y * y + 1.0)  # unit ray towards the surface: (x, y, 1) * inv
    d = light.direction.astype(np.float32)
    hx, hy, hz = -d[0] - x * inv, -d[1] - y * inv, -d[2] - inv  # to the light + to the eye
    nor = nor.astype(np.float32)
    cos = (nor[:, 0] * hx + nor[:, 1] * hy + nor[:, 2] * hz) / np.maximum(np.sqrt(hx * hx + hy * hy + hz * hz), 1e-12)
    return light.specular * np.clip(cos, 0.0, 1.0) ** np.float32(light.shininess)


def render(meshes: list[tuple[RenderMesh, np.ndarray, np.ndarray]], K: np.ndarray, width: int, height: int, light: Light) -> RenderResult:
    """Render posed meshes [(mesh, R, t), ...] through K into a width x height image."""
    n_pix = height * width
    samples = [_splat(m, R, t, K, width, height) for m, R, t in meshes]
    full = np.zeros((len(meshes), n_pix + 1), dtype=bool)
    depth = np.full(n_pix + 1, np.inf, dtype=np.float32)
    for i, smp in enumerate(samples):
        if smp is not None:
            full[i, smp.pix] = True
            np.minimum.at(depth, smp.pix, smp.depth)
    depth[n_pix] = np.inf
    # The nearest sample owns each pixel; on exact depth ties the later instance, then the later sample, wins.
    owner_mesh = np.full(n_pix + 1, -1, dtype=np.int32)
    owner_idx = np.full(n_pix + 1, -1, dtype=np.int64)
    for i, smp in enumerate(samples):
        if smp is not None:
            nearest = np.nonzero(smp.depth == depth[smp.pix])[0]
            owner_mesh[smp.pix[nearest]] = i
            owner_idx[smp.pix[nearest]] = nearest
    owner_mesh[n_pix] = -1
    rgb = np.zeros((n_pix + 1, 3), dtype=np.float32)
    points = np.zeros((n_pix + 1, 3), dtype=np.float32)
    lit: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []  # (pixels, normals, Lambert) for the highlights
    for i, (mesh, R, _) in enumerate(meshes):
        px = np.nonzero(owner_mesh == i)[0]
        if not len(px):
            continue
        face, w = samples[i].faces_and_weights(owner_idx[px])
        fv = mesh.faces[face]
        col = np.einsum("nk,nkc->nc", w, mesh.colors[fv])
        points[px] = np.einsum("nk,nkc->nc", w, mesh.vertices[fv])
        nor = np.einsum("nk,nkc->nc", w, mesh.normals[fv]) @ R.T
        nor /= np.maximum(np.linalg.norm(nor, axis=1, keepdims=True), 1e-12)
        lam = np.clip(-(nor @ light.direction), 0.0, 1.0)
        shade = (light.ambient + (1.0 - light.ambient) * lam)[:, None] * light.color[None, :]
        rgb[px] = np.clip(col * shade, 0.0, 1.0)
        lit.append((px, nor, lam))
    if light.specular > 0 and lit:
        px, nor, lam = (np.concatenate(a) for a in zip(*lit, strict=True))
        px, nor = px[lam > 0], nor[lam > 0]  # surfaces turned from the light get no highlight
        rgb[px] = np.clip(rgb[px] + _highlight(light, nor, px, K, width)[:, None] * light.color[None, :], 0.0, 1.0)
    return RenderResult(
        rgb[:n_pix].reshape(height, width, 3),
        depth[:n_pix].reshape(height, width),
        owner_mesh[:n_pix].reshape(height, width),
        full[:, :n_pix].reshape(-1, height, width),
        points[:n_pix].reshape(height, width, 3),
    )
