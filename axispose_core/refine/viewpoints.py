"""The sparse viewpoint model: an object's silhouette contour seen from views all around it, precomputed so that
refinement never renders (ICG's region model, Stoiber et al. 2022).

For each view on a geodesic sphere the mesh's silhouette is filled, its contours traced and `points` places spread
evenly along them; each place is snapped onto the nearest projected silhouette edge of the mesh, so the stored 3D
point lies on the object's contour generator to a fraction of a pixel (not half a pixel inside it, where a traced
mask's pixel centres lie). Per point: the model point, its outward contour normal (a 3D direction in the view's
image plane), and how far the silhouette stays foreground inwards and background outwards along that normal
(metres at the point's depth), which limits the lines a refiner draws through it.
"""

from __future__ import annotations

import functools
import hashlib
import inspect
import logging
import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial import cKDTree

log = logging.getLogger(__name__)

MARGIN = 0.08
"""Fraction of the view image left empty on each side around the object's bounding sphere."""
FAR = 1e3
"""A distance (m) standing for 'the background never ends' (a contour facing away from the rest of the object)."""


@dataclass(frozen=True)
class ViewpointSettings:
    """How the viewpoint model is made: more views follow a rotating object more closely, more points give the
    refiner more lines."""

    divides: int = 3
    """Geodesic subdivisions of an icosahedron: 10·4^n + 2 views (3: 642, about 8° apart)."""
    points: int = 200
    """Contour points per view."""
    image_size: int = 256
    """Side of the square view image the silhouette is traced in (px); the points are snapped onto the mesh's own
    silhouette edges, so this sets how finely the contour is found, not how exactly its points lie."""
    distance: float = 0.8
    """Distance of the views' camera from the object's origin (m), within LM-O's range of object distances."""

    def __post_init__(self) -> None:
        if not 0 <= self.divides <= 5:
            raise ValueError(f"viewpoints.divides must be 0-5, got {self.divides}")
        if self.points < 8 or self.image_size < 64 or not self.distance > 0:
            raise ValueError(f"viewpoints need points >= 8, image_size >= 64 and distance > 0, got {self}")


@dataclass(frozen=True)
class ViewpointModel:
    """Per view v (V views, N points each): `directions` (V,3), the unit vector from the camera to the object's
    origin in the model frame; `points` (V,N,3) on the contour (m, model frame); `normals` (V,N,3), outward, unit;
    `inside`, `outside` (V,N): how far along the normal the silhouette stays foreground / background (m, FAR for
    unbounded); `outline` (V,N) bool: the point lies on the view's largest contour (points are stored in contour
    order, so these trace its polygon)."""

    directions: np.ndarray
    points: np.ndarray
    normals: np.ndarray
    inside: np.ndarray
    outside: np.ndarray
    outline: np.ndarray

    def closest_view(self, R: np.ndarray, t: np.ndarray) -> int:
        """The view whose direction is nearest the camera's at pose (R, t) (camera from model)."""
        d = np.asarray(R).T @ np.asarray(t)
        n = float(np.linalg.norm(d))
        return 0 if n == 0 else int(np.argmax(self.directions @ (d / n)))

    def arrays(self) -> dict[str, np.ndarray]:
        return {k: getattr(self, k) for k in ("directions", "points", "normals", "inside", "outside", "outline")}


