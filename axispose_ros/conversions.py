"""sensor_msgs Image and CameraInfo <-> NumPy, without cv_bridge (not installable from the wheels here).

Every check a robot's camera driver can fail raises `InputError` with a message fit for a throttled log line:
unsupported encodings, rows shorter than the declared step, a K that is zero or NaN, a principal point far outside
the image, a focal length no lens has or a skew no sensor has, a CameraInfo whose size disagrees with the image
other than by a uniform scale, a distortion model OpenCV cannot invert.
"""

from __future__ import annotations

import struct

import cv2
import numpy as np
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import Header

from axispose_core.camera import Camera, IntrinsicsError

CHANNELS = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4, "mono8": 1}
"""Encodings the node reads (8 bits per channel)."""


class InputError(ValueError):
    """A message the node must drop; `reason` is the short key its drop counter uses."""

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


def stamp_seconds(header: Header) -> float:
    """A message header's stamp in seconds."""
    return header.stamp.sec + 1e-9 * header.stamp.nanosec


def stamp_ns(header: Header) -> int:
    """A message header's stamp in nanoseconds, exact: the key frames and poses are matched by."""
    return int(header.stamp.sec) * 10**9 + int(header.stamp.nanosec)


def cdr_stamp(raw: bytes) -> int | None:
    """The stamp (ns) of a serialized message whose first field is a std_msgs/Header, read from its CDR bytes
    without deserialising it: the 4-byte encapsulation, then the stamp's int32 sec and uint32 nanosec in the byte
    order it names. None for bytes too short to hold one."""
    if len(raw) < 12:
        return None
    sec, nanosec = struct.unpack_from("<iI" if raw[1] & 1 else ">iI", raw, 4)
    return sec * 10**9 + nanosec


def printable(text: str, limit: int = 32) -> str:
    """A string from a message as it may be logged: quoted with escapes (no newline reaches the log), cut short."""
    return repr(text[:limit]) + ("…" if len(text) > limit else "")


def check_image(msg: Image) -> int:
    """The Image's channels per pixel, or InputError: its encoding, size, row step and data length are checked
    without touching the pixels, so a bad frame is refused as it arrives."""
    enc = msg.encoding.lower()
    if enc not in CHANNELS:
        # One counter for every unsupported encoding: a stream of distinct strings must not grow the diagnostics.
        raise InputError("encoding", f"unsupported image encoding {printable(msg.encoding)} (supported: {', '.join(CHANNELS)})")
    h, w, c = msg.height, msg.width, CHANNELS[enc]
    if h == 0 or w == 0:
        raise InputError("image_size", "image has zero size")
    if msg.step < w * c:
        raise InputError("image_step", f"row step {msg.step} is shorter than width {w} x {c} channels")
    if len(msg.data) < msg.step * (h - 1) + w * c:
        raise InputError("image_data", f"image data holds {len(msg.data)} bytes, {msg.step * (h - 1) + w * c} needed")
    return c


def check_frame(image: Image, info: CameraInfo, use_rectified: bool = False) -> Camera:
    """The camera for this image, or InputError: the checks of `image_to_rgb`, `camera_from_info` and
    `camera_for_image` that need no pixels, run where the frame arrives so that every bad frame is counted as what
    it is (a busy node would otherwise replace most of them unseen) and none displaces a good one."""
    check_image(image)
    return camera_for_image(camera_from_info(info, use_rectified), image.width, image.height)


def image_to_rgb(msg: Image) -> np.ndarray:
    """An HxWx3 uint8 RGB array (a copy) from an Image of a supported encoding and any row step."""
    c = check_image(msg)
    enc, h, w = msg.encoding.lower(), msg.height, msg.width
    data = np.frombuffer(bytes(msg.data) if not isinstance(msg.data, np.ndarray) else msg.data.tobytes(), dtype=np.uint8)
    rows = np.lib.stride_tricks.as_strided(data, shape=(h, w, c), strides=(msg.step, c, 1))
    if enc == "mono8":
        return np.repeat(rows, 3, axis=2)
    if enc.startswith("bgr"):
        return np.ascontiguousarray(rows[:, :, 2::-1])
    return np.ascontiguousarray(rows[:, :, :3])


def rgb_to_image(rgb: np.ndarray, header: Header) -> Image:
    """An rgb8 Image carrying `header` (stamp and frame_id kept)."""
    rgb = np.ascontiguousarray(rgb, dtype=np.uint8)
    msg = Image()
    msg.header = header
    msg.height, msg.width = int(rgb.shape[0]), int(rgb.shape[1])
    msg.encoding = "rgb8"
    msg.is_bigendian = 0
    msg.step = int(rgb.shape[1] * 3)
    msg.data = rgb.tobytes()
    return msg


PRINCIPAL_POINT_RANGE = (-0.5, 1.5)
"""Where the principal point may lie, as fractions of the image's width and height: off-centre lenses and crops keep
it well inside; beyond, the K is not this image's."""
FOCAL_LENGTH_RANGE = (0.05, 50.0)
"""Plausible pixel focal lengths, as multiples of the image's larger side: a field of view from ~169 degrees (the
pinhole K of a fisheye) down to ~1 degree (a long telephoto)."""
FOCAL_ASPECT_RANGE = (0.2, 5.0)
"""Plausible fx / fy (non-square pixels, anamorphic lenses)."""


