"""A textured table top the objects rest on: its geometry, its pixels in a camera (perspective-correct texture
by ray-plane intersection, no mesh), its shading with the light and the objects' shadows, and resting a mesh on
it. Drawn apart from the meshes because the renderer colours by vertex, and a table is all texture."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from axispose_core.data.synth.raster import Light, RenderMesh, ShadowMap, pixel_rays


@dataclass(frozen=True)
class Table:
    """A rectangle in the camera frame: centre, unit normal (up, towards the camera's side), in-plane unit axes."""

    centre: np.ndarray
    normal: np.ndarray
    axes: np.ndarray
    """(2, 3): the texture's u and v directions."""
    half_size: tuple[float, float]
    """Half its extent (m) along the two axes."""
    texture: np.ndarray
    """(T, T, 3) float RGB, repeated mirrored over the table."""
    texel: float
    """Metres per texture pixel."""

    def rolled(self, roll: np.ndarray) -> Table:
        """The table after the camera rolls (every camera-frame vector turned by `roll`)."""
        return self.transformed(roll, np.zeros(3))

    def transformed(self, R: np.ndarray, t: np.ndarray) -> Table:
        """The table seen by a camera that moved: every camera-frame point p becomes R p + t."""
        return Table(R @ self.centre + t, R @ self.normal, self.axes @ R.T, self.half_size, self.texture, self.texel)


def table_frame(elevation_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """The table's up vector and its in-plane axes ((2, 3): across the view, away from the camera) seen from a
    camera at this elevation above it; the up vector is `scene.upright_rotation`'s, so upright objects stand on it."""
    e = np.radians(elevation_deg)
    up = np.array([0.0, -np.cos(e), -np.sin(e)])
    x = np.array([1.0, 0.0, 0.0])
    return up, np.stack([x, np.cross(up, x)])


def table_pixels(table: Table, K: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Where each pixel's ray meets the table: camera-frame points (H, W, 3) and depth z (H, W; inf where it
    misses the rectangle or meets its plane behind the camera)."""
    rays = pixel_rays(K, *np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64)))
    denom = rays @ table.normal
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.where(np.abs(denom) > 1e-9, (table.centre @ table.normal) / denom, np.inf)
    points = rays * np.where(np.isfinite(z) & (z > 0), z, 0.0)[..., None]
    local = (points - table.centre) @ table.axes.T
    hit = np.isfinite(z) & (z > 0) & (np.abs(local[..., 0]) <= table.half_size[0]) & (np.abs(local[..., 1]) <= table.half_size[1])
    return points, np.where(hit, z, np.inf)


def shade_table(table: Table, points: np.ndarray, depth: np.ndarray, light: Light, shadows: ShadowMap | None) -> np.ndarray:
    """The table's colour at `points` (from `table_pixels`; 0 where it is not seen): its texture lit by the
    directional light, less the direct part where the shadow map says the objects block it."""
    hit = np.isfinite(depth)
    rgb = np.zeros((*depth.shape, 3), np.float32)
    if not hit.any():
        return rgb
    local = (points - table.centre) @ table.axes.T / table.texel
    n = table.texture.shape[0]
    # Mirrored repeats (reflect-101 beyond the texture) hide the seams of a plain repeat.
    period = 2 * (n - 1)
    m = np.mod(local + 0.5 * n, period)
    m = np.where(m > n - 1, period - m, m).astype(np.float32)
    col = cv2.remap(table.texture, m[..., 0], m[..., 1], cv2.INTER_LINEAR)[hit]
    lam = max(0.0, float(-(table.normal @ light.direction)))
    direct = lam * (shadows.lit(points[hit]) if shadows is not None else np.ones(len(col)))
    shade = (light.ambient + (1.0 - light.ambient) * direct)[..., None] * light.color[None, :]
    rgb[hit] = np.clip(col * shade, 0.0, 1.0)
    return rgb


def rest_on(table: Table, mesh: RenderMesh, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """t moved along the table's normal so that the posed mesh's lowest point touches the table."""
    lowest = float(((mesh.vertices @ R.T + t) @ table.normal).min())
    return t + (table.centre @ table.normal - lowest) * table.normal


def light_from_above(light: Light, table: Table, rng: np.random.Generator) -> Light:
    """The light turned to fall on the table from above (30-80 degrees over it), keeping its side of the scene."""
    d = light.direction - (light.direction @ table.normal) * table.normal
    norm = float(np.linalg.norm(d))
    d = d / norm if norm > 1e-6 else table.axes[0]
    a = np.radians(rng.uniform(30.0, 80.0))
    return Light(np.cos(a) * d - np.sin(a) * table.normal, light.color, light.ambient, light.specular, light.shininess)
