"""BOP dataset format: the one module that reads and writes its files.

BOP stores lengths in millimetres; everything this project computes uses metres. The conversion happens here,
at the file boundary, through `MM` and nowhere else.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
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


# ----------------------------------------------------------------------------------------------- models


def model_path(models_dir: str | Path, obj_id: int) -> Path:
    """BOP model file name of an object id."""
    return Path(models_dir) / f"obj_{obj_id:06d}.ply"


@dataclass(frozen=True)
class ObjectInfo:
    """One entry of models_info.json, in metres."""

    obj_id: int
    diameter: float
    bbox_min: np.ndarray
    bbox_size: np.ndarray
    symmetries_discrete: tuple[np.ndarray, ...] = ()
    symmetries_continuous: tuple[dict[str, Any], ...] = ()
    """{"axis": 3 numbers, "offset": 3 numbers in metres} each: rotation about the axis through the offset."""

    @property
    def symmetric(self) -> bool:
        """Whether ADD-S (not ADD) scores this object."""
        return bool(self.symmetries_discrete or self.symmetries_continuous)


def _read_json(path: Path) -> Any:
    try:
        with open(path, encoding="utf-8") as f:
            return json.load(f)
    except FileNotFoundError as err:
        raise BopFormatError(f"{path}: file not found") from err
    except (OSError, json.JSONDecodeError, UnicodeDecodeError) as err:
        raise BopFormatError(f"{path}: not valid JSON ({err})") from err


def _write_json(path: Path, data: Any) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    with open(tmp, "w", encoding="utf-8") as f:
        json.dump(data, f, indent=1, sort_keys=False)
    tmp.replace(path)


def _numbers(path: Path, where: str, name: str, value: Any, n: int) -> np.ndarray:
    """A field that must hold n finite numbers, as float64."""
    try:
        arr = np.asarray(value, dtype=np.float64).ravel()
    except (TypeError, ValueError) as err:
        raise BopFormatError(f"{path}: {where}: field '{name}' must be numbers") from err
    if arr.size != n or not np.all(np.isfinite(arr)):
        raise BopFormatError(f"{path}: {where}: field '{name}' must hold {n} finite numbers, got {arr.size}")
    return arr


def _field(path: Path, where: str, entry: Any, name: str) -> Any:
    if not isinstance(entry, dict) or name not in entry:
        raise BopFormatError(f"{path}: {where}: missing field '{name}'")
    return entry[name]


def _int_key(path: Path, key: str) -> int:
    try:
        return int(key)
    except ValueError as err:
        raise BopFormatError(f"{path}: key '{key}' is not an integer id") from err


def _keyed(path: Path, what: str, lists: bool = False) -> Iterator[tuple[int, Any]]:
    """(id, entry) of a BOP JSON object keyed by `what` id ("object" or "image"); with `lists`, each entry must be
    a list (of instances)."""
    data = _read_json(path)
    if not isinstance(data, dict):
        raise BopFormatError(f"{path}: expected an object keyed by {what} id")
    for key, entry in data.items():
        i = _int_key(path, key)
        if lists and not isinstance(entry, list):
            raise BopFormatError(f"{path}: {what} {i}: expected a list of instances")
        yield i, entry


def load_models_info(path: str | Path) -> dict[int, ObjectInfo]:
    """models_info.json as ObjectInfo by object id (diameters, boxes and symmetry offsets converted to metres)."""
    path = Path(path)
    infos = {}
    for obj_id, entry in _keyed(path, "object"):
        where = f"object {obj_id}"
        diameter = float(_numbers(path, where, "diameter", _field(path, where, entry, "diameter"), 1)[0]) * MM
        if diameter <= 0:
            raise BopFormatError(f"{path}: {where}: field 'diameter' must be positive")
        bbox_min = np.array([_numbers(path, where, f"min_{a}", _field(path, where, entry, f"min_{a}"), 1)[0] for a in "xyz"]) * MM
        bbox_size = np.array([_numbers(path, where, f"size_{a}", _field(path, where, entry, f"size_{a}"), 1)[0] for a in "xyz"]) * MM
        syms = []
        for k, s in enumerate(entry.get("symmetries_discrete", [])):
            T = _numbers(path, where, f"symmetries_discrete[{k}]", s, 16).reshape(4, 4)
            T[:3, 3] *= MM
            syms.append(T)
        cont = []
        for k, s in enumerate(entry.get("symmetries_continuous", [])):
            where_k = f"{where} symmetries_continuous[{k}]"
            axis = _numbers(path, where_k, "axis", _field(path, where_k, s, "axis"), 3)
            if not np.linalg.norm(axis) > 0:
                raise BopFormatError(f"{path}: {where_k}: field 'axis' must not be zero")
            offset = _numbers(path, where_k, "offset", s.get("offset", [0.0, 0.0, 0.0]), 3) * MM
            cont.append({"axis": axis.tolist(), "offset": offset.tolist()})
        infos[obj_id] = ObjectInfo(obj_id, diameter, bbox_min, bbox_size, tuple(syms), tuple(cont))
    return infos


def write_models_info(path: str | Path, infos: dict[int, ObjectInfo]) -> None:
    """Write models_info.json (mm) from ObjectInfo in metres."""
    out = {}
    for obj_id, info in sorted(infos.items()):
        entry: dict[str, Any] = {"diameter": info.diameter / MM}
        for i, a in enumerate("xyz"):
            entry[f"min_{a}"] = info.bbox_min[i] / MM
            entry[f"size_{a}"] = info.bbox_size[i] / MM
        if info.symmetries_discrete:
            syms = []
            for T in info.symmetries_discrete:
                T = np.array(T, dtype=np.float64)
                T[:3, 3] /= MM
                syms.append(T.ravel().tolist())
            entry["symmetries_discrete"] = syms
        if info.symmetries_continuous:
            entry["symmetries_continuous"] = [
                {"axis": list(s["axis"]), "offset": (np.asarray(s["offset"], np.float64) / MM).tolist()} for s in info.symmetries_continuous
            ]
        out[str(obj_id)] = entry
    _write_json(Path(path), out)


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
    for im_id, entries in _keyed(path, "image", lists=True):
        insts = []
        for k, e in enumerate(entries):
            where = f"image {im_id} instance {k}"
            R = _numbers(path, where, "cam_R_m2c", _field(path, where, e, "cam_R_m2c"), 9).reshape(3, 3)
            t = _numbers(path, where, "cam_t_m2c", _field(path, where, e, "cam_t_m2c"), 3) * MM
            obj_id = int(_numbers(path, where, "obj_id", _field(path, where, e, "obj_id"), 1)[0])
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
    _write_json(Path(path), out)


def load_scene_camera(path: str | Path) -> dict[int, np.ndarray]:
    """scene_camera.json: K (3x3, pixels) per image id, validated."""
    path = Path(path)
    cams = {}
    for im_id, e in _keyed(path, "image"):
        where = f"image {im_id}"
        K = _numbers(path, where, "cam_K", _field(path, where, e, "cam_K"), 9).reshape(3, 3)
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
    for im_id, e in _keyed(path, "image"):
        if not isinstance(e, dict) or "cam_R_w2c" not in e:
            continue
        where = f"image {im_id}"
        R = _numbers(path, where, "cam_R_w2c", e["cam_R_w2c"], 9).reshape(3, 3)
        t = _numbers(path, where, "cam_t_w2c", _field(path, where, e, "cam_t_w2c"), 3) * MM
        off = max(float(np.abs(R @ R.T - np.eye(3)).max()), abs(float(np.linalg.det(R)) - 1.0))
        if off > ROTATION_TOL:
            raise BopFormatError(f"{path}: {where}: field 'cam_R_w2c' is not a rotation matrix (off orthonormal by {off:.3g})")
        poses[im_id] = (nearest_rotation(R) if off > 1e-6 else R, t)
    return poses


def load_depth_scales(path: str | Path) -> dict[int, float]:
    """scene_camera.json's depth_scale per image id (mm per depth-image unit; 1.0 where absent)."""
    path = Path(path)
    scales = {}
    for im_id, e in _keyed(path, "image"):
        scale = float(_numbers(path, f"image {im_id}", "depth_scale", e.get("depth_scale", 1.0) if isinstance(e, dict) else None, 1)[0])
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
    cam = _read_json(path)
    where = "camera"
    K = np.array([[_field(path, where, cam, "fx"), 0.0, _field(path, where, cam, "cx")],
                  [0.0, _field(path, where, cam, "fy"), _field(path, where, cam, "cy")], [0.0, 0.0, 1.0]])  # fmt: skip
    try:
        K = validate_intrinsics(_numbers(path, where, "fx, fy, cx, cy", K, 9).reshape(3, 3))
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
    _write_json(Path(path), out)


