"""BOP dataset format: the files of a dataset's scenes (scene_gt, scene_camera, scene_gt_info, depth and colour
images, camera.json, test targets) and the checked reading of BOP's JSON files that the sibling modules share:
`bop_models.py` (models and models_info.json), `bop_results.py` (BOP19 results files), `bop_scene.py` (a scene
folder as frames).

BOP stores lengths in millimetres; everything this project computes uses metres. The conversion happens at the
file boundary, in these modules, through `MM` and nowhere else.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from axispose_core.camera import IntrinsicsError, project_model, validate_intrinsics
from axispose_core.rotation import nearest_rotation

MM = 1e-3
"""Metres per millimetre: BOP files are in mm, the project in m."""
ROTATION_TOL = 0.03
"""How far a GT rotation may be from orthonormal (max |RR^T - I| entry, and |det - 1|) and still be taken, after
projection to the nearest rotation. The official LM-O annotations reach 0.0096 and det 1.0137 (rounding in the
published files); a reflection, a scaling by 3 % or more, or a shear is a different matrix, not a noisy rotation."""

log = logging.getLogger(__name__)


class BopFormatError(ValueError):
    """A BOP file is missing, unreadable or has a malformed field; the message names the file and the field."""


def read_json(path: Path) -> Any:
    """A JSON file's content; a missing or unreadable file is a BopFormatError naming it."""
    try:
        with open(path, encoding="utf-8") as f:
            return json.load(f)
    except FileNotFoundError as err:
        raise BopFormatError(f"{path}: file not found") from err
    except (OSError, json.JSONDecodeError, UnicodeDecodeError) as err:
        raise BopFormatError(f"{path}: not valid JSON ({err})") from err


def write_json(path: Path, data: Any) -> None:
    """Write `data` as JSON through a temporary file, so that a reader never sees half a file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    with open(tmp, "w", encoding="utf-8") as f:
        json.dump(data, f, indent=1, sort_keys=False)
    tmp.replace(path)


def numbers(path: Path, where: str, name: str, value: Any, n: int) -> np.ndarray:
    """A field that must hold n finite numbers, as float64."""
    try:
        arr = np.asarray(value, dtype=np.float64).ravel()
    except (TypeError, ValueError) as err:
        raise BopFormatError(f"{path}: {where}: field '{name}' must be numbers") from err
    if arr.size != n or not np.all(np.isfinite(arr)):
        raise BopFormatError(f"{path}: {where}: field '{name}' must hold {n} finite numbers, got {arr.size}")
    return arr


def required(path: Path, where: str, entry: Any, name: str) -> Any:
    """`entry`'s field `name`; a missing one is a BopFormatError naming the file, the entry and the field."""
    if not isinstance(entry, dict) or name not in entry:
        raise BopFormatError(f"{path}: {where}: missing field '{name}'")
    return entry[name]


def _int_key(path: Path, key: str) -> int:
    try:
        return int(key)
    except ValueError as err:
        raise BopFormatError(f"{path}: key '{key}' is not an integer id") from err


def keyed(path: Path, what: str, lists: bool = False) -> Iterator[tuple[int, Any]]:
    """(id, entry) of a BOP JSON object keyed by `what` id ("object" or "image"); with `lists`, each entry must be
    a list (of instances)."""
    data = read_json(path)
    if not isinstance(data, dict):
        raise BopFormatError(f"{path}: expected an object keyed by {what} id")
    for key, entry in data.items():
        i = _int_key(path, key)
        if lists and not isinstance(entry, list):
            raise BopFormatError(f"{path}: {what} {i}: expected a list of instances")
        yield i, entry


# ----------------------------------------------------------------------------------------------- scenes


@dataclass(frozen=True)
class GTInstance:
    """One annotated object instance: model-to-camera pose in metres."""

    obj_id: int
    R: np.ndarray
    t: np.ndarray


