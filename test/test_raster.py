"""The rasteriser against geometry, not against itself: silhouettes of a sphere and a box against their analytic
projections, an LM-O mesh against an independent point-in-triangle rasterisation, exact coverage where triangles
meet, and perspective-correct depth."""

import numpy as np
import pytest
from matplotlib.path import Path as PolyPath
from scipy.spatial import ConvexHull
from scipy.spatial.transform import Rotation

from axispose_core.data.bop_models import model_path
from axispose_core.data.meshes import load_ply
from axispose_core.data.synth.raster import Light, RenderMesh, _rasterize, render, render_depth, vertex_normals

LIGHT = Light(np.array([0.0, 0.0, 1.0]), np.ones(3), 0.5)
K = np.array([[572.4114, 0.0, 325.2611], [0.0, 573.57043, 242.04899], [0.0, 0.0, 1.0]])


def _mesh(vertices: np.ndarray, faces: np.ndarray, outward_from: np.ndarray | None = None) -> RenderMesh:
    """A grey mesh; faces are wound counter-clockwise seen from outside, away from `outward_from` (a convex
    shape's centre), else towards the camera at the origin."""
    vertices, faces = np.asarray(vertices, float), np.asarray(faces, np.int64).copy()
    v = vertices[faces]
    normal = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    inward = np.einsum("ij,ij->i", normal, v.mean(axis=1) - outward_from) < 0 if outward_from is not None else (
        np.einsum("ij,ij->i", normal, v[:, 0]) > 0)  # fmt: skip
    faces[inward] = faces[inward][:, ::-1]
    return RenderMesh(vertices, faces, np.full((len(vertices), 3), 0.5), vertex_normals(vertices, faces))


def _icosphere(radius: float, levels: int) -> RenderMesh:
    """A sphere: an icosahedron split `levels` times, its vertices on the sphere, faces wound outward."""
    g = (1 + 5**0.5) / 2
    verts = [np.array(p, float) / np.linalg.norm(p) for p in ([0, 1, g], [0, -1, g], [0, 1, -g], [0, -1, -g])]
    verts += [np.roll(p, 1) for p in verts] + [np.roll(p, 2) for p in verts]  # the 12 vertices of an icosahedron
    faces = ConvexHull(np.array(verts)).simplices.tolist()
    for _ in range(levels):
        cache: dict[tuple[int, int], int] = {}
        new = []
        for tri in faces:
            mids = []
            for a, b in ((tri[0], tri[1]), (tri[1], tri[2]), (tri[2], tri[0])):
                key = (min(a, b), max(a, b))
                if key not in cache:
                    m = verts[a] + verts[b]
                    verts.append(m / np.linalg.norm(m))
                    cache[key] = len(verts) - 1
                mids.append(cache[key])
            ab, bc, ca = mids
            new += [[tri[0], ab, ca], [tri[1], bc, ab], [tri[2], ca, bc], [ab, bc, ca]]
        faces = new
    return _mesh(np.array(verts) * radius, np.array(faces), np.zeros(3))


def _box(size: np.ndarray) -> RenderMesh:
    corners = np.array([[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5)]) * size
    return _mesh(corners, ConvexHull(corners).simplices, np.zeros(3))


def _centres_inside(polygons: list[np.ndarray], width: int, height: int) -> np.ndarray:
    """Pixel centres inside any of the polygons (an independent rasterisation: matplotlib's point-in-polygon)."""
    mask = np.zeros((height, width), dtype=bool)
    for poly in polygons:
        x0, y0 = np.maximum(np.ceil(poly.min(axis=0)).astype(int), 0)
        x1, y1 = np.minimum(np.floor(poly.max(axis=0)).astype(int), [width - 1, height - 1])
        if x1 < x0 or y1 < y0:
            continue
        xs, ys = np.meshgrid(np.arange(x0, x1 + 1), np.arange(y0, y1 + 1))
        inside = PolyPath(poly).contains_points(np.column_stack([xs.ravel(), ys.ravel()]))
        mask[ys.ravel()[inside], xs.ravel()[inside]] = True
    return mask


def _project(K: np.ndarray, R: np.ndarray, t: np.ndarray, pts: np.ndarray) -> np.ndarray:
    cam = pts @ R.T + t
    return (cam @ K.T)[:, :2] / cam[:, 2:3]


@pytest.mark.parametrize("distance", [0.5, 1.5, 4.0])
def test_a_sphere_covers_its_analytic_disc(distance):
    r = 0.05
    res = render([(_icosphere(r, 4), np.eye(3), np.array([0.0, 0.0, distance]))], K, 640, 480, LIGHT)
    # A sphere on the optical axis projects to a circle of radius f r / sqrt(d^2 - r^2); Kc centres it on a pixel.
    radius_px = K[0, 0] * r / np.sqrt(distance**2 - r**2)
    assert radius_px > 7
    area = res.full[0].sum()
    assert area == pytest.approx(np.pi * radius_px * K[1, 1] / K[0, 0] * radius_px, rel=0.01)


