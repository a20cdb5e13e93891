"""A user's recording of their scene as `axispose adapt` reads it: frames (an image, K, and the camera's pose in a
fixed frame where odometry gave one), never labels.

A recording is a BOP scene folder: `rgb/` and `scene_camera.json` (`cam_K`; `cam_R_w2c` / `cam_t_w2c` where the
camera's pose is known). A scene_gt.json beside them is never opened. A rosbag is first written out as such a folder
(`axispose_ros/recording.py`), so everything after reads one format.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from axispose_core.data.bop import BopFormatError, camera_to_fixed, load_camera_poses, load_scene_camera, read_bgr

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


class RecordingError(ValueError):
    """A recording that cannot be adapted on: the one-line reason."""


@dataclass(frozen=True)
class Frame:
    """One frame: its id in the recording, its image file, K (3x3), and the camera's pose in the fixed frame (4x4,
    camera to fixed; None without odometry)."""

    im_id: int
    path: Path
    K: np.ndarray
    camera: np.ndarray | None = None

    def rgb(self) -> np.ndarray:
        """The image, HxWx3 uint8 RGB (a file that does not read is a BopFormatError)."""
        return cv2.cvtColor(read_bgr(self.path), cv2.COLOR_BGR2RGB)


@dataclass(frozen=True)
class Recording:
    """The frames of one recording, in image-id order; `root` the scene folder they were read from."""

    root: Path
    frames: tuple[Frame, ...]

    @property
    def has_odometry(self) -> bool:
        """Every frame knows the camera's pose in the fixed frame."""
        return bool(self.frames) and all(f.camera is not None for f in self.frames)

    def select(self, im_ids: set[int] | None) -> Recording:
        """The recording cut down to the frames of `im_ids` (None: all of them)."""
        return self if im_ids is None else Recording(self.root, tuple(f for f in self.frames if f.im_id in im_ids))


def _image_file(rgb_dir: Path, im_id: int) -> Path | None:
    return next((p for s in IMAGE_SUFFIXES if (p := rgb_dir / f"{im_id:06d}{s}").is_file()), None)


def read_recording(folder: str | Path) -> Recording:
    """The frames of a BOP scene folder (or of the one scene of a split folder): every image of scene_camera.json
    that has its file in rgb/. A folder that is not such a scene, or holds no frame, is a RecordingError."""
    folder = Path(folder)
    if not folder.is_dir():
        raise RecordingError(f"{folder}: no such folder")
    if not (folder / "scene_camera.json").is_file():
        scenes = sorted(p for p in folder.iterdir() if (p / "scene_camera.json").is_file())
        if len(scenes) != 1:
            what = "several scene folders" if scenes else "no scene_camera.json"
            raise RecordingError(f"{folder}: {what}; give one BOP scene folder (rgb/ and scene_camera.json)")
        folder = scenes[0]
    try:
        cameras = load_scene_camera(folder / "scene_camera.json")
        poses = load_camera_poses(folder / "scene_camera.json")
    except BopFormatError as err:
        raise RecordingError(str(err)) from err
    frames = []
    for im_id, K in sorted(cameras.items()):
        path = _image_file(folder / "rgb", im_id)
        if path is not None:
            camera = camera_to_fixed(*poses[im_id]) if im_id in poses else None
            frames.append(Frame(im_id, path, K, camera))
    if not frames:
        raise RecordingError(f"{folder}: none of the {len(cameras)} images of scene_camera.json is in rgb/")
    return Recording(folder, tuple(frames))