@dataclass(frozen=True)
class GTInfo:
    """scene_gt_info.json entry: boxes are (x, y, w, h) in pixels, -1s when the object is not visible."""

    bbox_obj: tuple[int, int, int, int]
    """The whole object's projection, hidden parts included."""
    bbox_visib: tuple[int, int, int, int] = (-1, -1, -1, -1)
    """Its visible pixels'."""
    px_count_all: int = 0
    """Pixels of the whole silhouette."""
    px_count_valid: int = 0
    """Of those, the pixels with a valid depth measurement: all of them in synthetic frames, fewer in real ones
    where the sensor saw nothing."""
    px_count_visib: int = 0
    """Pixels of the silhouette not hidden by another object."""
    visib_fract: float = 0.0
    """px_count_visib / px_count_all: BOP19 scores instances at least 10 % visible."""


@dataclass(frozen=True)
class SceneGT:
    """scene_gt.json read: instances per image id, and how many rotations were projected to the nearest one."""

    instances: dict[int, list[GTInstance]]
    projected: int = 0
    worst: float = 0.0
    """The largest deviation from orthonormal among them (max |RR^T - I| entry or |det - 1|)."""


def read_scene_gt(path: str | Path) -> SceneGT:
    """scene_gt.json: per image id, the instances in file order (their index names the mask files). Rotations
    within ROTATION_TOL of orthonormal are projected to the nearest rotation and counted; others are refused."""
    path = Path(path)
    scene: dict[int, list[GTInstance]] = {}
    projected, worst = 0, 0.0
    for im_id, entries in keyed(path, "image", lists=True):
        insts = []
        for k, e in enumerate(entries):
            where = f"image {im_id} instance {k}"
            R = numbers(path, where, "cam_R_m2c", required(path, where, e, "cam_R_m2c"), 9).reshape(3, 3)
            t = numbers(path, where, "cam_t_m2c", required(path, where, e, "cam_t_m2c"), 3) * MM
            obj_id = int(numbers(path, where, "obj_id", required(path, where, e, "obj_id"), 1)[0])
            off = max(float(np.abs(R @ R.T - np.eye(3)).max()), abs(float(np.linalg.det(R)) - 1.0))
            if off > ROTATION_TOL:
                raise BopFormatError(
                    f"{path}: {where}: field 'cam_R_m2c' is not a rotation matrix (off orthonormal by {off:.3g}, "
                    f"more than the {ROTATION_TOL} that rounded annotations reach)"
                )
            if off > 1e-6:
                R, projected, worst = nearest_rotation(R), projected + 1, max(worst, off)
            insts.append(GTInstance(obj_id, R, t))
        scene[im_id] = insts
    if projected:
        log.warning("%s: %d GT rotations were not orthonormal (by up to %.3g); projected to the nearest rotation", path, projected, worst)
    return SceneGT(scene, projected, worst)


def load_scene_gt(path: str | Path) -> dict[int, list[GTInstance]]:
    """scene_gt.json's instances per image id (`read_scene_gt` without the count of projected rotations)."""
    return read_scene_gt(path).instances


def write_scene_gt(path: str | Path, scene: dict[int, list[GTInstance]]) -> None:
    """Write scene_gt.json (translations in mm)."""
    out = {
        str(im_id): [
            {"cam_R_m2c": np.asarray(g.R).ravel().tolist(), "cam_t_m2c": (np.asarray(g.t) / MM).tolist(), "obj_id": int(g.obj_id)}
            for g in insts
        ]
        for im_id, insts in sorted(scene.items())
    }
    write_json(Path(path), out)


def load_scene_camera(path: str | Path) -> dict[int, np.ndarray]:
    """scene_camera.json: K (3x3, pixels) per image id, validated."""
    path = Path(path)
    cams = {}
    for im_id, e in keyed(path, "image"):
        where = f"image {im_id}"
        K = numbers(path, where, "cam_K", required(path, where, e, "cam_K"), 9).reshape(3, 3)
        try:
            cams[im_id] = validate_intrinsics(K)
        except IntrinsicsError as err:
            raise BopFormatError(f"{path}: {where}: field 'cam_K': {err}") from err
    return cams


