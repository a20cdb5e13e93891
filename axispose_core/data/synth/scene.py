"""Scene sampling: which objects, where, and how they stand (floating in front of a photograph, or resting on a
table top); plus the primitive distractor shapes."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.spatial import ConvexHull
from scipy.spatial.transform import Rotation

from axispose_core.data.synth.config import SceneConfig
from axispose_core.data.synth.raster import RenderMesh, vertex_normals
from axispose_core.data.synth.table import Table, table_frame


@dataclass(frozen=True)
class Placement:
    """One object in the scene: its id (0 for a distractor), pose, and bounding-sphere radius (m)."""

    obj_id: int
    R: np.ndarray
    t: np.ndarray
    radius: float


def upright_rotation(rng: np.random.Generator, elevation_deg: float) -> np.ndarray:
    """Model +Z along the table's up vector as seen from a camera at this elevation, random yaw about it."""
    e = np.radians(elevation_deg)
    up = np.array([0.0, -np.cos(e), -np.sin(e)])  # image up at 0 deg, towards the camera at 90 deg
    helper = np.array([1.0, 0.0, 0.0])
    x = helper - up * (helper @ up)
    x /= np.linalg.norm(x)
    table = np.column_stack([x, np.cross(up, x), up])
    return table @ Rotation.from_euler("z", rng.uniform(0, 2 * np.pi)).as_matrix()


def _targets_and_centre(
    rng: np.random.Generator, cfg: SceneConfig, radii: dict[int, float], K: np.ndarray, width: int, height: int
) -> tuple[list[int], np.ndarray]:
    """Which objects (distinct ids), and the scene's centre: on the ray of a pixel near the middle of the image,
    inside the distance range."""
    ids = sorted(radii)
    n = int(rng.integers(cfg.objects_per_image[0], cfg.objects_per_image[1] + 1))
    chosen = list(rng.choice(ids, size=min(n, len(ids)), replace=False))
    zc = rng.uniform(cfg.distance[0] + 0.1, cfg.distance[1] - 0.1)
    ray = np.linalg.solve(K, [rng.uniform(0.3, 0.7) * width, rng.uniform(0.3, 0.7) * height, 1.0])
    return chosen, ray * zc


def _pack(
    rng: np.random.Generator,
    cfg: SceneConfig,
    radii: dict[int, float],
    chosen: list[int],
    target_at: Callable[[float], np.ndarray | None],
    distractor_at: Callable[[float], np.ndarray | None],
    elevation: float,
) -> list[Placement]:
    """The chosen objects, then the distractors, each at the first of its tries (`*_at(radius)`: a position, or
    None where the try is out of bounds) whose bounding sphere overlaps none placed before by more than 20 %;
    objects upright (model +Z up, seen from `elevation`) or uniformly rotated, distractors uniformly rotated."""
    placed: list[Placement] = []

    def free(t: np.ndarray, r: float) -> bool:
        return all(np.linalg.norm(t - p.t) >= 0.8 * (r + p.radius) for p in placed)

    for obj_id in chosen:
        r = radii[int(obj_id)]
        for _ in range(50):
            t = target_at(r)
            if t is not None and free(t, r):
                R = upright_rotation(rng, elevation) if rng.uniform() < cfg.upright_prob else Rotation.random(random_state=rng).as_matrix()
                placed.append(Placement(int(obj_id), R, t, r))
                break
    n_dis = int(rng.integers(cfg.distractors_per_image[0], cfg.distractors_per_image[1] + 1))
    for _ in range(n_dis):
        r = 0.5 * rng.uniform(*cfg.distractor_size)
        for _ in range(20):
            t = distractor_at(r)
            if t is not None and free(t, r):
                placed.append(Placement(0, Rotation.random(random_state=rng).as_matrix(), t, r))
                break
    return placed


def _roll(rng: np.random.Generator, cfg: SceneConfig, placed: list[Placement]) -> tuple[np.ndarray, list[Placement]]:
    """A random camera roll about the optical axis, and the placements it turns (every pose turns with it)."""
    roll = Rotation.from_euler("z", rng.uniform(*cfg.camera_roll_deg), degrees=True).as_matrix()
    return roll, [Placement(p.obj_id, roll @ p.R, roll @ p.t, p.radius) for p in placed]


