"""Boxes and visibility of annotated instances where a scene has no scene_gt_info.json (real recordings, many
published scenes), as bop_toolkit's calc_gt_info makes them: bbox_obj from the model at the GT pose, the visible
mask from a z-buffer of the frame's annotated instances. Objects that were not annotated cannot hide anything
here, so the visible fraction is an upper bound of the true one. `axispose gt-info` writes the file
(`write_gt_info`); readers that need the values now take `gt_info_from_models` (the BOP reader never renders)."""

from __future__ import annotations

from collections.abc import Callable
from functools import lru_cache
from pathlib import Path

import numpy as np

from axispose_core.data.bop import BopFormatError, GTInfo, GTInstance, bbox_from_mask, bbox_from_model, read_bgr, write_scene_gt_info
from axispose_core.data.bop_models import model_path
from axispose_core.data.bop_scene import BopScene
from axispose_core.data.meshes import load_render_mesh
from axispose_core.data.synth.raster import Light, RenderMesh, render

_LIGHT = Light(np.array([0.0, 0.0, 1.0]), np.ones(3), 1.0)  # shading is not looked at


@lru_cache(maxsize=64)
def _mesh(models_dir: Path, obj_id: int) -> RenderMesh:
    if not model_path(models_dir, obj_id).exists():
        raise BopFormatError(f"{model_path(models_dir, obj_id)}: no model for object {obj_id}, needed to estimate its visibility")
    return load_render_mesh(models_dir, obj_id)


def estimate_gt_info(K: np.ndarray, gts: list[GTInstance], models_dir: str | Path, width: int, height: int) -> list[GTInfo]:
    """scene_gt_info.json entries for one frame's instances, from their models rendered together at the GT poses."""
    models_dir = Path(models_dir)
    meshes = [_mesh(models_dir, g.obj_id) for g in gts]
    res = render([(m, g.R, g.t) for m, g in zip(meshes, gts, strict=True)], K, width, height, _LIGHT)
    infos = []
    for k, (m, g) in enumerate(zip(meshes, gts, strict=True)):
        n_all, visible = int(res.full[k].sum()), res.instance == k
        n_vis = int(visible.sum())
        infos.append(
            GTInfo(
                bbox_obj=bbox_from_model(K, g.R, g.t, m.vertices),
                bbox_visib=bbox_from_mask(visible),
                px_count_all=n_all,
                px_count_valid=n_all,
                px_count_visib=n_vis,
                visib_fract=n_vis / n_all if n_all else 0.0,
            )
        )
    return infos


def gt_info_from_models(models_dir: str | Path | None) -> Callable[[BopScene, int], list[GTInfo]] | None:
    """`BopScene.estimate_info` from the object models in `models_dir` (None: no estimate, a scene without
    scene_gt_info.json is then an error that says how to write it)."""
    if models_dir is None:
        return None

    def estimate(scene: BopScene, im_id: int) -> list[GTInfo]:
        h, w = read_bgr(scene.rgb_path(im_id)).shape[:2]
        return estimate_gt_info(scene.cameras[im_id], scene.gt[im_id], models_dir, w, h)

    return estimate


def write_gt_info(scene_dir: str | Path, models_dir: str | Path, overwrite: bool = False) -> bool:
    """Write the scene's scene_gt_info.json from the models; False where it has one already (and not `overwrite`)."""
    scene = BopScene(Path(scene_dir), gt_info_from_models(models_dir))
    if scene.gt_info is not None and not overwrite:
        return False
    scene.gt_info = None  # estimate even over an existing file
    infos = {im_id: [info for _, info in scene.instances(im_id)] for im_id in scene.image_ids}
    write_scene_gt_info(scene.root / "scene_gt_info.json", infos)
    return True
