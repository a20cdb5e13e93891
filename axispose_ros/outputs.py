"""The node's outputs for one processed frame: every posed instance as a Detection, pose topics, markers and the
debug overlay, all with the image's header."""

from __future__ import annotations

import cv2
import numpy as np
from geometry_msgs.msg import Point, Pose, PoseArray, PoseStamped, PoseWithCovarianceStamped
from rclpy.node import Node
from scipy.spatial.transform import Rotation
from sensor_msgs.msg import Image
from visualization_msgs.msg import Marker, MarkerArray

from axispose_core.axis_image import draw_axes
from axispose_core.camera import crop_transform
from axispose_core.estimator import Estimator
from axispose_core.pose_estimate import PoseEstimate
from axispose_core.tracking.poser import Box, Posed
from axispose_msgs.msg import Detection, DetectionArray
from axispose_ros.conversions import rgb_to_image


class PoseOutputs:
    """The publishers of `~/detections`, `~/pose`, `~/pose_cov`, `~/poses/<name>`, `~/pose_array`, `~/markers`
    and `~/debug/axis_image` for the objects in `names` (id -> name)."""

    def __init__(self, node: Node, names: dict[int, str]) -> None:
        self.names = names
        self.pub_pose = node.create_publisher(PoseStamped, "~/pose", 10)
        self.pub_pose_cov = node.create_publisher(PoseWithCovarianceStamped, "~/pose_cov", 10)
        self.pub_object = {i: node.create_publisher(PoseStamped, f"~/poses/{n}", 10) for i, n in names.items()}
        self.pub_array = node.create_publisher(PoseArray, "~/pose_array", 10)
        self.pub_detections = node.create_publisher(DetectionArray, "~/detections", 10)
        self.pub_markers = node.create_publisher(MarkerArray, "~/markers", 10)
        self.pub_debug = node.create_publisher(Image, "~/debug/axis_image", 1)

    def publish(self, header, posed: Posed, estimator: Estimator, rgb: np.ndarray, K: np.ndarray, marker_lifetime: float) -> int:
        """Publish one frame's poses (those refused are left out); returns how many were refused. `~/pose` and
        `~/pose_cov` get each object's highest-scoring instance; the overlay is drawn only while subscribed."""
        estimates = posed.estimates
        array = PoseArray(header=header)
        detections = DetectionArray(header=header)
        markers = MarkerArray(markers=[Marker(header=header, action=Marker.DELETEALL)])  # the last frame's go
        best: dict[int, tuple[float, PoseStamped, np.ndarray | None]] = {}
        refused = sum(not est.ok for est in estimates)
        poses = iter(_poses([est for est in estimates if est.ok]))
        for k, (est, score, box, track) in enumerate(zip(estimates, posed.scores, posed.boxes, posed.track_ids, strict=True)):
            if not est.ok:
                continue
            pose = next(poses)
            array.poses.append(pose)
            detections.detections.append(_detection(est, self.names[est.obj_id], score, pose, box, track))
            stamped = PoseStamped(header=header, pose=pose)
            self.pub_object[est.obj_id].publish(stamped)
            if est.obj_id not in best or score > best[est.obj_id][0]:
                best[est.obj_id] = (score, stamped, est.covariance)
            lengths = estimator.objects[est.obj_id].axes.lengths
            markers.markers.extend(_axis_markers(header, est, self.names[est.obj_id], lengths, k, marker_lifetime))
        for _, stamped, cov in best.values():
            self.pub_pose.publish(stamped)
            if cov is not None:
                msg = PoseWithCovarianceStamped(header=header)
                msg.pose.pose, msg.pose.covariance = stamped.pose, [float(v) for v in cov.ravel()]
                self.pub_pose_cov.publish(msg)
        self.pub_array.publish(array)
        self.pub_detections.publish(detections)
        self.pub_markers.publish(markers)
        if self.pub_debug.get_subscription_count() > 0:
            self.pub_debug.publish(rgb_to_image(debug_overlay(rgb, K, estimates, estimator), header))
        return refused


def _poses(estimates: list[PoseEstimate]) -> list[Pose]:
    """The estimates' poses as messages, their quaternions converted together (one scipy call a frame)."""
    if not estimates:
        return []
    quats = Rotation.from_matrix(np.stack([est.R for est in estimates])).as_quat()  # x, y, z, w
    out = []
    for est, q in zip(estimates, quats, strict=True):
        pose = Pose()
        pose.position.x, pose.position.y, pose.position.z = (float(v) for v in est.t)
        pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w = (float(v) for v in q)
        out.append(pose)
    return out


def _detection(est: PoseEstimate, name: str, score: float, pose: Pose, box: Box, track: int) -> Detection:
    """One posed instance as axispose_msgs/Detection; covariance all zeros (unknown) where the estimator gave none."""
    msg = Detection(obj_id=int(est.obj_id), name=name, score=float(score), box=[float(v) for v in box], track_id=int(track))
    msg.pose.pose = pose
    if est.covariance is not None:
        msg.pose.covariance = [float(v) for v in est.covariance.ravel()]
    return msg


def _axis_markers(header, est: PoseEstimate, name: str, lengths: np.ndarray, instance: int, lifetime: float) -> list[Marker]:
    """Three arrows (X red, Y green, Z blue) from the object's origin, in the camera frame; ids 3 x instance + axis,
    so that two instances of one object keep their own, and gone after `lifetime` seconds (0: until replaced)."""
    out = []
    for k, color in enumerate(((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))):
        m = Marker(header=header, ns=f"axispose/{name}", id=3 * instance + k, type=Marker.ARROW, action=Marker.ADD)
        m.lifetime.sec, m.lifetime.nanosec = int(lifetime), round((lifetime % 1.0) * 1e9) % 1_000_000_000
        start, end = est.t, est.t + est.R[:, k] * lengths[k]
        m.points = [
            Point(x=float(start[0]), y=float(start[1]), z=float(start[2])),
            Point(x=float(end[0]), y=float(end[1]), z=float(end[2])),
        ]
        m.scale.x, m.scale.y, m.scale.z = 0.004, 0.008, 0.01
        m.color.r, m.color.g, m.color.b, m.color.a = (*color, 1.0)
        out.append(m)
    return out


def debug_overlay(rgb: np.ndarray, K: np.ndarray, estimates: list[PoseEstimate], estimator: Estimator) -> np.ndarray:
    """The input with each generated axis image blended into its crop and the estimated axes drawn."""
    out = rgb.copy()
    S = estimator.size
    for est in estimates:
        A = crop_transform(est.center, est.side, S)[:2]
        warped = cv2.warpAffine((est.axis_image * 255).astype(np.uint8), A, (rgb.shape[1], rgb.shape[0]), flags=cv2.WARP_INVERSE_MAP)
        lit = warped.max(axis=2) > 64
        out[lit] = (0.4 * out[lit] + 0.6 * warped[lit]).astype(np.uint8)
        if est.ok:
            bgr = out[..., ::-1].copy()
            draw_axes(bgr, K, est.R, est.t, estimator.objects[est.obj_id].axes.lengths)
            out = bgr[..., ::-1].copy()
    return out
