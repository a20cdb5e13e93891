"""What `replay` reads from the recorded bag: its messages grouped by frame, the camera stream's decoded for the
player (`ros_message`), and the ground truth kept aside for the scores (`Truth`)."""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field

import numpy as np
from nav_msgs.msg import Odometry
from rclpy.serialization import deserialize_message
from scipy.spatial.transform import Rotation
from sensor_msgs.msg import CameraInfo, Image, RegionOfInterest

from axispose_ros.bag import CAMERA_INFO, GT_PREFIX, IMAGE, MODELS_PREFIX, ODOMETRY, BagError, BagMessage, cloud_points, deserialize

ROS_TYPES = {IMAGE: Image, CAMERA_INFO: CameraInfo, "sensor_msgs/msg/RegionOfInterest": RegionOfInterest, ODOMETRY: Odometry}


@dataclass
class Truth:
    """What the bag holds besides the camera stream, for the metrics: GT poses (stamp -> name -> [(R, t)]), K and
    the GT boxes by stamp, the model points by name."""

    gt: dict[int, dict[str, list]] = field(default_factory=lambda: defaultdict(lambda: defaultdict(list)))
    cameras: dict[int, np.ndarray] = field(default_factory=dict)
    boxes: dict[tuple[int, str], tuple[int, int, int, int]] = field(default_factory=dict)
    points: dict[str, np.ndarray] = field(default_factory=dict)

    def take(self, stamp: int, m: BagMessage) -> bool:
        """Keep `m` if it is ground truth (a model's points, a GT pose); False for any other message."""
        if m.topic.startswith(MODELS_PREFIX):
            self.points[m.topic[len(MODELS_PREFIX) :]] = cloud_points(deserialize(m))
        elif m.topic.startswith(GT_PREFIX):
            self.gt[stamp][m.topic[len(GT_PREFIX) :]].append(pose_rt(deserialize(m).pose))
        else:
            return False
        return True


def pose_rt(pose) -> tuple[np.ndarray, np.ndarray]:
    """A geometry_msgs Pose as (R, t)."""
    q = pose.orientation
    R = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
    return R, np.array([pose.position.x, pose.position.y, pose.position.z])


def by_stamp(messages: Iterable[BagMessage]) -> Iterator[tuple[int, list[BagMessage]]]:
    """Consecutive messages grouped by bag time: one camera frame with its boxes and ground truth."""
    group: list[BagMessage] = []
    for m in messages:
        if group and m.stamp_ns != group[0].stamp_ns:
            yield group[0].stamp_ns, group
            group = []
        group.append(m)
    if group:
        yield group[0].stamp_ns, group


def ros_message(m):
    """A bag message as the rclpy message the player publishes; one that does not decode is a BagError."""
    try:
        return deserialize_message(m.raw, ROS_TYPES[m.msgtype])
    except Exception as err:
        raise BagError(f"a '{m.topic}' message at {m.stamp_ns} ns does not decode as {m.msgtype} ({err})") from err
