"""rosbag2 recordings of BOP scenes, written and read with `rosbags` (rosbag2_py is not installable from wheels).

A bag written by `make_bag` holds, per frame, on one stamp:
- the camera stream: `sensor_msgs/Image` (rgb8) and `sensor_msgs/CameraInfo` (K, P, size);
- the ground truth: `/gt/<object_name>` `geometry_msgs/PoseStamped` (object in the camera frame, one message
  per instance with visib_fract >= 0.1, BOP19), and `/roi/<object_name>` `sensor_msgs/RegionOfInterest` (its
  GT box, what an external detector would give the node);
- where the scene gives the camera's pose (scene_camera.json's `cam_R_w2c`, `cam_t_w2c`: a rendered camera path):
  `/camera/odom` `nav_msgs/Odometry`, the camera's optical frame in the scene's world frame (`odom`), what a
  robot's odometry gives the node's `camera_odom`;
- once, at the start: `/gt/models/<object_name>` `sensor_msgs/PointCloud2` (x, y, z float32 in m, object
  frame), the model points the metrics need, so that a bag is evaluated without the models folder.

Only `rosbags` and NumPy are used here: writing a bag needs no ROS installation.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from rosbags.rosbag2 import Reader, ReaderError, StoragePlugin, Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from scipy.spatial.transform import Rotation
from tqdm import tqdm

from axispose_core.data.bop import BopFormatError
from axispose_core.data.bop_models import model_path
from axispose_core.data.bop_scene import BopScene
from axispose_core.data.meshes import load_ply
from axispose_core.data.visibility import gt_info_from_models
from axispose_core.objects import ObjectSpec

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
FORMATS = {"sqlite3": StoragePlugin.SQLITE3, "mcap": StoragePlugin.MCAP}
IMAGE_TOPIC = "/camera/color/image_raw"
INFO_TOPIC = "/camera/color/camera_info"
FRAME_ID = "camera_color_optical_frame"
ODOM_TOPIC = "/camera/odom"
ODOM_FRAME = "odom"
GT_PREFIX = "/gt/"
MODELS_PREFIX = "/gt/models/"
ROI_PREFIX = "/roi/"
MIN_VISIB = 0.1
STAMP_ORIGIN_NS = 1_700_000_000 * 10**9
"""Stamp of frame 0: BOP scenes have no times, and a zero stamp reads as 'unset' to many ROS tools."""

_T = TYPESTORE.types


class BagError(RuntimeError):
    """A bag that cannot be read (missing, not a rosbag2, truncated or corrupt) or lacks what is asked of it."""


def _header(stamp_ns: int, frame_id: str):
    return _T["std_msgs/msg/Header"](
        stamp=_T["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9), frame_id=frame_id
    )


def _image(rgb: np.ndarray, header):
    h, w = rgb.shape[:2]
    return _T["sensor_msgs/msg/Image"](
        header=header, height=h, width=w, encoding="rgb8", is_bigendian=0, step=3 * w, data=np.ascontiguousarray(rgb, np.uint8).reshape(-1)
    )


def _camera_info(K: np.ndarray, width: int, height: int, header):
    roi = _T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    P = np.hstack([K, np.zeros((3, 1))])
    return _T["sensor_msgs/msg/CameraInfo"](
        header=header, height=height, width=width, distortion_model="plumb_bob", d=np.zeros(5), k=np.asarray(K, float).reshape(-1),
        r=np.eye(3).reshape(-1), p=P.reshape(-1), binning_x=0, binning_y=0, roi=roi,
    )  # fmt: skip


def _pose(R: np.ndarray, t: np.ndarray):
    x, y, z, w = Rotation.from_matrix(R).as_quat()
    return _T["geometry_msgs/msg/Pose"](
        position=_T["geometry_msgs/msg/Point"](x=float(t[0]), y=float(t[1]), z=float(t[2])),
        orientation=_T["geometry_msgs/msg/Quaternion"](x=float(x), y=float(y), z=float(z), w=float(w)),
    )


def _pose_stamped(R: np.ndarray, t: np.ndarray, header):
    return _T["geometry_msgs/msg/PoseStamped"](header=header, pose=_pose(R, t))


def _odometry(R_w2c: np.ndarray, t_w2c: np.ndarray, stamp_ns: int):
    """The camera's optical frame in the world frame (the inverse of world to camera), no twist."""
    pose = _T["geometry_msgs/msg/PoseWithCovariance"](pose=_pose(R_w2c.T, -R_w2c.T @ t_w2c), covariance=np.zeros(36))
    twist = _T["geometry_msgs/msg/TwistWithCovariance"](
        twist=_T["geometry_msgs/msg/Twist"](linear=_T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
                                            angular=_T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)),
        covariance=np.zeros(36),
    )  # fmt: skip
    return _T["nav_msgs/msg/Odometry"](header=_header(stamp_ns, ODOM_FRAME), child_frame_id=FRAME_ID, pose=pose, twist=twist)


