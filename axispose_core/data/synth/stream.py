"""The crop stream: endless, seeded AGM training samples, each an object crop rendered fresh at its own resolution.

Sample i depends only on (seed, i): runs are reproducible and resumable without storing data, and no sample is
ever seen twice. Rendering the crop instead of the frame is what makes that affordable: the crop's patch
intrinsics K' (`camera.crop_intrinsics`) put the object exactly where a crop of a full frame would, so the axis
target rendered through the same K' is exact by construction.

One sample, in order:
1. the target object at a pose of the LM-O range, its origin anywhere in the frame (so perspective varies),
   uniformly rotated or upright on a table seen from the LM-O elevations;
2. the crop a localiser would cut: the estimator's square around the amodal box, moved and scaled as the
   shipped localiser's crops are for the visibility drawn (`Framing`, measured);
3. neighbours behind (other objects of the set, primitives) and the target, rendered through K' (one z-buffer);
4. an occluder in front, rendered on its own canvas and laid over the crop where it hides the drawn share of
   the target (the overlap of every placement at once, by FFT), so visible fractions follow `StreamConfig.visib`
   exactly; or, unoccluded, often an object beside the target;
5. background (photographs, textures, markers, clutter), light with highlights, object tints, and the camera
   (`randomize.camera_effects`, JPEG) applied at the resolution the frame had there, then resampled to the crop
   as `camera.crop_image` would; pixels beyond the frame's border are black, as `crop_image` fills them.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
from scipy.signal import fftconvolve
from scipy.spatial.transform import Rotation
from scipy.stats import t as student_t
from torch.utils.data import DataLoader, Dataset

from axispose_core.axis_image import axis_keypoints, render_axis_keypoints
from axispose_core.camera import crop_intrinsics, hull_points, square_around_box
from axispose_core.data.bop import bbox_from_model
from axispose_core.data.bop_models import load_models_info, model_path
from axispose_core.data.meshes import load_render_mesh, ply_vertex_properties
from axispose_core.data.synth.appearance import photometric, surface
from axispose_core.data.synth.clutter import distractor_mesh
from axispose_core.data.synth.config import StreamConfig
from axispose_core.data.synth.randomize import background, camera_effects, jpeg, light, object_tint, wrong_texture
from axispose_core.data.synth.raster import Light, RenderMesh, decimate, render
from axispose_core.data.synth.scene import primitive, upright_rotation
from axispose_core.objects import ObjectSpec, objects_from_models

log = logging.getLogger(__name__)

ATTEMPTS = 20
"""Fresh draws of one sample, from (seed, i, attempt), before giving up (a draw fails when its visible fraction
misses the range, e.g. a small occluder cannot hide enough)."""
LODS = 3
"""Levels of detail per object: cells of mesh_cell crop pixels when it appears the target's usual size (the
square of side `size` / pad), at half that size, and at a quarter; an object is drawn at the coarsest level that
keeps its cells within mesh_cell pixels, never finer than the first (occluders up to 1.5x its size: 3 px)."""
PRIMITIVES = 64
"""Unit-sized primitive shapes made once per stream and scaled and re-coloured per use (a convex hull per
sample would cost as much as rendering one)."""
VISIB_TOL = 0.02
"""An occluder placement is taken among those within this of the drawn visible fraction."""


@dataclass(frozen=True)
class CropSample:
    """One crop of object `obj_id` with everything known about it; images are size x size, keypoints in crop
    pixels."""

    obj_id: int
    crop: np.ndarray
    """uint8 RGB."""
    axes: np.ndarray
    """Axis-image target, float32 RGB (= X, Y, Z) in [0, 1]."""
    keypoints: np.ndarray
    """(4, 2): projected origin, X, Y and Z endpoints."""
    K: np.ndarray
    """The frame camera."""
    K_crop: np.ndarray
    R: np.ndarray
    t: np.ndarray
    center: tuple[float, float]
    side: float
    visib: float
    mask_visib: np.ndarray
    mask: np.ndarray
    """The target's whole silhouette in the crop."""
    points: np.ndarray
    """(size, size, 3) float32: the target's surface point seen at each pixel of `mask_visib`, in its model
    frame (m; 0 elsewhere): dense correspondences to teach the AGM's encoder the object's shape and pose."""