def geodesic_directions(divides: int) -> np.ndarray:
    """Unit vectors (10·4^n + 2, 3) on an icosahedron subdivided `divides` times: near-uniform over the sphere."""
    g = (1 + 5**0.5) / 2
    verts = [(-1, g, 0), (1, g, 0), (-1, -g, 0), (1, -g, 0), (0, -1, g), (0, 1, g), (0, -1, -g), (0, 1, -g), (g, 0, -1), (g, 0, 1),
             (-g, 0, -1), (-g, 0, 1)]  # fmt: skip
    faces = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4), (11, 10, 2), (10, 7, 6), (7, 1, 8),
             (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8), (3, 8, 9), (4, 9, 5), (2, 4, 11), (6, 2, 10), (8, 6, 7), (9, 8, 1)]  # fmt: skip
    v = [np.array(p, dtype=np.float64) / np.linalg.norm(p) for p in verts]
    for _ in range(divides):
        mids: dict[tuple[int, int], int] = {}
        split = []
        for a, b, c in faces:
            ab, bc, ca = (_midpoint(v, mids, i, j) for i, j in ((a, b), (b, c), (c, a)))
            split += [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]
        faces = split
    return np.stack(v)


def _midpoint(v: list[np.ndarray], mids: dict[tuple[int, int], int], a: int, b: int) -> int:
    """The index of the unit vector halfway between v[a] and v[b], appended to `v` the first time it is asked for."""
    key = (min(a, b), max(a, b))
    if key not in mids:
        m = v[a] + v[b]
        v.append(m / np.linalg.norm(m))
        mids[key] = len(v) - 1
    return mids[key]


def view_rotation(direction: np.ndarray) -> np.ndarray:
    """A camera-from-model rotation whose optical axis (its z) runs along `direction`."""
    z = direction / np.linalg.norm(direction)
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z])


@dataclass(frozen=True)
class _Edges:
    """A mesh's unique edges: their vertices (E,2), the two faces they join (E,2; an edge of one face names it
    twice) and whether they have only one face (E,)."""

    vertices: np.ndarray
    faces: np.ndarray
    single: np.ndarray

    @classmethod
    def of(cls, faces: np.ndarray) -> _Edges:
        pairs = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
        owner = np.tile(np.arange(len(faces)), 3)
        uniq, inverse = np.unique(pairs, axis=0, return_inverse=True)
        inverse = inverse.reshape(-1)
        order = np.argsort(inverse, kind="stable")
        starts = np.searchsorted(inverse[order], np.arange(len(uniq)))
        count = np.bincount(inverse, minlength=len(uniq))
        first = owner[order[starts]]
        second = np.where(count >= 2, owner[order[np.minimum(starts + 1, len(order) - 1)]], first)
        return cls(uniq, np.stack([first, second], axis=1), count < 2)


def build_viewpoint_model(vertices: np.ndarray, faces: np.ndarray, settings: ViewpointSettings) -> ViewpointModel:
    """The viewpoint model of a mesh (vertices (M,3) in metres, model frame; faces (F,3))."""
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    radius = float(np.linalg.norm(vertices, axis=1).max())
    if not radius > 0 or radius >= settings.distance:
        raise ValueError(f"a mesh of radius {radius:.3f} m does not fit views at {settings.distance} m")
    size = settings.image_size
    # The bounding sphere's image fills the view but the margin.
    half_angle = np.arcsin(radius / settings.distance)
    f = (0.5 - MARGIN) * size / np.tan(half_angle)
    K = np.array([[f, 0, (size - 1) / 2], [0, f, (size - 1) / 2], [0, 0, 1.0]])
    edges = _Edges.of(faces)
    directions = geodesic_directions(settings.divides)
    views = [_view(vertices, faces, edges, view_rotation(d), K, settings) for d in directions]
    return ViewpointModel(directions, *(np.stack([v[k] for v in views]) for k in range(5)))


