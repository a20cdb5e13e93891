"""`axispose synth`: render randomised scenes of known objects into a BOP-format dataset.

Layout of OUT (BOP "train_pbr"-like): ``synth_config.json``, ``models_info.json``, and one folder per scene
``000000/`` with ``rgb/000000.jpg``, ``mask/000000_000000.png`` (full silhouette), ``mask_visib/...``,
``scene_gt.json``, ``scene_camera.json`` and ``scene_gt_info.json``. A scene's JSON files are written last,
so a scene with ``scene_gt_info.json`` is complete; a rerun skips complete scenes and redoes the rest, which
makes generation resumable. Every image draws from its own generator seeded by (seed, scene, image), so the
output does not depend on the number of workers or on resumption.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import shutil
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation
from tqdm import tqdm

from axispose_core.data.bop import (
    GTInfo,
    GTInstance,
    bbox_from_mask,
    bbox_from_model,
    write_depth,
    write_scene_camera,
    write_scene_gt,
    write_scene_gt_info,
)
from axispose_core.data.bop_models import load_models_info
from axispose_core.data.meshes import load_render_mesh
from axispose_core.data.synth.clutter import distractor_mesh, lookalike
from axispose_core.data.synth.config import TABLE_TEXTURE, CameraPathConfig, SynthConfig
from axispose_core.data.synth.randomize import background, camera_effects, cutouts, light, motion_blur, object_tint
from axispose_core.data.synth.raster import Light, RenderMesh, render
from axispose_core.data.synth.scene import Placement, primitive, sample_scene
from axispose_core.data.synth.table import Table, light_from_above, rest_on, shade_table, table_pixels
from axispose_core.objects import NAMES_FILE

DEPTH_SCALE = 0.1
"""mm per unit of the depth images (BOP's PBR scenes use the same): 0.1 mm steps up to 6.5 m."""


@dataclass
class SynthImage:
    """One rendered frame with its annotations (instances in scene_gt order)."""

    rgb: np.ndarray
    jpeg_quality: int
    gt: list[GTInstance]
    info: list[GTInfo]
    masks: list[np.ndarray]
    masks_visib: list[np.ndarray]
    depth: np.ndarray
    """Of the meshes (m; inf elsewhere, 0 under cut-outs)."""
    table: Table | None = None
    """The table top the objects rest on, if the frame has one."""
    camera: tuple[np.ndarray, np.ndarray] | None = None
    """Along a camera path: the camera's pose, world (the first camera's frame) to this camera (R, t in m)."""


@dataclass
class World:
    """What one image (or, along a camera path, one scene) shows before the camera renders it: the posed meshes
    (camera frame; target objects where `placements` has an obj_id), the table, the background and the light."""

    placements: list[Placement]
    posed: list[tuple[RenderMesh, np.ndarray, np.ndarray]]
    table: Table | None
    background: np.ndarray
    light: Light
    shadows: bool


def sample_world(cfg: SynthConfig, meshes: dict[int, RenderMesh], diameters: dict[int, float], rng: np.random.Generator) -> World:
    """Objects, distractors, table, background and light, drawn from `rng`."""
    K = np.asarray(cfg.K, dtype=np.float64).reshape(3, 3)
    w, h = cfg.width, cfg.height
    rcfg = cfg.randomization
    radii = {i: 0.5 * diameters[i] for i in meshes}
    table_top = None
    if cfg.scene.table_prob > 0 and rng.uniform() < cfg.scene.table_prob:
        table_top = background(rng, rcfg.table_top, TABLE_TEXTURE, TABLE_TEXTURE), rng.uniform(*cfg.scene.table_texel)
    placements, table = sample_scene(rng, cfg.scene, radii, K, w, h, table_top)
    own_faces = frozenset(len(m.faces) for m in meshes.values())
    palettes = [meshes[i].colors for i in sorted(meshes)]
    posed = []
    for i, p in enumerate(placements):
        if p.obj_id:
            m = meshes[p.obj_id]
            m = RenderMesh(m.vertices, m.faces, np.clip(m.colors * object_tint(rng, rcfg.light), 0, 1), m.normals)
        elif cfg.scene.distractor_meshes > 0 and rng.uniform() < cfg.scene.distractor_meshes:
            m = distractor_mesh(rng, p.radius, cfg.scene.distractor_split, rcfg.background, own_faces)
        else:
            m = primitive(rng, p.radius)
        if not p.obj_id and cfg.scene.lookalike_prob > 0 and rng.uniform() < cfg.scene.lookalike_prob:
            m = lookalike(rng, m, palettes, object_tint(rng, rcfg.light))
        if table is not None:
            placements[i] = p = Placement(p.obj_id, p.R, rest_on(table, m, p.R, p.t), p.radius)
        posed.append((m, p.R, p.t))
    bg = background(rng, rcfg.background, w, h)
    lit = light(rng, rcfg.light)
    if table is not None:
        lit = light_from_above(lit, table, rng)
    shadows = rcfg.light.shadows > 0 and rng.uniform() < rcfg.light.shadows
    return World(placements, posed, table, bg, lit, shadows)


def moved(world: World, R: np.ndarray, t: np.ndarray) -> World:
    """The world seen by a camera that moved: every camera-frame point p becomes R p + t."""
    placements = [Placement(p.obj_id, R @ p.R, R @ p.t + t, p.radius) for p in world.placements]
    posed = [(m, R @ Rm, R @ tm + t) for m, Rm, tm in world.posed]
    table = None if world.table is None else world.table.transformed(R, t)
    return World(placements, posed, table, world.background, world.light, world.shadows)


def _target_centre(world: World) -> np.ndarray:
    """The mean position of the world's target objects (of every placement where it has none): what a path orbits."""
    return np.mean([p.t for p in world.placements if p.obj_id] or [p.t for p in world.placements], axis=0)


def camera_motion(path: CameraPathConfig, world: World, count: int, rng: np.random.Generator) -> list[tuple[np.ndarray, np.ndarray]]:
    """The first camera's points in each of `count` cameras along the path, (R, t) per image (identity first):
    an orbit about the target objects' centre, composed with a random walk of the camera's pose and a sweep of
    its view about its own centre."""
    centre = _target_centre(world)
    axis = world.table.normal if world.table is not None else np.array([0.0, -1.0, 0.0])
    phase = rng.uniform(0, 2 * np.pi, 2) if path.sweep_deg > 0 else np.zeros(2)
    shake_R, shake_t = np.eye(3), np.zeros(3)
    out = []
    for k in range(count):
        if k:
            shake_R = Rotation.from_rotvec(rng.normal(0.0, np.radians(path.shake_deg), 3)).as_matrix() @ shake_R
            shake_t = shake_t + rng.normal(0.0, path.shake_m, 3)
        orbit = Rotation.from_rotvec(-np.radians(path.orbit_deg * k) * axis).as_matrix()
        R = shake_R @ orbit
        t = shake_R @ (centre - orbit @ centre) + shake_t
        if path.sweep_deg > 0:  # pan about the camera's y, tilt about its x, both starting at zero
            w = 2 * np.pi * k / path.sweep_frames
            pan = path.sweep_deg * (np.sin(w + phase[0]) - np.sin(phase[0]))
            tilt = 0.5 * path.sweep_deg * (np.sin(w / 1.6 + phase[1]) - np.sin(phase[1]))
            sweep = Rotation.from_euler("yx", [pan, tilt], degrees=True).as_matrix()
            R, t = sweep @ R, sweep @ t
        out.append((R, t))
    return out


@dataclass(frozen=True)
class Passer:
    """An occluder crossing the view: its mesh, rotation, the image it enters at, its height and depth in the
    camera's frame (m) and the side it comes from (±1)."""

    mesh: RenderMesh
    R: np.ndarray
    start: int
    y: float
    z: float
    side: float

    def pose(self, k: int, frames: int, K: np.ndarray, width: int) -> tuple[np.ndarray, np.ndarray] | None:
        """Its camera-frame pose at image k, None outside its crossing (from beyond one edge to beyond the other)."""
        if not self.start <= k < self.start + frames:
            return None
        reach = self.z * (0.5 * width / K[0, 0]) + float(np.linalg.norm(self.mesh.vertices, axis=1).max())
        x = self.side * reach * (2 * (k - self.start) / max(1, frames - 1) - 1)
        return self.R, np.array([x + self.z * (K[0, 2] - 0.5 * width) / K[0, 0], self.y, self.z])


def passers(cfg: SynthConfig, world: World, rng: np.random.Generator) -> list[Passer]:
    """The scene's occluders that cross the view (`CameraPathConfig.passers`): library meshes 4-8 cm across at 40-80 %
    of the objects' depth."""
    path = cfg.camera_path
    if path is None or path.passers <= 0:
        return []
    depth = float(np.median([p.t[2] for p in world.placements if p.obj_id] or [0.8]))
    out = []
    for _ in range(path.passers):
        mesh = distractor_mesh(rng, rng.uniform(0.04, 0.08), cfg.scene.distractor_split, cfg.randomization.background)
        start = int(rng.integers(0, max(1, cfg.images_per_scene - path.pass_frames)))
        z = depth * rng.uniform(0.4, 0.8)
        y = z * rng.uniform(-0.25, 0.25) * cfg.height / (np.asarray(cfg.K).reshape(3, 3)[1, 1])
        out.append(Passer(mesh, Rotation.random(random_state=int(rng.integers(2**31))).as_matrix(), start, y, z, rng.choice([-1.0, 1.0])))
    return out


@dataclass(frozen=True)
class Exposure:
    """A frame of a camera path: the camera's settings (lens, white balance, tone; drawn from `sensor`, the scene's
    generator, so every frame shares them), the frame's smear (length in px, angle in degrees) and gain."""

    sensor: np.random.Generator
    smear: tuple[float, float] = (0.0, 0.0)
    gain: float = 1.0


def render_world(cfg: SynthConfig, world: World, meshes: dict[int, RenderMesh], rng: np.random.Generator,
                 exposure: Exposure | None = None) -> SynthImage:  # fmt: skip
    """The camera's image of `world`: render, table, cut-outs, lens and sensor (from `rng`), and the annotations;
    a camera path's frame (`exposure`) without cut-outs (its occluders move through the world), with its smear,
    gain and the camera's settings."""
    K = np.asarray(cfg.K, dtype=np.float64).reshape(3, 3)
    w, h = cfg.width, cfg.height
    rcfg, table, placements = cfg.randomization, world.table, world.placements
    res = render(world.posed, K, w, h, world.light, world.shadows)
    bg = world.background
    if table is not None:
        points, table_depth = table_pixels(table, K, w, h)
        bg = np.where(np.isfinite(table_depth)[..., None], shade_table(table, points, table_depth, world.light, res.shadows), bg)
    image = np.where(res.instance[..., None] >= 0, res.rgb.astype(np.float32), bg)
    if exposure is None:
        occluded = cutouts(rng, rcfg, image)
        image = camera_effects(rng, rcfg.sensor, image)
    else:
        occluded = np.zeros(image.shape[:2], dtype=bool)
        if exposure.smear[0] >= 0.5:
            image = motion_blur(image, *exposure.smear)
        image = camera_effects(exposure.sensor, rcfg.sensor, np.clip(image * np.float32(exposure.gain), 0, 1), noise=rng)
    quality = int(rng.integers(rcfg.sensor.jpeg_quality[0], rcfg.sensor.jpeg_quality[1] + 1))
    gt, info, masks, masks_visib = [], [], [], []
    for i, p in enumerate(placements):
        if not p.obj_id:
            continue
        full = res.full[i]
        visib = (res.instance == i) & ~occluded
        n_all, n_vis = int(full.sum()), int(visib.sum())
        gt.append(GTInstance(p.obj_id, p.R, p.t))
        info.append(
            GTInfo(
                bbox_obj=bbox_from_model(K, p.R, p.t, meshes[p.obj_id].vertices),
                bbox_visib=bbox_from_mask(visib),
                px_count_all=n_all,
                px_count_valid=n_all,
                px_count_visib=n_vis,
                visib_fract=n_vis / n_all if n_all else 0.0,
            )
        )
        masks.append(full)
        masks_visib.append(visib)
    depth = np.where(occluded, 0.0, res.depth)
    return SynthImage((image * 255 + 0.5).astype(np.uint8), quality, gt, info, masks, masks_visib, depth, table)


def render_image(cfg: SynthConfig, meshes: dict[int, RenderMesh], diameters: dict[int, float], scene_id: int, im_id: int) -> SynthImage:
    """Sample, render and randomise one frame deterministically from (cfg.seed, scene_id, im_id). Along a camera
    path, the scene's world is image 0's and only the camera and its sensor noise change."""
    if cfg.camera_path is None:
        rng = np.random.default_rng([cfg.seed, scene_id, im_id])
        return render_world(cfg, sample_world(cfg, meshes, diameters, rng), meshes, rng)
    rng = np.random.default_rng([cfg.seed, scene_id, 0])
    world = sample_world(cfg, meshes, diameters, rng)
    path = cfg.camera_path
    cameras = camera_motion(path, world, im_id + 1, np.random.default_rng([cfg.seed, scene_id, 0, 1]))
    R, t = cameras[im_id]
    seen = moved(world, R, t)
    K = np.asarray(cfg.K, dtype=np.float64).reshape(3, 3)
    for passer in passers(cfg, world, np.random.default_rng([cfg.seed, scene_id, 0, 3])):
        if (pose := passer.pose(im_id, path.pass_frames, K, cfg.width)) is not None:
            radius = float(np.linalg.norm(passer.mesh.vertices, axis=1).max())
            seen.placements.append(Placement(0, *pose, radius))
            seen.posed.append((passer.mesh, *pose))
    scene_rngs = (np.random.default_rng([cfg.seed, scene_id, 0, 4]), np.random.default_rng([cfg.seed, scene_id, 0, 5]))
    frame = render_world(cfg, seen, meshes, np.random.default_rng([cfg.seed, scene_id, im_id, 2]), _exposure(path, world, cameras, K,
                         *scene_rngs))  # fmt: skip
    return replace(frame, camera=(R, t))


def _exposure(path: CameraPathConfig, world: World, cameras: list[tuple[np.ndarray, np.ndarray]], K: np.ndarray,
              gains: np.random.Generator, sensor: np.random.Generator) -> Exposure:  # fmt: skip
    """The last camera's smear (the objects' centre's image motion since the camera before, times the shutter) and
    gain (a random walk along the path, drawn from `gains`, the scene's: each image draws the same steps before its
    own), with the scene's `sensor` generator for the camera's settings."""
    smear = (0.0, 0.0)
    if path.shutter > 0 and len(cameras) > 1:
        centre = _target_centre(world)
        (R0, t0), (R1, t1) = cameras[-2], cameras[-1]
        a, b = K @ (R0 @ centre + t0), K @ (R1 @ centre + t1)
        d = b[:2] / b[2] - a[:2] / a[2]
        smear = (path.shutter * float(np.hypot(*d)), float(np.degrees(np.arctan2(d[1], d[0]))))
    gain = 1.0
    if path.gain_walk > 0:
        steps = gains.normal(0.0, path.gain_walk, len(cameras))
        steps[0] = 0.0
        gain = float(np.exp(np.clip(np.cumsum(steps)[-1], -0.4, 0.4)))
    return Exposure(sensor, smear, gain)


def generate_scene(cfg: SynthConfig, meshes: dict[int, RenderMesh], diameters: dict[int, float], out: Path, scene_id: int) -> int:
    """Write one complete scene folder; returns the number of images."""
    folder = out / f"{scene_id:06d}"
    for sub in ("rgb", "mask", "mask_visib"):
        (folder / sub).mkdir(parents=True, exist_ok=True)
    K = np.asarray(cfg.K, dtype=np.float64).reshape(3, 3)
    gts, infos, cams, poses = {}, {}, {}, {}
    for im_id in range(cfg.images_per_scene):
        frame = render_image(cfg, meshes, diameters, scene_id, im_id)
        cv2.imwrite(str(folder / "rgb" / f"{im_id:06d}.jpg"), frame.rgb[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, frame.jpeg_quality])
        for k, (full, vis) in enumerate(zip(frame.masks, frame.masks_visib, strict=True)):
            cv2.imwrite(str(folder / "mask" / f"{im_id:06d}_{k:06d}.png"), full.astype(np.uint8) * 255)
            cv2.imwrite(str(folder / "mask_visib" / f"{im_id:06d}_{k:06d}.png"), vis.astype(np.uint8) * 255)
        gts[im_id], infos[im_id], cams[im_id] = frame.gt, frame.info, K
        if frame.camera is not None:
            poses[im_id] = frame.camera
        if cfg.depth:
            write_depth(folder / "depth" / f"{im_id:06d}.png", frame.depth, DEPTH_SCALE)
    write_scene_gt(folder / "scene_gt.json", gts)
    write_scene_camera(folder / "scene_camera.json", cams, DEPTH_SCALE, poses)
    write_scene_gt_info(folder / "scene_gt_info.json", infos)  # last: marks the scene complete
    return cfg.images_per_scene


def scene_complete(out: Path, scene_id: int) -> bool:
    return (out / f"{scene_id:06d}" / "scene_gt_info.json").exists()


_WORKER: dict = {}
_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def _init_worker(cfg: SynthConfig, models_dir: str, cache: str, diameters: dict[int, float]) -> None:
    cv2.setNumThreads(1)
    _WORKER.update(cfg=cfg, meshes={i: load_render_mesh(models_dir, i, cache) for i in cfg.objects}, diameters=diameters)


def _scene_task(args: tuple[str, int]) -> int:
    out, scene_id = args
    return generate_scene(_WORKER["cfg"], _WORKER["meshes"], _WORKER["diameters"], Path(out), scene_id)


def generate(
    cfg: SynthConfig,
    models_dir: str | Path,
    out: str | Path,
    workers: int = 1,
    progress: bool = True,
    mesh_cache: str | Path | None = None,
) -> int:
    """Generate (or finish) the dataset `cfg` describes into `out`; returns the number of images written now.

    Parsed meshes are cached in `mesh_cache` (default OUT/.mesh_cache), which several datasets may share.
    """
    out, models_dir = Path(out), Path(models_dir)
    infos = load_models_info(models_dir / "models_info.json")
    objects = cfg.objects or tuple(sorted(infos))
    missing = [i for i in objects if i not in infos]
    if missing:
        raise ValueError(f"{models_dir / 'models_info.json'} has no object(s) {missing}")
    cfg = SynthConfig(**{**cfg.__dict__, "objects": tuple(int(i) for i in objects)})
    out.mkdir(parents=True, exist_ok=True)
    cfg_path = out / "synth_config.json"
    if cfg_path.exists() and SynthConfig.load(cfg_path) != cfg:
        raise ValueError(f"{out} holds data of a different configuration ({cfg_path}); choose another --out")
    cfg.save(cfg_path)
    shutil.copyfile(models_dir / "models_info.json", out / "models_info.json")
    if (models_dir / NAMES_FILE).exists():
        shutil.copyfile(models_dir / NAMES_FILE, out / NAMES_FILE)
    cache = Path(mesh_cache) if mesh_cache is not None else out / ".mesh_cache"
    for i in cfg.objects:  # parse the PLYs once here, so workers start from the cache
        load_render_mesh(models_dir, i, cache)
    diameters = {i: infos[i].diameter for i in cfg.objects}
    pending = [s for s in range(cfg.scenes) if not scene_complete(out, s)]
    bar = tqdm(total=len(pending) * cfg.images_per_scene, desc="synth", unit="img", disable=not progress)
    done = 0
    if workers <= 1:
        _init_worker(cfg, str(models_dir), str(cache), diameters)
        for s in pending:
            done += _scene_task((str(out), s))
            bar.update(cfg.images_per_scene)
    else:
        ctx = mp.get_context("spawn")
        # One BLAS/OpenMP thread per worker: the workers already fill the cores, more threads only contend.
        saved = {k: os.environ.get(k) for k in _THREAD_VARS}
        os.environ.update(dict.fromkeys(_THREAD_VARS, "1"))
        try:
            with ctx.Pool(workers, initializer=_init_worker, initargs=(cfg, str(models_dir), str(cache), diameters)) as pool:
                for n in pool.imap_unordered(_scene_task, [(str(out), s) for s in pending]):
                    done += n
                    bar.update(n)
        finally:
            for k, v in saved.items():
                if v is None:
                    os.environ.pop(k, None)
                else:
                    os.environ[k] = v
    bar.close()
    return done
