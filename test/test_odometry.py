"""The camera's poses from odometry: messages to transforms, and the one nearest a frame's stamp."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
from scipy.spatial.transform import Rotation

from axispose_ros.odometry import KEEP_S, CameraPoses, pose_matrix


def _pose(t: list[float], q: list[float]) -> tuple[SimpleNamespace, SimpleNamespace]:
    return SimpleNamespace(x=t[0], y=t[1], z=t[2]), SimpleNamespace(x=q[0], y=q[1], z=q[2], w=q[3])


def test_a_pose_message_is_its_transform_and_a_non_pose_is_none():
    q = Rotation.from_euler("xyz", [10, -20, 30], degrees=True).as_quat()
    T = pose_matrix(*_pose([0.1, -0.2, 0.3], list(2 * q)))  # an unnormalised quaternion is the same rotation
    np.testing.assert_allclose(T[:3, :3], Rotation.from_quat(q).as_matrix(), atol=1e-12)
    np.testing.assert_allclose(T[:3, 3], [0.1, -0.2, 0.3])
    assert pose_matrix(*_pose([0, 0, 0], [0, 0, 0, 0])) is None
    assert pose_matrix(*_pose([0, float("nan"), 0], [0, 0, 0, 1])) is None


def test_the_pose_nearest_a_stamp_within_the_slop_and_old_ones_forgotten():
    poses = CameraPoses()
    for k in (3, 0, 1, 2):  # out of order
        T = np.eye(4)
        T[0, 3] = k
        poses.add(10.0 + 0.1 * k, T)
    assert poses.at(10.12, 0.05)[0, 3] == 1.0 and poses.at(10.18, 0.05)[0, 3] == 2.0
    assert poses.at(10.5, 0.05) is None and CameraPoses().at(10.0, 1.0) is None
    poses.add(10.3 + KEEP_S + 0.01, np.eye(4))
    assert poses.at(10.0, 0.05) is None  # forgotten


def test_an_odometry_message_is_added_at_its_stamp_and_a_non_pose_reported():
    invalid = []
    poses = CameraPoses(lambda: invalid.append(1))

    def message(sec: int, w: float) -> SimpleNamespace:
        position, orientation = _pose([0.5, 0.0, 0.0], [0.0, 0.0, 0.0, w])
        stamp = SimpleNamespace(sec=sec, nanosec=500_000_000)
        pose = SimpleNamespace(pose=SimpleNamespace(position=position, orientation=orientation))
        return SimpleNamespace(header=SimpleNamespace(stamp=stamp), pose=pose)

    poses.on_message(message(4, 1.0))
    poses.on_message(message(5, 0.0))
    assert poses.at(4.5, 0.01)[0, 3] == 0.5 and poses.at(5.5, 0.01) is None and invalid == [1]


def test_a_frame_waits_for_the_odometry_of_its_stamp_while_odometry_comes():
    """An image may be taken before its odometry's callback ran: `wait` returns the pose once it comes; at once with
    no odometry at all, or with odometry past the frame already (none will come for it); after `timeout` if it does
    not come."""
    import threading
    import time

    poses = CameraPoses()
    assert poses.wait(10.0, 0.01, timeout=5.0) is None  # no odometry: no wait
    poses.add(9.9, np.eye(4))
    T = np.eye(4)
    T[0, 3] = 1.0
    later = threading.Timer(0.05, poses.add, (10.0, T))
    start = time.monotonic()
    later.start()
    assert poses.wait(10.0, 0.01, timeout=5.0)[0, 3] == 1.0 and time.monotonic() - start < 2.0
    assert poses.wait(9.95, 0.01, timeout=5.0) is None and time.monotonic() - start < 2.0  # odometry is past it
    start = time.monotonic()
    assert poses.wait(10.1, 0.01, timeout=0.1) is None and 0.09 <= time.monotonic() - start < 2.0