def _view(
    vertices: np.ndarray, faces: np.ndarray, edges: _Edges, R: np.ndarray, K: np.ndarray, settings: ViewpointSettings
) -> tuple[np.ndarray, ...]:
    """One view's points, normals, inside and outside distances and outline flags (model frame)."""
    size, n = settings.image_size, settings.points
    t = np.array([0.0, 0.0, settings.distance])
    cam = vertices @ R.T + t
    uv = cam[:, :2] / cam[:, 2:3] * K[0, 0] + K[:2, 2]
    # The outline of a closed mesh's image is made of its silhouette edges (an edge between a face turned to the
    # camera and one turned away, or on an open border): drawn, with the outside flooded from the image's corner,
    # they leave the silhouette.
    u, v = uv[faces, 0], uv[faces, 1]
    facing = ((u[:, 1] - u[:, 0]) * (v[:, 2] - v[:, 0]) - (v[:, 1] - v[:, 0]) * (u[:, 2] - u[:, 0]) < 0)[edges.faces]
    rim = edges.vertices[edges.single | (facing[:, 0] != facing[:, 1])]
    shift = 4
    mask = np.zeros((size + 2, size + 2), dtype=np.uint8)
    cv2.polylines(mask[1:-1, 1:-1], np.round(uv[rim] * (1 << shift)).astype(np.int32), False, 1, lineType=cv2.LINE_8, shift=shift)
    outside = np.zeros((size + 4, size + 4), dtype=np.uint8)
    cv2.floodFill(mask, outside, (0, 0), 2)
    mask = (mask[1:-1, 1:-1] != 2).astype(np.uint8)
    contours, _ = cv2.findContours(mask, cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
    contours = sorted((c[:, 0, :] for c in contours if len(c) >= 15), key=len, reverse=True)
    # Places along every contour, evenly by length, in contour order; normals from the contour a few pixels on
    # either side, outward.
    lengths = np.array([len(c) for c in contours])
    place = (np.arange(n) + 0.5) * lengths.sum() / n
    which = np.searchsorted(np.cumsum(lengths), place, side="right")
    at = np.floor(place - np.concatenate([[0], np.cumsum(lengths)])[which]).astype(int)
    chain = np.concatenate(contours).astype(np.float64)
    start = np.concatenate([[0], np.cumsum(lengths)[:-1]])[which]
    radius = max(3, size // 128)
    pix = chain[start + at]
    tangent = chain[start + (at + radius) % lengths[which]] - chain[start + (at - radius) % lengths[which]]
    normal = np.stack([-tangent[:, 1], tangent[:, 0]], axis=1)
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
    probe = np.clip(np.round(pix + 2.5 * normal).astype(int), 0, size - 1)
    normal[mask[probe[:, 1], probe[:, 0]] > 0] *= -1
    # Snap each place onto the nearest silhouette edge on the outline (edges of folds inside it are left out): the
    # nearest of points every half pixel along them, then the foot of the perpendicular on that point's edge.
    near = np.zeros_like(mask)
    cv2.drawContours(near, contours, -1, 1, thickness=5)
    p0, p1 = uv[rim[:, 0]], uv[rim[:, 1]]
    mid = np.clip(np.round((p0 + p1) / 2).astype(int), 0, size - 1)
    on_outline = near[mid[:, 1], mid[:, 0]] > 0
    rim, p0, p1 = rim[on_outline], p0[on_outline], p1[on_outline]
    seg = p1 - p0
    steps = np.maximum(1, np.ceil(np.linalg.norm(seg, axis=1) * 2).astype(int))
    edge_of = np.repeat(np.arange(len(rim)), steps + 1)
    first = np.concatenate([[0], np.cumsum(steps + 1)[:-1]])
    frac = (np.arange(len(edge_of)) - first[edge_of]) / steps[edge_of]
    _, nearest = cKDTree(p0[edge_of] + frac[:, None] * seg[edge_of]).query(pix)
    e = edge_of[nearest]
    s = np.clip(np.einsum("ni,ni->n", pix - p0[e], seg[e]) / np.maximum(np.einsum("ni,ni->n", seg[e], seg[e]), 1e-12), 0, 1)
    # Perspective-correct: the point at image fraction s of the edge lies at depth-weighted fraction w along it.
    z0, z1 = cam[rim[e, 0], 2], cam[rim[e, 1], 2]
    w = s * z0 / (s * z0 + (1 - s) * z1)
    points = (1 - w)[:, None] * vertices[rim[e, 0]] + w[:, None] * vertices[rim[e, 1]]
    depth = (points @ R.T + t)[:, 2]
    inside, outside = _run_lengths(mask, p0[e] + s[:, None] * seg[e], normal)
    metres = depth / K[0, 0]
    normals = np.column_stack([normal, np.zeros(n)]) @ R  # image-plane direction, into the model frame
    inside, outside = (np.where(np.isfinite(d), d * metres, FAR) for d in (inside, outside))
    return points, normals, inside, outside, which == 0


def _run_lengths(mask: np.ndarray, at: np.ndarray, normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """How far (px) from the contour places `at` (N,2) the mask stays 1 inwards and 0 outwards along `normal`, up
    to a quarter of the image (inf beyond, or where the image ends first)."""
    size = mask.shape[0]
    steps = np.arange(1, size // 4 + 1, dtype=np.float64)

    def run(sign: float, value: int) -> np.ndarray:
        q = np.round(at[:, None, :] + sign * steps[None, :, None] * normal[:, None, :]).astype(int)
        off = (q < 0).any(axis=2) | (q >= size).any(axis=2)
        q = np.clip(q, 0, size - 1)
        hit = (mask[q[..., 1], q[..., 0]] != value) & ~off
        return np.where(hit.any(axis=1), steps[np.argmax(hit, axis=1)], np.inf)

    return run(-1.0, 1), run(1.0, 0)


@functools.cache
def builder_digest() -> str:
    """A digest of the code that builds viewpoint models: a model cached by other code (an earlier version of this
    module) is never taken for this code's."""
    h = hashlib.sha256()
    for part in (geodesic_directions, _midpoint, view_rotation, _Edges, build_viewpoint_model, _view, _run_lengths):
        h.update(inspect.getsource(part).encode())
    return h.hexdigest()[:16]


def mesh_digest(vertices: np.ndarray, faces: np.ndarray, settings: ViewpointSettings) -> str:
    """A key for a mesh's viewpoint model under `settings`: the same mesh and settings, built by the same code
    (`builder_digest`), give the same model."""
    h = hashlib.sha256()
    for a in (np.ascontiguousarray(vertices, dtype=np.float32), np.ascontiguousarray(faces, dtype=np.int32)):
        h.update(a.tobytes())
    h.update(repr(settings).encode())
    h.update(builder_digest().encode())
    return h.hexdigest()[:24]


def cache_dir() -> Path:
    """Where built viewpoint models are kept between runs: $AXISPOSE_CACHE, else $XDG_CACHE_HOME/axispose, else
    ~/.cache/axispose."""
    root = os.environ.get("AXISPOSE_CACHE") or Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "axispose"
    return Path(root) / "viewpoints"


_MEMORY: dict[str, ViewpointModel] = {}


def viewpoint_model(vertices: np.ndarray, faces: np.ndarray, settings: ViewpointSettings) -> ViewpointModel:
    """The mesh's viewpoint model: from this process's memory, else the disk cache, else built (about a second per
    object) and cached in both. A cache that cannot be written only costs the next process the build."""
    key = mesh_digest(vertices, faces, settings)
    if key in _MEMORY:
        return _MEMORY[key]
    path = cache_dir() / f"{key}.npz"
    model = None
    if path.exists():
        try:
            with np.load(path) as data:
                model = ViewpointModel(**{k: data[k] for k in data.files})
        except (OSError, ValueError, TypeError, KeyError) as err:
            log.warning("viewpoint cache %s unreadable (%s): rebuilding", path, err)
    if model is None:
        model = build_viewpoint_model(vertices, faces, settings)
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_suffix(f".{os.getpid()}.tmp.npz")
            np.savez(tmp, **model.arrays())
            tmp.replace(path)
        except OSError as err:
            log.warning("viewpoint cache %s not written (%s)", path, err)
    _MEMORY[key] = model
    return model
