#!/usr/bin/env bash
# Creates `.venv` at the repository root with rclpy (Jazzy) and the message
# packages the ROS 2 interop tests use. The `ros-jazzy-*` wheels on PyPI
# carry rclpy, rmw_fastrtps and the type support libraries themselves: no ROS
# installation, no `source setup.bash` and no environment variables needed.
#
# Usage: bash tests/ros/setup_venv.sh   (idempotent; PYTHON=python3.12 to choose)
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)"
python="${PYTHON:-python3}"
venv="$root/.venv"
if [ ! -x "$venv/bin/python" ]; then
    "$python" -m venv "$venv"
fi
"$venv/bin/python" -m pip install --quiet --upgrade pip
"$venv/bin/python" -m pip install --quiet \
    'ros-jazzy-rclpy[fastrtps]' \
    ros-jazzy-std-msgs \
    ros-jazzy-diagnostic-msgs \
    ros-jazzy-trajectory-msgs \
    ros-jazzy-sensor-msgs
"$venv/bin/python" - <<'PY'
import rclpy, std_msgs.msg, diagnostic_msgs.msg, trajectory_msgs.msg, sensor_msgs.msg
print("rclpy venv ready:", rclpy.__file__)
PY
