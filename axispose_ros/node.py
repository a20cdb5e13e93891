"""`axispose_node`: the ROS 2 entry point (init -> spin -> destroy -> shutdown).

The node validates its parameters at start and refuses, with a clear error, a checkpoint it cannot load. The
estimator it will run (AGM + TBM) and the Image/CameraInfo pipeline are the "ROS 2 node" issue's work; until
an estimator checkpoint exists, every start ends at that check.
"""

from __future__ import annotations

import sys
from pathlib import Path

import rclpy
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.node import Node

from axispose_core.checkpoint import CheckpointError, read_metadata

ESTIMATOR_KIND = "estimator"


class AxisPoseNode(Node):
    """Pose estimation node; construction fails with CheckpointError when `checkpoint` is unusable."""

    def __init__(self) -> None:
        super().__init__("axispose")
        self.declare_parameter(
            "checkpoint", "", ParameterDescriptor(description="path of the AxisPose estimator checkpoint (.safetensors)")
        )
        path = Path(self.get_parameter("checkpoint").value)
        if not str(path) or str(path) == ".":
            raise CheckpointError("parameter 'checkpoint' is empty: pass -p checkpoint:=/path/to/model.safetensors")
        read_metadata(path, ESTIMATOR_KIND)


def main(args: list[str] | None = None) -> int:
    rclpy.init(args=args)
    try:
        node = AxisPoseNode()
    except CheckpointError as err:
        print(f"axispose_node: {err}", file=sys.stderr)
        rclpy.try_shutdown()
        return 2
    try:
        rclpy.spin(node)
    except KeyboardInterrupt:
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