@dataclass(frozen=True)
class _Model:
    spec: ObjectSpec
    lods: tuple[RenderMesh, ...]
    """The mesh at LODS levels of detail (one: the full mesh, where mesh_cell is 0)."""
    hull: np.ndarray
    """Convex-hull vertices (m): the amodal box is theirs."""

    def mesh(self, level: int) -> RenderMesh:
        return self.lods[min(level, len(self.lods) - 1)]


def _check_mesh(mesh: RenderMesh, path: Path) -> None:
    if not len(mesh.faces):
        raise ValueError(f"{path}: the mesh has no faces (the stream renders surfaces, not point clouds)")
    if "red" not in ply_vertex_properties(path):  # rendered grey, as the synthetic frames render it
        log.warning("%s: the mesh has no vertex colours; the crop stream renders it grey", path)


class CropStream:
    """Samples of `StreamConfig` from the objects of a BOP models folder (obj_XXXXXX.ply + models_info.json)."""

    def __init__(self, cfg: StreamConfig, models_dir: str | Path, mesh_cache: str | Path | None = None) -> None:
        models_dir = Path(models_dir)
        infos = load_models_info(models_dir / "models_info.json")
        ids = tuple(cfg.objects) or tuple(sorted(infos))
        if not ids:
            raise ValueError(f"{models_dir / 'models_info.json'} lists no objects")
        unknown = [i for i in ids if i not in infos]
        if unknown:
            raise ValueError(f"object id(s) {unknown} are not in {models_dir / 'models_info.json'} (it has {sorted(infos)})")
        self.cfg = cfg
        self.K = np.asarray(cfg.K, dtype=np.float64).reshape(3, 3)
        self.objects = objects_from_models(models_dir, list(ids))
        self.index = {o.obj_id: k for k, o in enumerate(self.objects)}
        self.models: dict[int, _Model] = {}
        own_faces = set()
        for spec in self.objects:
            mesh = load_render_mesh(models_dir, spec.obj_id, mesh_cache)
            own_faces.add(len(mesh.faces))
            _check_mesh(mesh, model_path(models_dir, spec.obj_id))
            hull = hull_points(mesh.vertices)
            cell = cfg.mesh_cell * spec.diameter * cfg.framing.pad / cfg.size  # metres per mesh_cell px at usual size
            lods = tuple(decimate(mesh, cell * 2**level) for level in range(LODS)) if cfg.mesh_cell > 0 else (mesh,)
            self.models[spec.obj_id] = _Model(spec, lods, hull)
        self.own_faces = frozenset(own_faces)
        """The objects' face counts: no distractor mesh with one of them (`clutter.distractor_mesh`)."""
        pool = np.random.default_rng([cfg.seed, 2**31])
        self.primitives = [primitive(pool, 1.0) for _ in range(PRIMITIVES)]
        # The t distribution's scale that gives the measured robust spread (1.4826 MAD).
        self._t_scale = 1.0 / (1.4826 * student_t.ppf(0.75, cfg.framing.dof))

    # ------------------------------------------------------------------------------------------------ sampling

    def __getitem__(self, index: int) -> CropSample:
        for attempt in range(ATTEMPTS):
            sample = self._draw(np.random.default_rng([self.cfg.seed, int(index), attempt]))
            if sample is not None:
                return sample
        raise RuntimeError(f"crop stream: sample {index} missed visib {self.cfg.visib} in {ATTEMPTS} draws; widen the range")

    def _pose(self, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        cfg = self.cfg
        m = cfg.margin
        u, v = rng.uniform(m, 1 - m) * cfg.width, rng.uniform(m, 1 - m) * cfg.height
        t = np.linalg.solve(self.K, [u, v, 1.0]) * rng.uniform(*cfg.distance)
        if rng.uniform() < cfg.upright_prob:
            roll = Rotation.from_euler("z", rng.uniform(*cfg.camera_roll_deg), degrees=True).as_matrix()
            R = roll @ upright_rotation(rng, rng.uniform(*cfg.elevation_deg))
        else:
            R = Rotation.random(random_state=rng).as_matrix()
        return R, t

    def _framing(self, rng: np.random.Generator, box: tuple[int, int, int, int], visib: float) -> tuple[tuple[float, float], float]:
        f = self.cfg.framing
        band = int(np.searchsorted(f.visib_edges, visib, side="right"))
        (cx, cy), side = square_around_box(box, f.pad)
        shift = np.clip(rng.standard_t(f.dof, 2) * self._t_scale * f.centre_std[band], -0.5, 0.5)
        log_scale = np.clip(f.scale_median[band] + rng.standard_t(f.dof) * self._t_scale * f.scale_std[band], -0.7, 0.7)
        return (cx + shift[0] * side, cy + shift[1] * side), side * float(np.exp(log_scale))

    def _tinted(self, rng: np.random.Generator, obj_id: int, apparent: float) -> RenderMesh:
        """The object's mesh at the level of detail for `apparent` crop pixels across, re-tinted."""
        level = int(np.clip(np.floor(np.log2(self.cfg.size / self.cfg.framing.pad / max(apparent, 1e-6))), 0, LODS - 1))
        m, lcfg = self.models[obj_id].mesh(level), self.cfg.randomization.light
        colors = wrong_texture(rng, m.colors, m.vertices) if lcfg.texture_prob > 0 and rng.uniform() < lcfg.texture_prob else m.colors
        return RenderMesh(m.vertices, m.faces, np.clip(colors * object_tint(rng, lcfg), 0, 1), m.normals)

    def _primitive(self, rng: np.random.Generator, radius: float) -> RenderMesh:
        """A primitive of the pool scaled to `radius`, in a new colour (its own colour variation kept), or a
        distractor mesh where `distractor_meshes` says so."""
        cfg = self.cfg
        if cfg.distractor_meshes > 0 and rng.uniform() < cfg.distractor_meshes:
            return distractor_mesh(rng, radius, cfg.distractor_split, cfg.randomization.background, self.own_faces)
        p = self.primitives[int(rng.integers(len(self.primitives)))]
        colors = np.clip(p.colors - p.colors.mean(axis=0) + rng.uniform(0.05, 1.0, 3), 0, 1)
        return RenderMesh(p.vertices * radius, p.faces, colors, p.normals)

    def _other(self, rng: np.random.Generator, obj_id: int) -> int | None:
        """Another object of the set; None where a primitive is to stand instead."""
        others = [i for i in self.models if i != obj_id]
        if others and rng.uniform() < self.cfg.object_prob:
            return others[int(rng.integers(len(others)))]
        return None

    def _draw(self, rng: np.random.Generator) -> CropSample | None:
        cfg, rcfg, S = self.cfg, self.cfg.randomization, self.cfg.size
        obj_id = self.objects[int(rng.integers(len(self.objects)))].obj_id
        model = self.models[obj_id]
        R, t = self._pose(rng)
        lo, hi = cfg.visib
        occluded = hi < 1.0 or rng.uniform() < cfg.occluded_prob
        want = rng.uniform(lo, hi) if occluded else 1.0
        center, side = self._framing(rng, bbox_from_model(self.K, R, t, model.hull), want)
        Kc = crop_intrinsics(self.K, center, side, S)
        lit = light(rng, rcfg.light)
        radius = 0.5 * model.spec.diameter
        f = 0.5 * (Kc[0, 0] + Kc[1, 1])
        posed = [(self._tinted(rng, obj_id, 2 * radius * f / t[2]), R, t)]
        for _ in range(int(rng.integers(cfg.neighbours[0], cfg.neighbours[1] + 1))):
            other = self._other(rng, obj_id)
            r = 0.5 * (self.models[other].spec.diameter if other is not None else rng.uniform(*cfg.primitive_size))
            z = t[2] + radius + r + rng.uniform(0.0, 0.3)
            mesh = self._tinted(rng, other, 2 * r * f / z) if other is not None else self._primitive(rng, r)
            px = rng.uniform(-0.25, 1.25, 2) * S
            posed.append((mesh, Rotation.random(random_state=rng).as_matrix(), np.linalg.solve(Kc, [px[0], px[1], 1.0]) * z))
        res = render(posed, Kc, S, S, lit)
        full = res.full[0]
        if not full.any():
            return None
        inside = self._inside_frame(center, side)
        visible = (res.instance == 0) & inside
        image = surface(rng, rcfg.surface, res.rgb, res.instance == 0)
        covered = np.zeros((S, S), bool)
        if occluded or rng.uniform() < cfg.clutter_prob:
            # Its apparent diameter in crop pixels grows with the share of the target it must hide (0.84-1.22
            # crops to leave a tenth, 0.36-0.58 to leave nine tenths: big enough to reach it, no bigger, since a
            # canvas costs its area to render); beside the target, 0.3-0.7 crops.
            apparent = S * (rng.uniform(0.3 + 0.6 * (1 - want), 0.5 + 0.8 * (1 - want)) if occluded else rng.uniform(0.3, 0.7))
            occ = self._occluder(rng, obj_id, t[2] - radius, Kc, lit, apparent)
            if occ is not None:
                occ_rgb, occ_mask = occ
                where = self._placement(rng, visible, full.sum(), occ_mask, want if occluded else None)
                if where is not None:
                    covered, image = self._paste(image, occ_rgb, occ_mask, where)
        owned = (res.instance >= 0) | covered
        zoom = side / cfg.height
        n = int(np.clip(round(side), 16, 2 * S))
        bg = cv2.resize(background(rng, rcfg.background, n, n, zoom), (S, S), interpolation=cv2.INTER_AREA if n > S else cv2.INTER_LINEAR)
        image = np.where(owned[..., None], image, bg).astype(np.float32)
        image = self._camera(rng, image, center, side)
        image, dropped = photometric(rng, rcfg.photometric, image, scale=S / side)
        image[~inside] = 0.0
        mask_visib = visible & ~covered
        visib = float(mask_visib.sum() / full.sum())
        if not lo <= visib <= hi:
            return None
        if dropped is not None:  # blacked-out cells hide the surface from the dense targets, not from `visib`
            mask_visib &= ~dropped
        kp = axis_keypoints(Kc, R, t, model.spec.axes.lengths)
        return CropSample(
            crop=(image * 255 + 0.5).astype(np.uint8),
            axes=render_axis_keypoints(kp, S),
            keypoints=kp,
            obj_id=obj_id,
            K=self.K,
            K_crop=Kc,
            R=R,
            t=t,
            center=(float(center[0]), float(center[1])),
            side=float(side),
            visib=visib,
            mask_visib=mask_visib,
            mask=full,
            points=np.where(mask_visib[..., None], res.points, np.float32(0)),
        )

    def _inside_frame(self, center: tuple[float, float], side: float) -> np.ndarray:
        """Crop pixels whose centre lies on the frame (crop_image's bilinear footprint), as a (size, size) mask."""
        S = self.cfg.size
        coords = center[0] - 0.5 * side + (np.arange(S) + 0.5) * side / S, center[1] - 0.5 * side + (np.arange(S) + 0.5) * side / S
        inx = (coords[0] > -1.0) & (coords[0] < self.cfg.width)
        iny = (coords[1] > -1.0) & (coords[1] < self.cfg.height)
        return iny[:, None] & inx[None, :]

    def _occluder(
        self, rng: np.random.Generator, obj_id: int, z_front: float, Kc: np.ndarray, lit: Light, apparent: float
    ) -> tuple[np.ndarray, np.ndarray] | None:
        """An object or primitive wholly nearer than `z_front` (the target's nearest possible depth), about
        `apparent` crop pixels across, rendered alone on a square canvas around it through the crop's focal
        lengths: (rgb, mask), or None if none fits."""
        S = self.cfg.size
        f = 0.5 * (Kc[0, 0] + Kc[1, 1])
        other = self._other(rng, obj_id)
        if other is not None:  # an object: its depth follows from its apparent size, and must lie in front
            r = 0.5 * self.models[other].spec.diameter
            z = min(2 * r * f / apparent, z_front - r - 0.01)
            mesh = self._tinted(rng, other, 2 * r * f / max(z, 1e-3))
        else:
            z = rng.uniform(0.35, 0.9) * z_front
            r = min(0.5 * apparent * z / f, z_front - z - 0.01)
            if r <= 0.002:
                return None
            mesh = self._primitive(rng, r)
        if z - r < 0.06:  # the renderer drops triangles nearer than 5 cm
            return None
        canvas = int(np.ceil(2 * f * r / np.sqrt(z * z - r * r))) + 4
        if canvas > 2 * S:
            return None
        Ko = np.array([[Kc[0, 0], 0.0, 0.5 * (canvas - 1)], [0.0, Kc[1, 1], 0.5 * (canvas - 1)], [0.0, 0.0, 1.0]])
        res = render([(mesh, Rotation.random(random_state=rng).as_matrix(), np.array([0.0, 0.0, z]))], Ko, canvas, canvas, lit)
        mask = res.instance == 0
        return (res.rgb, mask) if mask.any() else None

    def _placement(
        self, rng: np.random.Generator, visible: np.ndarray, n_full: int, occ: np.ndarray, want: float | None
    ) -> tuple[int, int] | None:
        """Top-left crop position (x, y) of the occluder canvas: one that leaves `want` of the silhouette visible
        (within VISIB_TOL, else the nearest), or with want None one beside the target, hiding none of it."""
        S, c = self.cfg.size, occ.shape[0]
        # overlap[k] for canvas origin o = k - (c - 1): pixels of `visible` the occluder covers there.
        overlap = np.rint(fftconvolve(visible.astype(np.float32), occ[::-1, ::-1].astype(np.float32), mode="full"))
        # Occluder pixels inside the crop at each origin: box sums of the mask over the S x S window, from its integral.
        integral = cv2.integral(np.pad(occ.astype(np.uint8), S - 1))
        in_crop = integral[S:, S:] - integral[:-S, S:] - integral[S:, :-S] + integral[:-S, :-S]
        in_crop = in_crop[::-1, ::-1]
        present = in_crop >= 0.1 * min(occ.sum(), S * S)
        if want is None:
            ok = present & (overlap == 0)
        else:
            vis = (visible.sum() - overlap) / n_full
            ok = present & (np.abs(vis - want) <= VISIB_TOL)
            if not ok.any():
                gap = np.where(present, np.abs(vis - want), np.inf)
                ok = gap == gap.min()
        cand = np.flatnonzero(ok)
        if not len(cand):
            return None
        ky, kx = np.unravel_index(cand[int(rng.integers(len(cand)))], ok.shape)
        return int(kx) - (c - 1), int(ky) - (c - 1)

    @staticmethod
    def _paste(image: np.ndarray, rgb: np.ndarray, mask: np.ndarray, where: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        """Lay the occluder canvas (top-left at crop pixel `where`) over the image: (covered mask, new image)."""
        S, c = image.shape[0], mask.shape[0]
        x, y = where
        x0, y0, x1, y1 = max(0, x), max(0, y), min(S, x + c), min(S, y + c)
        covered = np.zeros((S, S), bool)
        covered[y0:y1, x0:x1] = mask[y0 - y : y1 - y, x0 - x : x1 - x]
        out = image.copy()
        out[y0:y1, x0:x1][covered[y0:y1, x0:x1]] = rgb[y0 - y : y1 - y, x0 - x : x1 - x][covered[y0:y1, x0:x1]]
        return covered, out

    def _camera(self, rng: np.random.Generator, image: np.ndarray, center: tuple[float, float], side: float) -> np.ndarray:
        """The camera's effects at the frame's own resolution there: a crop cut from fewer frame pixels than it has
        is blurred, noisy and blocky at that scale, then resampled up (as crop_image's bilinear warp does); lens
        effects grow with the crop's distance from the frame's centre."""
        S, sensor = self.cfg.size, self.cfg.randomization.sensor
        quality = int(rng.integers(sensor.jpeg_quality[0], sensor.jpeg_quality[1] + 1))
        n = round(side)
        where = {"origin": (center[0] - 0.5 * side, center[1] - 0.5 * side), "frame": (self.cfg.width, self.cfg.height)}
        if n < S:
            small = cv2.resize(image, (n, n), interpolation=cv2.INTER_AREA)
            small = jpeg(camera_effects(rng, sensor, small, **where), quality)  # n ~ side: one frame px per px
            return cv2.resize(small, (S, S), interpolation=cv2.INTER_LINEAR)
        return jpeg(camera_effects(rng, sensor, image, scale=S / side, **where), quality)


class CropStreamDataset(Dataset):
    """The stream as training tensors (crop uint8 and axes in [-1, 1], channels first; object index; K', R, t; visible
    fraction; keypoints; surface points in units of the object's radius and the visible mask, at the crop's
    resolution: `train/losses.py`'s `dense_targets` brings them to the encoder's). Index i is sample i;
    `stream_loader` batches it in worker processes."""

    def __init__(self, stream: CropStream) -> None:
        self.stream = stream

    @staticmethod
    def worker_init(_: int) -> None:
        """DataLoader's worker_init_fn: one OpenCV thread per worker, since the workers already fill the cores."""
        cv2.setNumThreads(1)

    def __len__(self) -> int:
        return 2**62

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        s = self.stream[i]
        pts = s.points / np.float32(0.5 * self.stream.models[s.obj_id].spec.diameter)
        return {
            "crop": torch.from_numpy(s.crop).permute(2, 0, 1),
            "axes": torch.from_numpy(s.axes * 2 - 1).permute(2, 0, 1),
            "object": torch.tensor(self.stream.index[s.obj_id]),
            "K": torch.from_numpy(s.K_crop),
            "R": torch.from_numpy(s.R),
            "t": torch.from_numpy(s.t),
            "visib": torch.tensor(s.visib),
            "keypoints": torch.from_numpy(s.keypoints),
            "points": torch.from_numpy(pts.astype(np.float32)).permute(2, 0, 1),
            "mask_visib": torch.from_numpy(s.mask_visib.astype(np.float32))[None],
        }


def stream_loader(
    stream: CropStream, batch_size: int, start: int = 0, stop: int | None = None, workers: int = 0, stride: int = 1
) -> DataLoader:
    """Batches of samples start, start + stride, ... (endless without `stop`), in order whatever the number of
    worker processes, so a run resumes by starting at the samples it has used (`stride`: one of several ranks).
    Workers are spawned, not forked: a fork of a process whose OpenCV thread pool has run can hang in the child."""
    if batch_size < 1 or workers < 0 or stride < 1:
        raise ValueError(f"batch_size and stride must be >= 1 and workers >= 0, got {batch_size}, {stride} and {workers}")
    sampler = range(start, stop if stop is not None else 2**62, stride)
    return DataLoader(
        CropStreamDataset(stream),
        batch_size=batch_size,
        sampler=sampler,
        num_workers=workers,
        multiprocessing_context="spawn" if workers else None,
        worker_init_fn=CropStreamDataset.worker_init if workers else None,
        persistent_workers=workers > 0,
        prefetch_factor=4 if workers else None,
    )