def camera_from_info(info: CameraInfo, use_rectified: bool = False) -> Camera:
    """The pinhole camera of a CameraInfo: K, or P's left 3x3 for rectified images. Finite but absurd intrinsics
    are refused here, each with its reason: they pass the pinhole checks yet overflow the crop arithmetic later."""
    which = "P" if use_rectified else "K"
    K = np.asarray(info.p, dtype=np.float64).reshape(3, 4)[:, :3] if use_rectified else np.asarray(info.k, dtype=np.float64).reshape(3, 3)
    if info.width == 0 or info.height == 0:
        raise InputError("camera_info_size", "CameraInfo has zero width or height")
    try:
        camera = Camera(K, int(info.width), int(info.height))
    except IntrinsicsError as err:
        raise InputError("camera_info_k", f"CameraInfo {which} is unusable: {err}") from err
    w, h = camera.width, camera.height
    (fx, skew, cx), (_, fy, cy) = camera.K[0], camera.K[1]
    lo, hi = PRINCIPAL_POINT_RANGE
    if not (lo * w <= cx <= hi * w and lo * h <= cy <= hi * h):
        raise InputError(
            "camera_info_principal_point", f"CameraInfo {which}'s principal point ({cx:.4g}, {cy:.4g}) lies far outside the {w}x{h} image"
        )
    lo, hi = FOCAL_LENGTH_RANGE[0] * max(w, h), FOCAL_LENGTH_RANGE[1] * max(w, h)
    if not (lo <= fx <= hi and lo <= fy <= hi and FOCAL_ASPECT_RANGE[0] <= fx / fy <= FOCAL_ASPECT_RANGE[1]):
        raise InputError(
            "camera_info_focal_length",
            f"CameraInfo {which}'s focal length (fx {fx:.4g}, fy {fy:.4g} px) is implausible for a {w}x{h} image "
            f"(expected {lo:.4g}-{hi:.4g} px)",
        )
    if abs(skew) > fx:  # axes more than 45 degrees off perpendicular: no sensor; 1e300 fails in the back-projection
        raise InputError("camera_info_k", f"CameraInfo {which}'s skew {skew:.4g} is implausible for fx {fx:.4g} px")
    return camera


def camera_for_image(camera: Camera, width: int, height: int, tolerance: float = 1e-3) -> Camera:
    """The camera for an image of width x height: itself, scaled when the image is a uniformly resized copy,
    else InputError (the CameraInfo does not describe this image)."""
    if (width, height) == (camera.width, camera.height):
        return camera
    sx, sy = width / camera.width, height / camera.height
    if abs(sx - sy) > tolerance * max(sx, sy):
        raise InputError(
            "camera_info_mismatch", f"image is {width}x{height} but CameraInfo says {camera.width}x{camera.height} (not a uniform scale)"
        )
    return camera.scaled(width, height)


DISTORTION_MODELS = ("plumb_bob", "rational_polynomial", "equidistant")
"""CameraInfo distortion models the node undoes (OpenCV's pinhole model with 4-14 coefficients; its fisheye one)."""


class Undistorter:
    """Undoes a CameraInfo's lens distortion so that the image is a pinhole image of the same K, as the AGM and the
    TBM assume. The remap tables are built once per (model, coefficients, K, size) and reused."""

    def __init__(self) -> None:
        self._key: tuple | None = None
        self._maps: tuple[np.ndarray, np.ndarray] | None = None

    @staticmethod
    def needed(info: CameraInfo) -> bool:
        """True where the CameraInfo describes any distortion (an empty or all-zero D is none)."""
        return len(info.d) > 0 and bool(np.any(np.asarray(info.d, dtype=np.float64) != 0))

    def __call__(self, info: CameraInfo, K: np.ndarray, rgb: np.ndarray) -> np.ndarray:
        """`rgb` (taken through `info`, K already scaled to its size) as the undistorted pinhole image of K."""
        model = info.distortion_model
        D = np.asarray(info.d, dtype=np.float64)
        if model not in DISTORTION_MODELS:
            raise InputError("distortion_model", f"CameraInfo distortion model {printable(model)} is not supported "
                             f"(supported: {', '.join(DISTORTION_MODELS)}; or publish rectified images with use_rectified)")  # fmt: skip
        if (
            not np.isfinite(D).all()
            or (model == "equidistant" and len(D) < 4)
            or (model != "equidistant" and len(D) not in (4, 5, 8, 12, 14))
        ):
            raise InputError("distortion_coefficients", f"CameraInfo has {len(D)} distortion coefficients, unusable for {model}")
        h, w = rgb.shape[:2]
        key = (model, D.tobytes(), K.tobytes(), w, h)
        if key != self._key:
            if model == "equidistant":
                maps = cv2.fisheye.initUndistortRectifyMap(K, D[:4], np.eye(3), K, (w, h), cv2.CV_16SC2)
            else:
                maps = cv2.initUndistortRectifyMap(K, D, None, K, (w, h), cv2.CV_16SC2)
            self._key, self._maps = key, maps
        return cv2.remap(rgb, self._maps[0], self._maps[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
