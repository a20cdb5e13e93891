"""Contact sheets for a person to judge: `axispose synth-preview` (rendered frames with every instance's GT axes
and visible box) and `axispose stream-preview` (crop-stream samples with their GT axes and visible mask)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from axispose_core.axis_image import AxisSpec, draw_axes
from axispose_core.camera import Camera
from axispose_core.data.bop import read_bgr
from axispose_core.data.bop_models import load_models_info
from axispose_core.data.bop_scene import BopScene, scene_dirs
from axispose_core.data.synth.stream import CropStream


def contact_sheet(data_dir: str | Path, out: str | Path, count: int = 16, columns: int = 4, tile_width: int = 320) -> Path:
    """Tile the first `count` frames of a synthetic BOP dataset, GT axes and bbox_visib drawn, into one PNG."""
    data_dir = Path(data_dir)
    infos = load_models_info(data_dir / "models_info.json")
    tiles = []
    for scene_dir in scene_dirs(data_dir):
        scene = BopScene(scene_dir)
        for im_id in scene.image_ids:
            img = read_bgr(scene.rgb_path(im_id))
            K = scene.cameras[im_id]
            for g, info in scene.instances(im_id):
                if info.visib_fract > 0:
                    x, y, w, h = info.bbox_visib
                    cv2.rectangle(img, (x, y), (x + w - 1, y + h - 1), (255, 255, 255), 1)
                    cv2.putText(
                        img, f"{g.obj_id}:{info.visib_fract:.2f}", (x, max(10, y - 3)), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1
                    )
                draw_axes(img, K, g.R, g.t, AxisSpec.from_diameter(infos[g.obj_id].diameter).lengths)
            scale = tile_width / img.shape[1]
            tiles.append(cv2.resize(img, (tile_width, round(img.shape[0] * scale)), interpolation=cv2.INTER_AREA))
            if len(tiles) == count:
                break
        if len(tiles) == count:
            break
    if not tiles:
        raise ValueError(f"{data_dir}: no complete scene to preview")
    while len(tiles) % columns:
        tiles.append(np.zeros_like(tiles[0]))
    rows = [np.hstack(tiles[i : i + columns]) for i in range(0, len(tiles), columns)]
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(out), np.vstack(rows), [cv2.IMWRITE_PNG_COMPRESSION, 9])
    return out


def stream_sheet(stream: CropStream, out: str | Path, start: int = 0, count: int = 32, columns: int = 8, scale: int = 4) -> Path:
    """Tile crop-stream samples start .. start+count-1, enlarged `scale` times, with their GT axes, the outline
    of the target's visible mask and `obj_id:visib`, into one PNG."""
    if count < 1:
        raise ValueError(f"count must be at least 1, got {count}")
    tiles = []
    for i in range(start, start + count):
        s = stream[i]
        size = s.crop.shape[0] * scale
        tile = cv2.resize(s.crop[..., ::-1], (size, size), interpolation=cv2.INTER_NEAREST)
        mask = cv2.resize(s.mask_visib.astype(np.uint8), (size, size), interpolation=cv2.INTER_NEAREST)
        contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        cv2.drawContours(tile, contours, -1, (255, 255, 255), 1)
        K = Camera(s.K_crop, s.crop.shape[1], s.crop.shape[0]).scaled(size, size).K
        draw_axes(tile, K, s.R, s.t, stream.objects[stream.index[s.obj_id]].axes.lengths)
        cv2.putText(tile, f"{s.obj_id}:{s.visib:.2f}", (3, 12), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
        tiles.append(tile)
    while len(tiles) % columns:
        tiles.append(np.zeros_like(tiles[0]))
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(out), np.vstack([np.hstack(tiles[i : i + columns]) for i in range(0, len(tiles), columns)]))
    return out
