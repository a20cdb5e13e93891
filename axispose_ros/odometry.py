"""The camera's pose in a fixed frame, by stamp, from an odometry topic (nav_msgs/Odometry of the camera's optical
frame: a visual-inertial camera's own, or a robot's odometry composed with the camera's mount): what lets the
tracker average a still object's pose over the views a moving camera gives (`view_window`)."""

from __future__ import annotations

import bisect
import threading
import time
from collections.abc import Callable

import numpy as np
from scipy.spatial.transform import Rotation

from axispose_ros.conversions import stamp_seconds

KEEP_S = 2.0
"""Seconds of poses kept behind the newest: frames wait for inference far less."""
WAIT_S = 0.1
"""Longest a frame waits for the odometry of its stamp (an image and its odometry arrive in either order)."""


def pose_matrix(position, orientation) -> np.ndarray | None:
    """A geometry_msgs Pose's (position, orientation quaternion) as a 4x4 transform; None where it is not finite or
    the quaternion is not a rotation (zero length)."""
    q = np.array([orientation.x, orientation.y, orientation.z, orientation.w], dtype=float)
    p = np.array([position.x, position.y, position.z], dtype=float)
    if not (np.all(np.isfinite(q)) and np.all(np.isfinite(p))) or np.linalg.norm(q) < 1e-6:
        return None
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = Rotation.from_quat(q / np.linalg.norm(q)).as_matrix(), p
    return T


class CameraPoses:
    """Camera poses by stamp, added from the executor's thread and read from the inference thread; a message that
    holds no pose is dropped and reported to `invalid`."""

    def __init__(self, invalid: Callable[[], None] = lambda: None) -> None:
        self._stamps: list[float] = []
        self._poses: list[np.ndarray] = []
        self._lock = threading.Condition()
        self._invalid = invalid

    def on_message(self, msg) -> None:
        """A nav_msgs/Odometry (or anything with its header and pose.pose)."""
        pose = pose_matrix(msg.pose.pose.position, msg.pose.pose.orientation)
        if pose is None:
            self._invalid()
        else:
            self.add(stamp_seconds(msg.header), pose)

    def add(self, stamp: float, pose: np.ndarray) -> None:
        """One pose (camera to fixed frame) at `stamp` (s); those older than KEEP_S before the newest are forgotten."""
        with self._lock:
            k = bisect.bisect(self._stamps, stamp)
            self._stamps.insert(k, stamp)
            self._poses.insert(k, pose)
            drop = bisect.bisect_left(self._stamps, self._stamps[-1] - KEEP_S)
            del self._stamps[:drop], self._poses[:drop]
            self._lock.notify_all()

    def at(self, stamp: float, slop: float) -> np.ndarray | None:
        """The pose whose stamp is nearest `stamp`, within `slop` seconds; None without one."""
        with self._lock:
            return self._nearest(stamp, slop)

    def wait(self, stamp: float, slop: float, timeout: float = WAIT_S) -> np.ndarray | None:
        """`at(stamp, slop)`, waiting up to `timeout` s for it while odometry comes (a pose within KEEP_S before
        `stamp`) and none after `stamp + slop` has come yet: a frame taken before its odometry's callback ran is
        not posed without it."""
        end = time.monotonic() + timeout
        with self._lock:
            while True:
                pose = self._nearest(stamp, slop)
                coming = bool(self._stamps) and stamp - KEEP_S <= self._stamps[-1] <= stamp + slop
                left = end - time.monotonic()
                if pose is not None or not coming or left <= 0:
                    return pose
                self._lock.wait(left)

    def _nearest(self, stamp: float, slop: float) -> np.ndarray | None:
        if not self._stamps:
            return None
        k = bisect.bisect(self._stamps, stamp)
        near = min((i for i in (k - 1, k) if 0 <= i < len(self._stamps)), key=lambda i: abs(self._stamps[i] - stamp))
        return self._poses[near].copy() if abs(self._stamps[near] - stamp) <= slop else None
