"""Distractor meshes that look like things on a desk: pybullet_data's everyday objects (a mug, a duck, bricks,
a teddy, ...) and its 1,000 procedurally generated shapes ("random_urdfs"), scaled to the distractor's size and
coloured flat or with a texture projected onto them. One mesh in ten is held out of the "train" split for
stress sets. The meshes come with pybullet (a registry wheel, a dependency of the package)."""

from __future__ import annotations

import importlib.util
from functools import lru_cache
from pathlib import Path

import numpy as np

from axispose_core.data.meshes import load_obj
from axispose_core.data.synth.config import BackgroundConfig
from axispose_core.data.synth.randomize import background
from axispose_core.data.synth.raster import RenderMesh, vertex_normals

EVERYDAY = (
    "objects/mug.obj", "duck.obj", "lego/lego.obj", "jenga/jenga.obj", "domino/domino.obj", "soccerball.obj",
    "torus/torus_textured.obj", "bunny.obj", "teddy2_VHACD_CHs.obj", "sphere_smooth.obj", "cube.obj", "tray/tray_textured.obj",
)  # fmt: skip
"""pybullet_data's meshes of everyday things (closed, at least roughly)."""
RANDOM_SHAPES = 1000
"""pybullet_data/random_urdfs/000 ... 999."""
HELD_OUT_EVERY = 10
"""Every tenth mesh of the library (by its index) is held out of the "train" split."""
TEXTURE = 64
"""Side (px) of the texture projected onto a textured distractor."""


def _data_path() -> Path:
    spec = importlib.util.find_spec("pybullet_data")
    if spec is None or spec.origin is None:
        raise RuntimeError("distractor meshes come from pybullet_data: `pip install pybullet` (or set distractor_meshes to 0)")
    return Path(spec.origin).parent


@lru_cache(maxsize=3)
def library(split: str) -> tuple[Path, ...]:
    """The meshes of a split: "train", "held_out" or "all"."""
    root = _data_path()
    paths = [root / p for p in EVERYDAY] + [root / "random_urdfs" / f"{i:03d}" / f"{i:03d}.obj" for i in range(RANDOM_SHAPES)]
    keep = {"train": lambda i: i % HELD_OUT_EVERY != HELD_OUT_EVERY - 1, "held_out": lambda i: i % HELD_OUT_EVERY == HELD_OUT_EVERY - 1,
            "all": lambda i: True}[split]  # fmt: skip
    return tuple(p for i, p in enumerate(paths) if keep(i) and p.exists())


@lru_cache(maxsize=256)
def unit_mesh(path: Path) -> tuple[np.ndarray, np.ndarray] | None:
    """A library mesh centred on its bounding box and scaled to unit radius, its faces wound outward (vertices,
    faces); faces on non-finite vertices dropped (one random shape has NaN vertices), None if none is left."""
    mesh = load_obj(path, units=1.0)
    finite = np.all(np.isfinite(mesh.vertices), axis=1)
    f = mesh.faces[finite[mesh.faces].all(axis=1)]
    if not len(f):
        return None
    used = np.unique(f)
    v = mesh.vertices[used]
    f = np.searchsorted(used, f)
    v = v - 0.5 * (v.min(axis=0) + v.max(axis=0))
    v /= max(float(np.linalg.norm(v, axis=1).max()), 1e-9)
    tri = v[f]
    if np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() < 0:  # negative volume: wound inward
        f = f[:, ::-1].copy()
    return v, f


PICKS = 10
"""Library draws before giving up on finding a usable mesh."""


def distractor_mesh(
    rng: np.random.Generator, radius: float, split: str, backgrounds: BackgroundConfig, exclude_faces: frozenset[int] = frozenset()
) -> RenderMesh:
    """A random library mesh of bounding radius `radius` (m), stretched a little per axis, coloured flat with
    a little noise (half of them) or with a background texture projected along its dominant axes.
    `exclude_faces`: the face counts of the scene's own objects. A library mesh with one of them is drawn again:
    it may be one of those objects (an own object taken from pybullet_data), which would appear unannotated."""
    paths = library(split)
    if not paths:
        raise RuntimeError(f"no pybullet_data meshes in the {split!r} split")
    for _ in range(PICKS):
        unit = unit_mesh(paths[int(rng.integers(len(paths)))])
        if unit is not None and len(unit[1]) not in exclude_faces:
            break
    else:
        raise RuntimeError(f"no usable pybullet_data mesh in {PICKS} draws from the {split!r} split")
    v, f = unit
    v = v * rng.uniform(0.7, 1.3, 3)
    v = v * (radius / float(np.linalg.norm(v, axis=1).max()))
    normals = vertex_normals(v, f)
    if rng.uniform() < 0.5:
        colors = np.clip(rng.uniform(0.05, 1.0, 3) + rng.normal(0, rng.uniform(0, 0.1), (len(v), 3)), 0, 1)
    else:
        # Each vertex reads the texture in the plane across its normal's dominant axis (a triplanar projection).
        texture = background(rng, backgrounds, TEXTURE, TEXTURE)
        axis = np.abs(normals).argmax(axis=1)
        uv = np.where(axis[:, None] == 0, v[:, [1, 2]], np.where(axis[:, None] == 1, v[:, [0, 2]], v[:, [0, 1]]))
        px = np.clip(np.rint((uv / radius + 1) * 0.5 * (TEXTURE - 1)), 0, TEXTURE - 1).astype(np.int64)
        colors = texture[px[:, 1], px[:, 0]]
    return RenderMesh(v, f, np.clip(colors, 0, 1).astype(np.float64), normals)


def lookalike(rng: np.random.Generator, mesh: RenderMesh, palettes: list[np.ndarray], tint: np.ndarray) -> RenderMesh:
    """`mesh` coloured flat in one object's own colour (a random vertex colour of a random palette, the objects'
    vertex colours), times `tint` as the objects are, with the flat distractors' noise: an object's colour on a
    shape that is not the object, the hard negative a real desk's clutter is."""
    palette = palettes[int(rng.integers(len(palettes)))]
    base = palette[int(rng.integers(len(palette)))] * tint
    colors = base + rng.normal(0, rng.uniform(0, 0.1), (len(mesh.vertices), 3))
    return RenderMesh(mesh.vertices, mesh.faces, np.clip(colors, 0, 1).astype(np.float64), mesh.normals)