def load_camera_poses(path: str | Path) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """scene_camera.json's camera poses (`cam_R_w2c`, `cam_t_w2c`: world to camera, t in m) per image id, for the
    images that give one (BOP's optional fields: a recording's odometry, a rendered camera path's truth)."""
    path = Path(path)
    poses = {}
    for im_id, e in keyed(path, "image"):
        if not isinstance(e, dict) or "cam_R_w2c" not in e:
            continue
        where = f"image {im_id}"
        R = numbers(path, where, "cam_R_w2c", e["cam_R_w2c"], 9).reshape(3, 3)
        t = numbers(path, where, "cam_t_w2c", required(path, where, e, "cam_t_w2c"), 3) * MM
        off = max(float(np.abs(R @ R.T - np.eye(3)).max()), abs(float(np.linalg.det(R)) - 1.0))
        if off > ROTATION_TOL:
            raise BopFormatError(f"{path}: {where}: field 'cam_R_w2c' is not a rotation matrix (off orthonormal by {off:.3g})")
        poses[im_id] = (nearest_rotation(R) if off > 1e-6 else R, t)
    return poses


def camera_to_fixed(R_w2c: np.ndarray, t_w2c: np.ndarray) -> np.ndarray:
    """The 4x4 camera-to-fixed pose of a world-to-camera one."""
    T = np.eye(4)
    T[:3, :3] = R_w2c.T
    T[:3, 3] = -R_w2c.T @ t_w2c
    return T


def load_depth_scales(path: str | Path) -> dict[int, float]:
    """scene_camera.json's depth_scale per image id (mm per depth-image unit; 1.0 where absent)."""
    path = Path(path)
    scales = {}
    for im_id, e in keyed(path, "image"):
        scale = float(numbers(path, f"image {im_id}", "depth_scale", e.get("depth_scale", 1.0) if isinstance(e, dict) else None, 1)[0])
        if scale <= 0:
            raise BopFormatError(f"{path}: image {im_id}: field 'depth_scale' must be positive, got {scale}")
        scales[im_id] = scale
    return scales


def read_depth(path: str | Path, depth_scale: float) -> np.ndarray:
    """A BOP depth image (16-bit PNG, mm / depth_scale per unit) as float64 metres (0: no measurement)."""
    depth = cv2.imread(str(path), cv2.IMREAD_ANYDEPTH)
    if depth is None or depth.ndim != 2:
        raise BopFormatError(f"{path}: unreadable depth image")
    return depth.astype(np.float64) * (depth_scale * MM)


def write_depth(path: str | Path, depth: np.ndarray, depth_scale: float) -> None:
    """Write metres (0, inf or NaN: no measurement) as a BOP 16-bit depth PNG in units of depth_scale mm."""
    units = np.where(np.isfinite(depth), np.asarray(depth, np.float64) / (depth_scale * MM), 0.0)
    if units.max(initial=0.0) > 65535:
        raise ValueError(f"{path}: depth up to {units.max() * depth_scale * MM:.1f} m does not fit 16 bits at depth_scale {depth_scale}")
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.round(units).astype(np.uint16))


def load_camera(path: str | Path) -> tuple[np.ndarray, int | None, int | None]:
    """A dataset's camera.json: K (3x3, validated) and the image width and height where it gives them."""
    path = Path(path)
    cam = read_json(path)
    where = "camera"
    K = np.array([[required(path, where, cam, "fx"), 0.0, required(path, where, cam, "cx")],
                  [0.0, required(path, where, cam, "fy"), required(path, where, cam, "cy")], [0.0, 0.0, 1.0]])  # fmt: skip
    try:
        K = validate_intrinsics(numbers(path, where, "fx, fy, cx, cy", K, 9).reshape(3, 3))
    except IntrinsicsError as err:
        raise BopFormatError(f"{path}: {err}") from err
    size = [cam.get(k) for k in ("width", "height")]
    if any(v is not None and (not isinstance(v, int) or v <= 0) for v in size):
        raise BopFormatError(f"{path}: width and height must be positive integers, got {size}")
    return K, size[0], size[1]


def write_scene_camera(path: str | Path, cams: dict[int, np.ndarray], depth_scale: float = 1.0,
                       poses: dict[int, tuple[np.ndarray, np.ndarray]] | None = None) -> None:  # fmt: skip
    """Write scene_camera.json; with `poses`, each image's camera pose (world to camera, t in m) where it has one."""
    out = {str(i): {"cam_K": np.asarray(K).ravel().tolist(), "depth_scale": depth_scale} for i, K in sorted(cams.items())}
    for i, (R, t) in (poses or {}).items():
        out[str(i)].update(cam_R_w2c=np.asarray(R).ravel().tolist(), cam_t_w2c=(np.asarray(t) / MM).tolist())
    write_json(Path(path), out)


