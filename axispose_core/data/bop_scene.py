"""A BOP scene folder as frames: its images with their camera and GT instances (`BopScene`), and the scenes of a
split or dataset folder (`scene_dirs`, `bop_frames`). It reads the files through `bop.py` and never renders."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from axispose_core.data.bop import (
    BopFormatError,
    GTInfo,
    GTInstance,
    load_camera_poses,
    load_depth_scales,
    load_scene_camera,
    load_scene_gt_info,
    read_bgr,
    read_depth,
    read_scene_gt,
)

_NO_GT_INFO = (
    "{root}: no scene_gt_info.json; write it with `axispose gt-info {root} --models MODELS`, or give the "
    "object models to estimate the instances' boxes and visibility"
)


@dataclass
class BopScene:
    """One scene folder (``rgb/``, ``scene_gt.json``, ``scene_camera.json``, optional ``scene_gt_info.json``).

    Real recordings and many published scenes have no scene_gt_info.json. This reader never renders: such a scene
    gets its boxes and visibility from `estimate_info(scene, im_id)`, which the caller passes in (e.g.
    `data/visibility.py`'s `gt_info_from_models`; `visibility_estimated` says so), or `axispose gt-info` writes
    the file once.
    """

    root: Path
    estimate_info: Callable[[BopScene, int], list[GTInfo]] | None = None
    gt: dict[int, list[GTInstance]] = field(init=False)
    cameras: dict[int, np.ndarray] = field(init=False)
    gt_info: dict[int, list[GTInfo]] | None = field(init=False)
    camera_poses: dict[int, tuple[np.ndarray, np.ndarray]] = field(init=False)
    """The camera's pose (world to camera, t in m) of the images scene_camera.json gives one for."""
    rotations_projected: int = field(init=False)
    """GT rotations of scene_gt.json that were not orthonormal and were projected (`read_scene_gt`)."""

    def __post_init__(self) -> None:
        self.root = Path(self.root)
        gt = read_scene_gt(self.root / "scene_gt.json")
        self.gt, self.rotations_projected = gt.instances, gt.projected
        self.cameras = load_scene_camera(self.root / "scene_camera.json")
        self.camera_poses = load_camera_poses(self.root / "scene_camera.json")
        info_path = self.root / "scene_gt_info.json"
        self.gt_info = load_scene_gt_info(info_path) if info_path.exists() else None
        self._estimated: dict[int, list[GTInfo]] = {}
        self._depth_scales: dict[int, float] | None = None
        for im_id in self.gt:
            if im_id not in self.cameras:
                raise BopFormatError(f"{self.root / 'scene_camera.json'}: image {im_id} of scene_gt.json has no camera")
            if self.gt_info is not None and len(self.gt_info.get(im_id, [])) != len(self.gt[im_id]):
                raise BopFormatError(f"{info_path}: image {im_id}: instance count differs from scene_gt.json")

    @property
    def image_ids(self) -> list[int]:
        return sorted(self.gt)

    @property
    def visibility_estimated(self) -> bool:
        """Whether boxes and visibility come from the models (no scene_gt_info.json) rather than the files."""
        return self.gt_info is None

    def rgb_path(self, im_id: int) -> Path:
        """The image file (PNG or JPEG, as BOP allows both)."""
        for ext in (".png", ".jpg", ".jpeg"):
            p = self.root / "rgb" / f"{im_id:06d}{ext}"
            if p.exists():
                return p
        raise BopFormatError(f"{self.root / 'rgb'}: no image file for image {im_id}")

    def rgb(self, im_id: int) -> np.ndarray:
        """The image as HxWx3 uint8 RGB; an unreadable file is a BopFormatError, not a None further on."""
        return cv2.cvtColor(read_bgr(self.rgb_path(im_id)), cv2.COLOR_BGR2RGB)

    def depth(self, im_id: int) -> np.ndarray | None:
        """The image's depth in metres (0: no measurement), None where the scene has no depth image."""
        path = self.root / "depth" / f"{im_id:06d}.png"
        if not path.exists():
            return None
        if self._depth_scales is None:
            self._depth_scales = load_depth_scales(self.root / "scene_camera.json")
        return read_depth(path, self._depth_scales[im_id])

    def instances(self, im_id: int) -> list[tuple[GTInstance, GTInfo]]:
        """Each GT instance of the image with its boxes and visibility, in file order: scene_gt_info.json's, else
        estimated by `estimate_info` (which the scene must then have been given)."""
        if self.gt_info is not None:
            return list(zip(self.gt[im_id], self.gt_info[im_id], strict=True))
        if self.estimate_info is None:
            raise BopFormatError(_NO_GT_INFO.format(root=self.root))
        if im_id not in self._estimated:
            self._estimated[im_id] = self.estimate_info(self, im_id)
        return list(zip(self.gt[im_id], self._estimated[im_id], strict=True))


def scene_dirs(root: str | Path) -> list[Path]:
    """A scene folder itself, or the scene folders of a BOP split/dataset folder."""
    root = Path(root)
    if (root / "scene_gt.json").exists():
        return [root]
    scenes = sorted(p for p in root.iterdir() if (p / "scene_gt.json").exists()) if root.is_dir() else []
    if not scenes:
        raise BopFormatError(f"{root}: neither a BOP scene folder nor a folder of scenes")
    return scenes


def bop_frames(roots: list[str | Path], estimate_info: Callable[[BopScene, int], list[GTInfo]] | None = None) -> list[tuple[BopScene, int]]:
    """Every (scene, image id) of the BOP folders (each a scene or a folder of scenes), in folder and image order.
    Its users read the instances' boxes and visibility: a scene without scene_gt_info.json has them from
    `estimate_info` (`BopScene`), and without it is a BopFormatError here, before any frame is read."""
    scenes = [BopScene(sd, estimate_info) for root in roots for sd in scene_dirs(root)]
    for scene in scenes:
        if scene.gt_info is None and estimate_info is None:
            raise BopFormatError(_NO_GT_INFO.format(root=scene.root))
    return [(scene, im_id) for scene in scenes for im_id in scene.image_ids]
