"""Rendered twins of real frames: the annotated objects re-rendered at their GT poses and pasted over the frame.

A twin keeps everything of the real frame but the annotated objects' own look: the background, the clutter, the
camera, the poses, the framing and the occlusion among the annotated objects stay; the objects' pixels become
the project's vertex-coloured renders under one fixed light. Scoring a checkpoint on a split and on its twins
tells how much of its error on a camera comes from the objects' appearance (what renders lack) and how much
from the scene. Occluders that are not annotated (a real object in front of an annotated one) are painted over,
so the twins see a little more of each object than the frame does.

A twin can also take only part of the objects' look from the render (`part`), to ask where the real look enters:
the inside of each silhouette or the band along it (`px` wide), the coarse look (shading and colour, below a
Gaussian of σ = `px`) or the fine detail above it; the rest of each object stays the frame's.
"""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np

from axispose_core.data.bop import GTInstance, read_bgr
from axispose_core.data.bop_scene import BopScene, scene_dirs
from axispose_core.data.meshes import load_render_mesh
from axispose_core.data.synth.randomize import wrong_texture
from axispose_core.data.synth.raster import Light, RenderMesh, render

TWIN_LIGHT = Light(np.array([0.0, 0.4, 1.0]) / np.hypot(0.4, 1.0), np.ones(3), ambient=0.45, specular=0.2, shininess=30.0)
"""One light for every twin: from above and behind the camera, a mild highlight."""

PARTS = ("all", "inside", "edge", "coarse", "fine")
"""What of the objects a twin takes from the render: everything; the inside of each silhouette (the band along it
stays the frame's); that band; the coarse look (the frame's detail added); the fine detail (on the frame's coarse
look)."""


@dataclass(frozen=True)
class TwinPart:
    """Which part of the objects' look a twin takes from the render (`PARTS`); `px`: the band's width or the
    Gaussian's σ, in frame pixels."""

    part: str = "all"
    px: float = 3.0

    def __post_init__(self) -> None:
        if self.part not in PARTS:
            raise ValueError(f"part must be one of {', '.join(PARTS)}, got {self.part!r}")
        if self.part != "all" and self.px <= 0:
            raise ValueError(f"px must be > 0, got {self.px}")


_COPIED = ("scene_camera.json", "scene_gt_info.json", "scene_gt.json")
"""scene_gt.json last: a scene counts as written once it is there."""


def twin_frame(
    rgb: np.ndarray, K: np.ndarray, gts: list[GTInstance], meshes: list[RenderMesh], light: Light = TWIN_LIGHT, part: TwinPart = TwinPart()
) -> np.ndarray:
    """`rgb` (H,W,3 uint8) with the instances `gts` (their `meshes`) rendered at their poses over it; where they
    overlap, the nearest wins, as in the frame. `part`: what of the objects comes from the render."""
    h, w = rgb.shape[:2]
    res = render([(m, g.R, g.t) for m, g in zip(meshes, gts, strict=True)], K, w, h, light)
    twin = rgb.copy()
    drawn = res.instance >= 0
    twin[drawn] = np.round(res.rgb[drawn] * 255.0).astype(np.uint8)
    if part.part == "all":
        return twin
    if part.part in ("inside", "edge"):
        inside = _inside(res.instance, len(gts), part.px)
        keep = ~inside if part.part == "inside" else inside  # the frame's pixels there
        return np.where((drawn & keep)[..., None], rgb, twin)
    real, rendered = rgb.astype(np.float32), twin.astype(np.float32)
    real_coarse, rendered_coarse = (cv2.GaussianBlur(im, (0, 0), part.px) for im in (real, rendered))
    if part.part == "coarse":
        mixed = rendered_coarse + (real - real_coarse)
    else:
        mixed = real_coarse + (rendered - rendered_coarse)
    out = rgb.copy()
    out[drawn] = np.clip(np.round(mixed[drawn]), 0, 255).astype(np.uint8)
    return out


def _inside(instance: np.ndarray, count: int, px: float) -> np.ndarray:
    """Pixels farther than `px` from the edge of their instance's silhouette (in the instance map: each instance
    eroded on its own, so the border between two objects is a band too)."""
    r = max(1, round(px))
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    inside = np.zeros(instance.shape, bool)
    for k in range(count):
        inside |= cv2.erode((instance == k).astype(np.uint8), kernel, borderType=cv2.BORDER_REPLICATE).astype(bool)
    return inside


def write_twins(
    data: str | Path, models: str | Path, out: str | Path, light: Light = TWIN_LIGHT, colours: str = "scan", part: TwinPart = TwinPart()
) -> Path:
    """The twins of every scene of the BOP split `data` as a BOP split under `out` (same scene names, same
    annotations, PNG frames); a scene already written is kept. `colours`: the objects' scanned vertex colours
    ("scan"), each object's mean colour ("mean": what shape and shading alone tell) or a wrong surface ("wrong":
    `randomize.wrong_texture`, seeded by the object: what a network reads when the surface misleads). `part`: what
    of the objects comes from the render (`TwinPart`). Returns `out`."""
    if colours not in ("scan", "mean", "wrong"):
        raise ValueError(f"colours must be 'scan', 'mean' or 'wrong', got {colours!r}")
    out = Path(out)
    meshes: dict[int, RenderMesh] = {}
    for scene_dir in scene_dirs(data):
        target = out / scene_dir.name
        if (target / "scene_gt.json").exists():
            continue
        scene = BopScene(scene_dir)
        (target / "rgb").mkdir(parents=True, exist_ok=True)
        for im_id in scene.image_ids:
            gts = scene.gt[im_id]
            for g in gts:
                if g.obj_id not in meshes:
                    meshes[g.obj_id] = _coloured(load_render_mesh(models, g.obj_id), colours, g.obj_id)
            rgb = read_bgr(scene.rgb_path(im_id))[..., ::-1]
            twin = twin_frame(rgb, scene.cameras[im_id], gts, [meshes[g.obj_id] for g in gts], light, part)
            cv2.imwrite(str(target / "rgb" / f"{im_id:06d}.png"), twin[..., ::-1])
        copy_annotations(scene_dir, target)
        record = {"source": str(scene_dir.resolve()), "light": _light_record(light), "colours": colours, "part": part.part, "px": part.px}
        (target / "twins.json").write_text(json.dumps(record, indent=1))
    return out


def copy_annotations(scene_dir: Path, target: Path) -> None:
    """The BOP scene's camera and annotation files into `target`, scene_gt.json last."""
    for name in _COPIED:
        if (scene_dir / name).exists():
            shutil.copy2(scene_dir / name, target / name)


def _coloured(mesh: RenderMesh, colours: str, obj_id: int) -> RenderMesh:
    if colours == "mean":
        return replace(mesh, colors=np.broadcast_to(mesh.colors.mean(axis=0), mesh.colors.shape).copy())
    if colours == "wrong":
        return replace(mesh, colors=wrong_texture(np.random.default_rng(obj_id), mesh.colors, mesh.vertices))
    return mesh


def _light_record(light: Light) -> dict:
    return {"direction": light.direction.tolist(), "color": light.color.tolist(), "ambient": light.ambient,
            "specular": light.specular, "shininess": light.shininess}  # fmt: skip
