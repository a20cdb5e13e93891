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
    shadows: ShadowMap | None = None
    """With `render(..., shadows=True)`: the light's shadow map, for surfaces drawn apart (a table)."""


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


def _depth(samples: list[_Samples | None], n_pix: int) -> np.ndarray:
    """The nearest sample's depth per pixel (flat, one slot more for the samples outside the image; inf: none)."""
    depth = np.full(n_pix + 1, np.inf, dtype=np.float32)
    for smp in samples:
        if smp is not None:
            np.minimum.at(depth, smp.pix, smp.depth)
    depth[n_pix] = np.inf
    return depth


def render_depth(mesh: RenderMesh, R: np.ndarray, t: np.ndarray, K: np.ndarray, width: int, height: int) -> np.ndarray:
    """The depth (z, m) of one posed mesh per pixel, 0 where it is not (the BOP convention), without shading."""
    depth = _depth([_splat(mesh, R, t, K, width, height)], height * width)[:-1].reshape(height, width)
    return np.where(np.isfinite(depth), depth, 0.0).astype(np.float64)


def pixel_rays(K: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rays (..., 3) with z = 1 through pixels (u, v) (centres at integers), skew included."""
    y = (v - K[1, 2]) / K[1, 1]
    x = (u - K[0, 2] - K[0, 1] * y) / K[0, 0]
    return np.stack([x, y, np.ones_like(x)], axis=-1)


def backproject_pixels(K: np.ndarray, px: np.ndarray, depth: np.ndarray, width: int) -> np.ndarray:
    """Camera-frame points (N,3) at the flat pixel indices `px` and their depths (z)."""
    v, u = np.divmod(px, width)
    return pixel_rays(K, u, v) * depth[:, None]


SHADOW_DISTANCE = 100.0
"""How far (m) the shadow map's viewpoint stands back along the light: far enough that its rays are parallel to
within half a degree over a table top, so that it stands for a directional light."""
SHADOW_SIZE = 768
SHADOW_BIAS = 0.004
"""Depth (m) a point may lie behind the nearest surface the light sees and still count as lit (plus two texels'
worth), against self-shadowing from the samples' discretisation."""


@dataclass(frozen=True)
class ShadowMap:
    """Depth of the scene seen along a directional light: which camera-frame points it reaches."""

    R: np.ndarray
    """Camera frame -> light view rotation (its z axis along the light's direction)."""
    C: np.ndarray
    """The light view's centre, camera frame."""
    K: np.ndarray
    depth: np.ndarray
    """(SHADOW_SIZE + 2, SHADOW_SIZE + 2) nearest depth along the light (inf: nothing), a border of inf around it
    so that `lit` reads 3 x 3 texels at the edges too."""
    bias: float

    @classmethod
    def of(cls, meshes: list[tuple[RenderMesh, np.ndarray, np.ndarray]], direction: np.ndarray, size: int = SHADOW_SIZE) -> ShadowMap:
        """The shadow map of posed meshes under a light travelling along `direction` (camera frame)."""
        d = np.asarray(direction, np.float64) / np.linalg.norm(direction)
        helper = np.array([1.0, 0.0, 0.0]) if abs(d[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        x = np.cross(helper, d)
        x /= np.linalg.norm(x)
        R = np.stack([x, np.cross(d, x), d])
        radii = [float(np.linalg.norm(m.vertices, axis=1).max()) for m, _, _ in meshes]
        centres = np.array([t for _, _, t in meshes], np.float64).reshape(-1, 3)
        centre = centres.mean(axis=0) if len(centres) else np.zeros(3)
        lateral = (centres - centre) @ R[:2].T
        extent = max([float(np.linalg.norm(a)) + r for a, r in zip(lateral, radii, strict=True)] + [1e-3])
        C = centre - SHADOW_DISTANCE * d
        f = 0.5 * size * SHADOW_DISTANCE / (1.05 * extent)
        K = np.array([[f, 0.0, 0.5 * (size - 1)], [0.0, f, 0.5 * (size - 1)], [0.0, 0.0, 1.0]])
        samples = [_splat(m, R @ Rm, R @ (t - C), K, size, size) for m, Rm, t in meshes]
        depth = np.pad(_depth(samples, size * size)[:-1].reshape(size, size), 1, constant_values=np.inf)
        return cls(R, C, K, depth, SHADOW_BIAS + 2 * 1.05 * extent * 2 / size)

    def lit(self, points: np.ndarray) -> np.ndarray:
        """(N,) share in [0, 1] of the 3 x 3 texels about each camera-frame point from which the light reaches it
        (0: in shadow); points outside the map are lit."""
        p = (np.asarray(points, np.float64) - self.C) @ self.R.T
        n = self.depth.shape[0] - 2
        u = np.floor(self.K[0, 0] * p[:, 0] / p[:, 2] + self.K[0, 2] + 0.5).astype(np.int64)
        v = np.floor(self.K[1, 1] * p[:, 1] / p[:, 2] + self.K[1, 2] + 0.5).astype(np.int64)
        inside = (u >= 0) & (u < n) & (v >= 0) & (v < n)
        uc, vc = np.clip(u, 0, n - 1) + 1, np.clip(v, 0, n - 1) + 1
        reached = np.zeros(len(p))
        for dv in (-1, 0, 1):
            for du in (-1, 0, 1):
                reached += p[:, 2] <= self.depth[vc + dv, uc + du] + self.bias
        return np.where(inside, reached / 9.0, 1.0)


def render(
    meshes: list[tuple[RenderMesh, np.ndarray, np.ndarray]], K: np.ndarray, width: int, height: int, light: Light, shadows: bool = False
) -> RenderResult:
    """Render posed meshes [(mesh, R, t), ...] through K into a width x height image; with `shadows`, surfaces the
    light does not reach (`ShadowMap`) get its ambient part only, and the map comes back for other receivers."""
    n_pix = height * width
    samples = [_splat(m, R, t, K, width, height) for m, R, t in meshes]
    full = np.zeros((len(meshes), n_pix + 1), dtype=bool)
    for i, smp in enumerate(samples):
        if smp is not None:
            full[i, smp.pix] = True
    depth = _depth(samples, n_pix)
    shadow_map = ShadowMap.of(meshes, light.direction) if shadows and meshes else None
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
        if shadow_map is not None:
            lam = lam * shadow_map.lit(backproject_pixels(K, px, depth[px], width))
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
        shadow_map,
    )