def load_scene_gt_info(path: str | Path) -> dict[int, list[GTInfo]]:
    """scene_gt_info.json, entries in the same order as scene_gt.json."""
    path = Path(path)
    out: dict[int, list[GTInfo]] = {}
    for im_id, entries in _keyed(path, "image", lists=True):
        infos = []
        for k, e in enumerate(entries):
            where = f"image {im_id} instance {k}"
            box = tuple(int(v) for v in _numbers(path, where, "bbox_obj", _field(path, where, e, "bbox_obj"), 4))
            vis = tuple(int(v) for v in _numbers(path, where, "bbox_visib", e.get("bbox_visib", [-1] * 4), 4))
            fract = float(_numbers(path, where, "visib_fract", e.get("visib_fract", 0.0), 1)[0])
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
    _write_json(Path(path), out)


def load_test_targets(path: str | Path) -> dict[tuple[int, int], dict[int, int]]:
    """test_targets_bop19.json: per (scene_id, im_id), the instance count to find of each object id."""
    path = Path(path)
    data = _read_json(path)
    if not isinstance(data, list):
        raise BopFormatError(f"{path}: expected a list of targets")
    targets: dict[tuple[int, int], dict[int, int]] = {}
    for k, e in enumerate(data):
        where = f"target {k}"
        scene_id, im_id, obj_id, count = (
            int(_numbers(path, where, name, _field(path, where, e, name), 1)[0]) for name in ("scene_id", "im_id", "obj_id", "inst_count")
        )
        if count < 1:
            raise BopFormatError(f"{path}: {where}: field 'inst_count' must be at least 1, got {count}")
        targets.setdefault((scene_id, im_id), {})[obj_id] = count
    return targets