def sample_scene(
    rng: np.random.Generator,
    cfg: SceneConfig,
    radii: dict[int, float],
    K: np.ndarray,
    width: int,
    height: int,
    table_top: tuple[np.ndarray, float] | None = None,
) -> tuple[list[Placement], Table | None]:
    """Target objects clustered about a random scene centre, so that they occlude each other, without
    interpenetrating bounding spheres beyond 20 %, each origin in view and within the distance range; then
    distractors. The whole scene is finally rolled about the optical axis.

    Without `table_top` they float in front of the background, spread more along the viewing ray than across
    it, distractors anywhere in view. With it (a texture and its metres per texel) they stand on a table top
    seen from `cfg.table_elevation_deg` above it, spread more away from the camera than across, distractors
    anywhere on the table in view; each about its radius above it, until `table.rest_on` sets it down once its
    mesh is known."""
    chosen, centre = _targets_and_centre(rng, cfg, radii, K, width, height)

    def in_view(t: np.ndarray, lo: float, hi: float) -> bool:
        if not lo <= t[2] <= hi:
            return False
        u, v, w = K @ t
        return 0 <= u / w < width and 0 <= v / w < height

    if table_top is None:
        elevation = rng.uniform(*cfg.elevation_deg)
        Kinv = np.linalg.inv(K)

        def target_at(r: float) -> np.ndarray | None:
            t = centre + rng.normal(0.0, 2 * r, size=3) * [cfg.cluster_spread, cfg.cluster_spread, 2.0]
            return t if in_view(t, *cfg.distance) else None

        def distractor_at(r: float) -> np.ndarray | None:
            px = np.array([rng.uniform(0, width), rng.uniform(0, height), 1.0])
            return Kinv @ px * rng.uniform(cfg.distance[0], cfg.distance[1] + 0.3)

        # Rolling the camera about its axis keeps objects near the principal point in view.
        _, rolled = _roll(rng, cfg, _pack(rng, cfg, radii, chosen, target_at, distractor_at, elevation))
        return [p for p in rolled if p.obj_id == 0 or in_view(p.t, 0.0, np.inf)], None
    elevation = rng.uniform(*cfg.table_elevation_deg)
    up, (across, away) = table_frame(elevation)
    a = rng.uniform(0, 2 * np.pi)  # the texture's grain at any angle on the table
    axes = np.stack([np.cos(a) * across + np.sin(a) * away, -np.sin(a) * across + np.cos(a) * away])
    side = rng.uniform(*cfg.table_size, 2)
    table = Table(centre, up, axes, (0.5 * float(side[0]), 0.5 * float(side[1])), *table_top)

    def on_table(r: float) -> np.ndarray | None:
        local = rng.uniform(-1.0, 1.0, 2) * table.half_size
        t = centre + local[0] * axes[0] + local[1] * axes[1] + r * up
        return t if in_view(t, *cfg.distance) else None

    def clustered(r: float) -> np.ndarray | None:
        offset = rng.normal(0.0, 2 * r * cfg.cluster_spread, size=2) * [1.0, 2.0]
        t = centre + offset[0] * across + offset[1] * away + r * up
        return t if in_view(t, *cfg.distance) else None

    roll, rolled = _roll(rng, cfg, _pack(rng, cfg, radii, chosen, clustered, on_table, elevation))
    return rolled, table.rolled(roll)


def primitive(rng: np.random.Generator, radius: float) -> RenderMesh:
    """A random convex distractor inside `radius`: a box (flat-shaded), cylinder or ellipsoid, randomly coloured."""
    kind = rng.integers(3)
    if kind == 0:
        pts = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=float) * rng.uniform(0.3, 1.0, 3)
    elif kind == 1:
        u = np.linspace(0, 2 * np.pi, 32, endpoint=False)
        r = rng.uniform(0.3, 1.0)
        ring = np.column_stack([r * np.cos(u), r * np.sin(u), np.zeros_like(u)])
        h = rng.uniform(0.3, 1.0)
        pts = np.vstack([ring + [0, 0, -h], ring + [0, 0, h]])
    else:
        i = np.arange(300) + 0.5
        phi, theta = np.arccos(1 - 2 * i / 300), np.pi * (1 + 5**0.5) * i
        pts = np.column_stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)]) * rng.uniform(0.4, 1.0, 3)
    pts *= radius / np.linalg.norm(pts, axis=1).max()
    faces = _outward(pts, ConvexHull(pts).simplices)
    if kind == 0:  # one vertex per face corner: flat faces
        pts, faces = pts[faces.ravel()], np.arange(3 * len(faces)).reshape(-1, 3)
    base = rng.uniform(0.05, 1.0, 3)
    colors = np.clip(base + rng.normal(0, rng.uniform(0, 0.15), (len(pts), 3)), 0, 1)
    return RenderMesh(pts, faces, colors, vertex_normals(pts, faces))


def _outward(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Orient the faces of a convex, origin-centred mesh counter-clockwise seen from outside."""
    tri = verts[faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    inward = np.einsum("ij,ij->i", n, tri.mean(axis=1)) < 0
    faces = faces.copy()
    faces[inward] = faces[inward][:, ::-1]
    return faces
