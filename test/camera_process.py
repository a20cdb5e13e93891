"""A camera driver in a process of its own, for test_transport.py: full-size rgb8 frames with their CameraInfo at a
camera's rate, sensor-data QoS, stamped on the camera's schedule (its clock at exposure), plus the node's ROI for
`ape` before each frame (so that every frame has a box to estimate). Prints one JSON line: the stamps sent (s)."""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np
import rclpy
from rclpy.qos import qos_profile_sensor_data
from rclpy.time import Time
from sensor_msgs.msg import CameraInfo, Image, RegionOfInterest

from axispose_core.lmo import LMO_K


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--rate", type=float, default=15.0)
    ap.add_argument("--image", default="image")
    ap.add_argument("--camera-info", default="camera_info")
    ap.add_argument("--roi", default="/axispose/roi/ape")
    ap.add_argument("--size", type=int, nargs=2, default=(640, 480), metavar=("W", "H"))
    ap.add_argument("--wait", type=float, default=60.0, help="seconds to wait for the node's subscriptions")
    ap.add_argument("--go-from-stdin", action="store_true", help="start only on a line on stdin (the listener is ready)")
    args = ap.parse_args()
    rclpy.init()
    node = rclpy.create_node("camera_process")
    pub_image = node.create_publisher(Image, args.image, qos_profile_sensor_data)
    pub_info = node.create_publisher(CameraInfo, args.camera_info, qos_profile_sensor_data)
    pub_roi = node.create_publisher(RegionOfInterest, args.roi, 10)
    end = time.monotonic() + args.wait
    while min(p.get_subscription_count() for p in (pub_image, pub_info, pub_roi)) == 0:
        if time.monotonic() > end:
            print("camera_process: no subscriber", file=sys.stderr)
            return 1
        time.sleep(0.05)
    time.sleep(1.0)  # both ends matched: the node's side too
    if args.go_from_stdin:
        sys.stdin.readline()
    w, h = args.size
    pixels = np.random.default_rng(0).integers(0, 256, (h, w, 3), dtype=np.uint8)
    roi = RegionOfInterest(x_offset=280, y_offset=200, width=80, height=90)
    stamps, start = [], time.monotonic()
    first = node.get_clock().now().nanoseconds
    for k in range(args.frames):
        pixels[0, 0, 0] = k % 256  # each frame differs
        img = Image(height=h, width=w, encoding="rgb8", step=w * 3, data=pixels.tobytes())
        img.header.frame_id = "camera_optical"
        # stamped at its exposure on the camera's schedule, as a camera's clock does: a publisher that runs late on a
        # loaded machine must not read as frames lost in transport
        img.header.stamp = Time(nanoseconds=first + round(k * 1e9 / args.rate)).to_msg()
        info = CameraInfo(header=img.header, width=w, height=h, distortion_model="plumb_bob", d=[0.0] * 5)
        info.k = [float(v) for v in np.asarray(LMO_K).ravel()]
        pub_roi.publish(roi)
        pub_info.publish(info)
        pub_image.publish(img)
        stamps.append(img.header.stamp.sec + 1e-9 * img.header.stamp.nanosec)
        time.sleep(max(0.0, start + (k + 1) / args.rate - time.monotonic()))
    time.sleep(1.0)  # let the last frames leave before the participant goes
    print(json.dumps({"stamps": stamps}))
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