def _roi(box: tuple[int, int, int, int], width: int, height: int):
    x, y, w, h = (int(v) for v in box)
    x0, y0 = max(0, x), max(0, y)
    x1, y1 = min(width, x + w), min(height, y + h)
    return _T["sensor_msgs/msg/RegionOfInterest"](x_offset=x0, y_offset=y0, height=max(0, y1 - y0), width=max(0, x1 - x0), do_rectify=False)


def _cloud(points: np.ndarray, header):
    field = _T["sensor_msgs/msg/PointField"]
    fields = [field(name=n, offset=4 * i, datatype=field.FLOAT32, count=1) for i, n in enumerate("xyz")]
    data = np.ascontiguousarray(points, dtype="<f4").view(np.uint8).reshape(-1)
    n = len(points)
    return _T["sensor_msgs/msg/PointCloud2"](
        header=header, height=1, width=n, fields=fields, is_bigendian=False, point_step=12, row_step=12 * n, data=data, is_dense=True
    )


def cloud_points(msg) -> np.ndarray:
    """(N,3) float64 points of a PointCloud2 with float32 x, y, z fields (any layout of other fields)."""
    offsets = {f.name: f.offset for f in msg.fields if f.datatype == 7}
    if not {"x", "y", "z"} <= offsets.keys():
        raise BagError(f"point cloud '{msg.header.frame_id}' has no float32 x, y, z fields")
    raw = np.asarray(msg.data, dtype=np.uint8).reshape(-1, msg.point_step)
    return np.stack([raw[:, offsets[c] : offsets[c] + 4].copy().view("<f4")[:, 0] for c in "xyz"], axis=1).astype(np.float64)


def _eval_points(models_dir: Path, obj_id: int, count: int) -> np.ndarray:
    pts = load_ply(model_path(models_dir, obj_id)).vertices
    if len(pts) > count:
        pts = pts[np.linspace(0, len(pts) - 1, count).astype(int)]
    return pts


@dataclass(frozen=True)
class BagSummary:
    path: Path
    frames: int
    instances: int
    bytes: int


@dataclass(frozen=True)
class BagOptions:
    """How `make_bag` writes a bag; checked when made."""

    storage: str = "sqlite3"
    """A key of FORMATS."""
    fps: float = 10.0
    """Frame rate the stamps are spaced by."""
    stamp_by_id: bool = False
    """Stamp each image at its image id / fps rather than its position / fps: a BOP split that keeps every n-th
    frame of a recording (LM-O's test images) then keeps the recording's timing, which a tracker's motion model
    needs."""
    limit: int | None = None
    """The scene's first N images only; None: all."""
    model_points: int = 1000
    """Points per model in `/gt/models/*` (evenly picked from its vertices)."""
    progress: bool = True

    def __post_init__(self) -> None:
        if self.storage not in FORMATS:
            raise ValueError(f"storage must be one of {sorted(FORMATS)}, got {self.storage!r}")
        if not self.fps > 0:
            raise ValueError(f"fps must be > 0, got {self.fps}")


def make_bag(
    scene_dir: str | Path, out: str | Path, objects: list[ObjectSpec], models_dir: str | Path, options: BagOptions | None = None
) -> BagSummary:
    """Write a BOP scene as a rosbag2 (module docstring) as `options` say (default: sqlite3, 10 fps, every image).
    `objects` names the objects (topic names) and picks which get GT and ROI topics; `models_dir` gives the points
    for `/gt/models/*`."""
    opts = options or BagOptions()
    out = Path(out)
    if out.exists():
        raise FileExistsError(f"{out} exists; rosbag2 writers refuse to overwrite a bag")
    scene = BopScene(Path(scene_dir), gt_info_from_models(models_dir))  # boxes, visibility: the models' if no gt_info
    specs = {o.obj_id: o for o in objects}
    im_ids = scene.image_ids[: opts.limit] if opts.limit else scene.image_ids
    frames = instances = 0
    with Writer(out, version=9, storage_plugin=FORMATS[opts.storage]) as writer:
        conns: dict[str, object] = {}

        def write(topic: str, msgtype: str, msg, stamp_ns: int) -> None:
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msgtype, typestore=TYPESTORE)
            writer.write(conns[topic], stamp_ns, TYPESTORE.serialize_cdr(msg, msgtype))

        present = sorted({g.obj_id for im in im_ids for g in scene.gt[im]} & specs.keys())
        for obj_id in present:
            name = specs[obj_id].name
            pts = _eval_points(Path(models_dir), obj_id, opts.model_points)
            write(MODELS_PREFIX + name, "sensor_msgs/msg/PointCloud2", _cloud(pts, _header(STAMP_ORIGIN_NS, name)), STAMP_ORIGIN_NS)

        for k, im_id in enumerate(tqdm(im_ids, desc="make-bag", disable=not opts.progress)):
            stamp = STAMP_ORIGIN_NS + round(((im_id - im_ids[0]) if opts.stamp_by_id else k) * 1e9 / opts.fps)
            header = _header(stamp, FRAME_ID)
            try:
                rgb = scene.rgb(im_id)
            except BopFormatError as err:
                raise BagError(str(err)) from err
            h, w = rgb.shape[:2]
            for g, info in scene.instances(im_id):
                if g.obj_id not in specs or info.visib_fract < MIN_VISIB:
                    continue
                box = info.bbox_obj
                name = specs[g.obj_id].name
                write(GT_PREFIX + name, "geometry_msgs/msg/PoseStamped", _pose_stamped(g.R, g.t, header), stamp)
                write(ROI_PREFIX + name, "sensor_msgs/msg/RegionOfInterest", _roi(box, w, h), stamp)
                instances += 1
            if im_id in scene.camera_poses:
                write(ODOM_TOPIC, "nav_msgs/msg/Odometry", _odometry(*scene.camera_poses[im_id], stamp), stamp)
            write(INFO_TOPIC, "sensor_msgs/msg/CameraInfo", _camera_info(scene.cameras[im_id], w, h, header), stamp)
            write(IMAGE_TOPIC, "sensor_msgs/msg/Image", _image(rgb, header), stamp)
            frames += 1
    size = sum(p.stat().st_size for p in out.rglob("*") if p.is_file())
    return BagSummary(out, frames, instances, size)