@dataclass(frozen=True)
class BopEstimate:
    """One line of a BOP19 results file: a pose (metres here, mm in the file) with its score and the time its
    image took (s; -1 unknown)."""

    scene_id: int
    im_id: int
    obj_id: int
    score: float
    R: np.ndarray
    t: np.ndarray
    time: float = -1.0


RESULTS_HEADER = "scene_id,im_id,obj_id,score,R,t,time"


def write_bop_results(path: str | Path, estimates: list[BopEstimate]) -> None:
    """A BOP19 results CSV, as the official toolkit reads it (name it METHOD_DATASET-SPLIT.csv for its scripts)."""
    lines = [RESULTS_HEADER]
    for e in estimates:
        R = " ".join(repr(float(v)) for v in np.asarray(e.R, np.float64).ravel())
        t = " ".join(repr(float(v)) for v in np.asarray(e.t, np.float64).ravel() / MM)
        lines.append(f"{e.scene_id},{e.im_id},{e.obj_id},{float(e.score)!r},{R},{t},{float(e.time)!r}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n")


def read_bop_results(path: str | Path) -> list[BopEstimate]:
    """A BOP19 results CSV (header optional, as the official toolkit allows)."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as err:
        raise BopFormatError(f"{path}: cannot read ({err})") from err
    out = []
    for n, line in enumerate(text.splitlines(), 1):
        if not line.strip() or (n == 1 and RESULTS_HEADER in line):
            continue
        cells = line.split(",")
        if len(cells) != 7:
            raise BopFormatError(f"{path}: line {n}: expected 7 comma-separated fields, got {len(cells)}")
        try:
            ids = [int(c) for c in cells[:3]]
            R = np.array(cells[4].split(), np.float64).reshape(3, 3)
            t = np.array(cells[5].split(), np.float64).reshape(3) * MM
            out.append(BopEstimate(*ids, float(cells[3]), R, t, float(cells[6])))
        except ValueError as err:
            raise BopFormatError(f"{path}: line {n}: {err}") from err
    return out


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
