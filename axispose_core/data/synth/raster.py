"""A CPU z-buffer rasteriser for vertex-coloured meshes, in NumPy.

Coverage is exact: a triangle covers the pixels whose centres lie inside its projection, and a centre on an edge
two triangles share belongs to exactly one of them (a top-left rule), so silhouettes have the size the geometry
gives them, not half a pixel more. Depth and the interpolated attributes are perspective-correct, and any K
works (skew and off-centre principal points included). The nearest surface per pixel wins. One pass yields
colour, depth, the instance seen at each pixel (visible masks), the pixels each instance covers (full masks) and
the surface points. No OpenGL, no native state: nothing leaks across calls, and the output is bit-identical for
identical input.

Why not OpenGL: pyrender + OSMesa grew 3-15 MB per render here; pybullet's TinyRenderer ignores vertex colours.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

NEAR = 0.05
"""Triangles with a vertex closer than this (m) are dropped."""


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


@dataclass
class _Samples:
    """The pixels one posed mesh covers, one entry per (face, pixel): `pix` the flat pixel index, `depth` the
    surface's depth there; face and barycentric weights are looked up only for the pixels' winners."""

    pix: np.ndarray
    depth: np.ndarray
    faces: np.ndarray
    weights: np.ndarray

    def faces_and_weights(self, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Face index and perspective-correct barycentric weights (N,3) of the entries `idx`."""
        return self.faces[idx], self.weights[idx]


def _min3(a: np.ndarray) -> np.ndarray:
    return np.minimum(np.minimum(a[:, 0], a[:, 1]), a[:, 2])


def _max3(a: np.ndarray) -> np.ndarray:
    return np.maximum(np.maximum(a[:, 0], a[:, 1]), a[:, 2])


_CHUNK = 1 << 22
"""Candidate pixels tested at once (memory bound)."""


def _rasterize(mesh: RenderMesh, R: np.ndarray, t: np.ndarray, K: np.ndarray, width: int, height: int) -> _Samples | None:
    """Rasterise one posed mesh's front faces exactly: a face covers the pixels whose centres lie inside its
    projection; a centre on an edge or vertex that faces share goes to exactly one of them (a top-left rule).
    Depth and barycentric weights are perspective-correct, so the surface is exact at every covered pixel."""
    fx, skew, cx, fy, cy = (float(v) for v in (K[0, 0], K[0, 1], K[0, 2], K[1, 1], K[1, 2]))
    cam = np.asarray(mesh.vertices, np.float64) @ np.asarray(R, np.float64).T + np.asarray(t, np.float64)
    iz = 1.0 / np.maximum(cam[:, 2], 1e-9)
    uv = np.column_stack([(fx * cam[:, 0] + skew * cam[:, 1]) * iz + cx, fy * cam[:, 1] * iz + cy])
    f = mesh.faces
    u, v = uv[f, 0], uv[f, 1]
    # Twice the signed area in the image (u right, v down): negative for a face turned towards the camera (wound
    # counter-clockwise seen from outside), while all its vertices lie in front of the camera.
    area = (u[:, 1] - u[:, 0]) * (v[:, 2] - v[:, 0]) - (v[:, 1] - v[:, 0]) * (u[:, 2] - u[:, 0])
    x0 = np.maximum(np.ceil(_min3(u)), 0)
    x1 = np.minimum(np.floor(_max3(u)), width - 1)
    y0 = np.maximum(np.ceil(_min3(v)), 0)
    y1 = np.minimum(np.floor(_max3(v)), height - 1)
    keep = (area < 0) & (x1 >= x0) & (y1 >= y0)
    keep[keep] &= _min3(cam[f[keep], 2]) > NEAR
    face_ids = np.nonzero(keep)[0]
    if not len(face_ids):
        return None
    x0, y0 = x0[face_ids].astype(np.int64), y0[face_ids].astype(np.int64)
    bw, bh = x1[face_ids].astype(np.int64) - x0 + 1, y1[face_ids].astype(np.int64) - y0 + 1
    area = -area[face_ids]
    # Edge k runs from vertex a = k+1 to b = k+2, opposite vertex k: w = (v_b - v_a) u + (u_a - u_b) v + (u_b v_a -
    # u_a v_b), positive inside a face turned to the camera. The face on the other side of the edge runs it from b
    # to a and gets exactly -w (floating-point subtraction is antisymmetric and products commute), so a centre is
    # never inside both; one on the edge (w = 0) goes to the face for which the edge is "top-left", as if every
    # centre were nudged by (1, +0): exactly one face of a shared edge or vertex takes it.
    pts = uv[f[face_ids]]
    coef = np.empty((len(face_ids), 3, 3))
    top_left = np.empty((len(face_ids), 3), dtype=bool)
    for k in range(3):
        ua, va, ub, vb = pts[:, (k + 1) % 3, 0], pts[:, (k + 1) % 3, 1], pts[:, (k + 2) % 3, 0], pts[:, (k + 2) % 3, 1]
        coef[:, k, 0], coef[:, k, 1], coef[:, k, 2] = vb - va, ua - ub, ub * va - ua * vb
        top_left[:, k] = (va < vb) | ((va == vb) & (ua > ub))
    inv_z = 1.0 / cam[f[face_ids], 2]
    # Faces are tested in classes of box area up to 1, 2, 4, 8, ... pixels: candidate j of a face is the pixel
    # (j mod width, j div width) of its box, so each class is one set of array operations whatever the boxes' shapes.
    box = bw * bh
    area_class = np.ceil(np.log2(box)).astype(np.int64)
    pix_out, depth_out, face_out, w_out = [], [], [], []
    for cls in np.flatnonzero(np.bincount(area_class)):
        cap = 1 << int(cls)
        sel_all = np.flatnonzero(area_class == cls)
        j = np.arange(cap)
        step = max(1, _CHUNK // cap)
        for start in range(0, len(sel_all), step):
            sel = sel_all[start : start + step]
            dy, dx = np.divmod(j[None], bw[sel, None])
            px = x0[sel, None] + dx
            py = y0[sel, None] + dy
            inside = j[None] < box[sel, None]
            c, tl = coef[sel], top_left[sel]
            pxf, pyf = px.astype(np.float64), py.astype(np.float64)
            ws = []
            for k in range(3):
                w = c[:, k, 0:1] * pxf + c[:, k, 1:2] * pyf + c[:, k, 2:3]
                inside &= (w > 0) | ((w == 0) & tl[:, k : k + 1])
                ws.append(w)
            idx = np.flatnonzero(inside)
            if not len(idx):
                continue
            faces = sel[idx // cap]
            # Screen-space barycentrics (edge functions over twice the area), over depth: perspective-correct.
            lam = np.column_stack([w.ravel()[idx] for w in ws]) * (inv_z[faces] / area[faces, None])
            total = lam.sum(axis=1)
            pix_out.append(py.ravel()[idx] * width + px.ravel()[idx])
            depth_out.append((1.0 / total).astype(np.float32))
            face_out.append(face_ids[faces])
            w_out.append((lam / total[:, None]).astype(np.float32))
    if not pix_out:
        return None
    return _Samples(np.concatenate(pix_out), np.concatenate(depth_out), np.concatenate(face_out), np.concatenate(w_out))


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
    depth = _depth([_rasterize(mesh, R, t, K, width, height)], height * width)[:-1].reshape(height, width)
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
        samples = [_rasterize(m, R @ Rm, R @ (t - C), K, size, size) for m, Rm, t in meshes]
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
    samples = [_rasterize(m, R, t, K, width, height) for m, R, t in meshes]
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
