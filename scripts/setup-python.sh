#!/usr/bin/env bash
# Creates the two Python environments the project uses (idempotent):
#   sim/.venv  the simulator (PyBullet, mcap writers, rosbags and pytest for its tests)
#              and Ray (generation and retraining on a cluster, docs/retraining.md)
#   .venv      rclpy (Jazzy, from PyPI wheels; no ROS install) for the ROS 2 interop tests
set -euo pipefail
cd "$(dirname "$0")/.."
python="${PYTHON:-python3}"
if [ ! -x sim/.venv/bin/python ]; then
  "$python" -m venv sim/.venv
fi
sim/.venv/bin/python -m pip install --quiet --upgrade pip
sim/.venv/bin/python -m pip install --quiet -r sim/requirements.txt
sim/.venv/bin/python -m pip install --quiet -r sim/requirements-ray.txt
bash tests/ros/setup_venv.sh
