#!/usr/bin/env bash
# Build axispose_msgs and install it into a Python virtual environment that holds rclpy from the registry
# wheels (the environment is then its ament prefix, as for the wheels' own message packages). In a ROS install,
# build it with colcon instead: `colcon build --paths . axispose_msgs`.
#   tools/build_msgs.sh VENV
set -euo pipefail
VENV=$(cd "${1:?usage: tools/build_msgs.sh VENV}" && pwd)
ROOT=$(cd "$(dirname "$0")/.." && pwd)
BUILD=$(mktemp -d)
trap 'rm -rf "$BUILD"' EXIT
"$VENV/bin/python" -m pip install -q -r "$ROOT/axispose_msgs/build-requirements.txt"
export AMENT_PREFIX_PATH="$VENV"  # where rosidl looks up the available type supports
# $ORIGIN/../../..: the Python extension modules in lib/pythonX.Y/site-packages/axispose_msgs find the libraries
# in lib/ without LD_LIBRARY_PATH.
cmake -S "$ROOT/axispose_msgs" -B "$BUILD" -G Ninja -DCMAKE_PREFIX_PATH="$VENV" -DCMAKE_INSTALL_PREFIX="$VENV" \
    -DPython3_EXECUTABLE="$VENV/bin/python" -DBUILD_TESTING=OFF -DCMAKE_BUILD_TYPE=Release \
    -DCMAKE_INSTALL_RPATH='$ORIGIN:$ORIGIN/../../..' > "$BUILD/configure.log" || { cat "$BUILD/configure.log"; exit 1; }
cmake --build "$BUILD" > "$BUILD/build.log" || { tail -40 "$BUILD/build.log"; exit 1; }
cmake --install "$BUILD" > /dev/null
"$VENV/bin/python" -c "from axispose_msgs.msg import DetectionArray; DetectionArray()"
echo "axispose_msgs installed into $VENV"
