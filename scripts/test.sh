#!/usr/bin/env bash
# The whole test suite: Rust (unit, integration with real MCAP files, a real pty and
# real rclpy peers) and the simulator's pytest suite. Run scripts/setup-python.sh once first.
set -euo pipefail
cd "$(dirname "$0")/.."

# The crate graph: the robot's binary links the runtime, never the lab nor
# plotters, linfa or indicatif; inside each library crate the modules import
# one another without a cycle (docs/architecture.md).
bash scripts/checks/check-crates.sh
python3 scripts/checks/check-layers.py

# DDS Security (cargo feature `security`, docs/ros.md "Security"): secured
# peers against the daemon. Only the DDS crates and fall-guard's are built
# again for it. First, so that target/debug/fall-guard (packaged by
# scripts/package/test-deb.sh) is the default build's, made by the next line.
cargo test --features security --test ros_security

# The whole workspace: the robot binary's tests and example, the runtime's
# (crates/runtime) and the lab's (crates/lab) tests and benches, and the
# test kit (crates/testkit: the bus emulator and synthetic recordings the
# tests use; a dev-dependency, out of the shipped build).
cargo test --workspace --all-targets --no-fail-fast
cargo test --workspace --doc

if [ -x sim/.venv/bin/python ]; then
  # The simulator, and the retrain's scripts (model card, subsets by cause).
  sim/.venv/bin/python -m pytest -q sim/tests scripts/retrain/tests
else
  echo "sim/.venv missing: run 'bash scripts/setup-python.sh' first" >&2
  exit 1
fi