def load_scene_gt_info(path: str | Path) -> dict[int, list[GTInfo]]:
    """scene_gt_info.json, entries in the same order as scene_gt.json."""
    path = Path(path)
    out: dict[int, list[GTInfo]] = {}
    for im_id, entries in keyed(path, "image", lists=True):
        infos = []
        for k, e in enumerate(entries):
            where = f"image {im_id} instance {k}"
            box = tuple(int(v) for v in numbers(path, where, "bbox_obj", required(path, where, e, "bbox_obj"), 4))
            vis = tuple(int(v) for v in numbers(path, where, "bbox_visib", e.get("bbox_visib", [-1] * 4), 4))
            fract = float(numbers(path, where, "visib_fract", e.get("visib_fract", 0.0), 1)[0])
            if not 0.0 <= fract <= 1.0:
                raise BopFormatError(f"{path}: {where}: field 'visib_fract' must lie in [0, 1], got {fract}")
            counts = [int(e.get(name, 0)) for name in ("px_count_all", "px_count_valid", "px_count_visib")]
            infos.append(GTInfo(box, vis, *counts, fract))  # type: ignore[arg-type]
        out[im_id] = infos
    return out


def write_scene_gt_info(path: str | Path, infos: dict[int, list[GTInfo]]) -> None:
    """Write scene_gt_info.json."""
    out = {
        str(im_id): [
            {
                "bbox_obj": list(i.bbox_obj),
                "bbox_visib": list(i.bbox_visib),
                "px_count_all": i.px_count_all,
                "px_count_valid": i.px_count_valid,
                "px_count_visib": i.px_count_visib,
                "visib_fract": i.visib_fract,
            }
            for i in lst
        ]
        for im_id, lst in sorted(infos.items())
    }
    write_json(Path(path), out)


def load_test_targets(path: str | Path) -> dict[tuple[int, int], dict[int, int]]:
    """test_targets_bop19.json: per (scene_id, im_id), the instance count to find of each object id."""
    path = Path(path)
    data = read_json(path)
    if not isinstance(data, list):
        raise BopFormatError(f"{path}: expected a list of targets")
    targets: dict[tuple[int, int], dict[int, int]] = {}
    for k, e in enumerate(data):
        where = f"target {k}"
        scene_id, im_id, obj_id, count = (
            int(numbers(path, where, name, required(path, where, e, name), 1)[0]) for name in ("scene_id", "im_id", "obj_id", "inst_count")
        )
        if count < 1:
            raise BopFormatError(f"{path}: {where}: field 'inst_count' must be at least 1, got {count}")
        targets.setdefault((scene_id, im_id), {})[obj_id] = count
    return targets


def bbox_from_model(K: np.ndarray, R: np.ndarray, t: np.ndarray, pts: np.ndarray) -> tuple[int, int, int, int]:
    """(x, y, w, h) of the projected model points, not clipped to the image (BOP's bbox_obj)."""
    uv = project_model(K, R, t, pts)
    x0, y0 = np.floor(uv.min(axis=0)).astype(int)
    x1, y1 = np.floor(uv.max(axis=0)).astype(int)
    return int(x0), int(y0), int(x1 - x0 + 1), int(y1 - y0 + 1)


def bbox_from_mask(mask: np.ndarray) -> tuple[int, int, int, int]:
    """(x, y, w, h) of a mask's pixels, (-1, -1, -1, -1) for an empty one (BOP's bbox_visib)."""
    ys, xs = np.nonzero(mask)
    if not len(xs):
        return (-1, -1, -1, -1)
    return (int(xs.min()), int(ys.min()), int(xs.max() - xs.min() + 1), int(ys.max() - ys.min() + 1))


def read_bgr(path: str | Path) -> np.ndarray:
    """An image file as HxWx3 uint8 BGR (OpenCV's order, for drawing and writing); an unreadable file is a
    BopFormatError rather than cv2.imread's None."""
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise BopFormatError(f"{path}: unreadable image")
    return bgr