@pytest.mark.parametrize("seed", range(4))
def test_a_box_covers_exactly_its_projected_hull(seed):
    rng = np.random.default_rng(seed)
    size = rng.uniform(0.02, 0.12, 3)
    R = Rotation.random(random_state=rng).as_matrix()
    t = np.array([rng.uniform(-0.15, 0.15), rng.uniform(-0.1, 0.1), rng.uniform(0.4, 1.2)])
    mesh = _box(size)
    res = render([(mesh, R, t)], K, 640, 480, LIGHT)
    uv = _project(K, R, t, mesh.vertices)
    hull = uv[ConvexHull(uv).vertices]
    expected = _centres_inside([hull], 640, 480)
    got = res.full[0]
    assert expected.sum() > 300  # at least 20 px across
    assert np.count_nonzero(got != expected) <= 2  # only centres within rounding of the outline may differ
    x, y = hull[:, 0], hull[:, 1]
    polygon_area = 0.5 * abs(np.dot(x, np.roll(y, 1)) - np.dot(y, np.roll(x, 1)))
    assert got.sum() == pytest.approx(polygon_area, rel=0.01)


def test_an_lmo_mesh_matches_an_independent_rasterisation(lmo_dir):
    ape = load_ply(model_path(lmo_dir / "models_eval", 1))
    mesh = RenderMesh(ape.vertices, ape.faces, np.full((len(ape.vertices), 3), 0.5), vertex_normals(ape.vertices, ape.faces))
    S = 64
    R = Rotation.from_euler("xyz", [30, -50, 20], degrees=True).as_matrix()
    t = np.array([0.0, 0.0, 0.6])
    Kc = np.array([[330.0, 0.0, 31.5], [0.0, 330.0, 31.5], [0.0, 0.0, 1.0]])  # the object spans ~70 % of the crop
    uv = _project(Kc, R, t, mesh.vertices)
    expected = _centres_inside([uv[f] for f in mesh.faces], S, S)
    got = render([(mesh, R, t)], Kc, S, S, LIGHT).full[0]
    assert 0.3 * S * S < expected.sum() < 0.8 * S * S
    assert np.count_nonzero(got != expected) <= 2
    # The renderer's depth is the surface's: the camera-frame z of the model point it reports.
    res = render([(mesh, R, t)], Kc, S, S, LIGHT)
    covered = res.instance == 0
    z = (res.points[covered] @ R.T + t)[:, 2]
    assert np.allclose(z, res.depth[covered], atol=1e-5)


def test_triangles_meeting_on_pixel_centres_cover_each_centre_once():
    # A 6 x 6 grid of squares, two triangles each, at z = 1 through f = 8: every vertex projects onto a pixel
    # centre and every edge runs through centres, so only the tie rule decides who covers them.
    n, step = 6, 0.5
    xs = np.arange(n + 1) * step - n * step / 2
    verts = np.array([[x, y, 1.0] for y in xs for x in xs])
    faces = []
    for j in range(n):
        for i in range(n):
            a, b, c, d = j * (n + 1) + i, j * (n + 1) + i + 1, (j + 1) * (n + 1) + i, (j + 1) * (n + 1) + i + 1
            faces += [[a, c, b], [b, c, d]] if (i + j) % 2 else [[a, c, d], [a, d, b]]  # both diagonals
    mesh = _mesh(verts, np.array(faces))
    K8 = np.array([[8.0, 0.0, 20.0], [0.0, 8.0, 20.0], [0.0, 0.0, 1.0]])
    samples = _rasterize(mesh, np.eye(3), np.zeros(3), K8, 40, 40)
    counts = np.bincount(samples.pix, minlength=40 * 40).reshape(40, 40)
    # The outline from centre 8 to centre 32: its interior once each; on the outline itself, the top-left rule
    # keeps two of the four sides.
    assert counts.max() == 1
    assert counts[9:32, 9:32].min() == 1
    assert counts.sum() == 24 * 24


def test_depth_is_perspective_correct_on_a_tilted_plane():
    # One large quad on the plane z = 1 + 0.5 x: depth at each pixel is the ray's intersection with that plane.
    quad = np.array([[-0.4, -0.3, 0.8], [0.4, -0.3, 1.2], [0.4, 0.3, 1.2], [-0.4, 0.3, 0.8]])
    mesh = _mesh(quad, np.array([[0, 2, 1], [0, 3, 2]]))
    depth = render_depth(mesh, np.eye(3), np.zeros(3), K, 640, 480)
    v, u = np.nonzero(depth > 0)
    x = (u - K[0, 2]) / K[0, 0]
    assert len(u) > 10000
    assert np.allclose(depth[v, u], 1.0 / (1.0 - 0.5 * x), rtol=0, atol=2e-6)  # z = 1 + 0.5 x z along (x, y, 1)