@dataclass(frozen=True)
class BagMessage:
    topic: str
    msgtype: str
    stamp_ns: int
    raw: bytes


@contextmanager
def _reading(path: Path) -> Iterator[Reader]:
    """An open rosbag2 reader; every failure to read it, on opening or later, becomes a BagError naming the bag."""
    if not path.exists():
        raise BagError(f"{path}: no such bag")
    try:
        with Reader(path) as reader:
            yield reader
    except ReaderError as err:
        raise BagError(f"{path}: cannot read the bag ({err})") from err
    except Exception as err:  # sqlite3/mcap decoding errors of a truncated file surface as many types
        raise BagError(f"{path}: the bag is truncated or corrupt ({type(err).__name__}: {err})") from err


def read_bag(path: str | Path, topics: list[str] | None = None) -> Iterator[BagMessage]:
    """Messages of a rosbag2 (sqlite3 or mcap) in time order, as raw CDR; errors of a damaged bag become BagError."""
    with _reading(Path(path)) as reader:
        conns = [c for c in reader.connections if topics is None or c.topic in topics]
        _learn_types(conns)
        for conn, stamp, raw in reader.messages(connections=conns):
            yield BagMessage(conn.topic, conn.msgtype, stamp, bytes(raw))


def register_types(definitions: dict[str, str]) -> None:
    """Teach TYPESTORE the message types (e.g. axispose_msgs) that {msgtype: .msg text} defines, those it knows
    already kept as they are."""
    for msgtype, text in definitions.items():
        found = get_types_from_msg(text, msgtype)
        TYPESTORE.register({name: t for name, t in found.items() if name not in TYPESTORE.types})


def _learn_types(conns) -> None:
    """Register the message types TYPESTORE does not know from the definitions the bag stores with its
    connections, so that `deserialize` reads them; a definition that does not parse leaves the type unknown, and
    `deserialize` then says so for its messages."""
    for conn in conns:
        if conn.msgtype in TYPESTORE.types or not conn.msgdef.data:
            continue
        try:
            register_types({conn.msgtype: conn.msgdef.data})
        except Exception:  # rosbags raises several kinds for a definition it cannot read
            continue


def bag_topics(path: str | Path) -> dict[str, str]:
    """topic -> message type of a bag."""
    with _reading(Path(path)) as reader:
        return {c.topic: c.msgtype for c in reader.connections}


IMAGE = "sensor_msgs/msg/Image"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
ODOMETRY = "nav_msgs/msg/Odometry"


def unique_topic(topics: dict[str, str], msgtype: str, given: str | None) -> str:
    """The topic of `msgtype` to read: `given` (which must be one), else the bag's only one (BagError otherwise)."""
    if given:
        if topics.get(given) != msgtype:
            raise BagError(f"the bag has no {msgtype} topic '{given}' (it has: {sorted(topics)})")
        return given
    found = sorted(t for t, m in topics.items() if m == msgtype)
    if len(found) != 1:
        raise BagError(f"the bag has {len(found)} {msgtype} topics ({found}); name the one to use")
    return found[0]


def camera_topics(topics: dict[str, str], image: str | None, info: str | None, odom: str | None) -> tuple[str, str, str | None]:
    """A bag's Image, CameraInfo and (where it has one, or one is named) Odometry topic."""
    odom_topic = unique_topic(topics, ODOMETRY, odom) if odom or ODOMETRY in topics.values() else None
    return unique_topic(topics, IMAGE, image), unique_topic(topics, CAMERA_INFO, info), odom_topic


def deserialize(msg: BagMessage):
    """The rosbags message object of a raw bag message."""
    try:
        return TYPESTORE.deserialize_cdr(msg.raw, msg.msgtype)
    except Exception as err:
        raise BagError(f"a '{msg.topic}' message at {msg.stamp_ns} ns does not decode as {msg.msgtype} ({err})") from err
