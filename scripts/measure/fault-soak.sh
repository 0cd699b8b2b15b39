#!/usr/bin/env bash
# The fault soak (tests/fault_soak.rs, docs/daemon.md "Fault soak"): an hour
# of faults from a seeded schedule against `fall-guard run` on the two
# emulated Poppy buses, with a ROS 2 planner and camera (rclpy peers), and
# its JSON report.
#
#   bash scripts/measure/fault-soak.sh [SECONDS [SEED [REPORT]]]
#
# SECONDS: how long the faults go on (default 3600); SEED: the schedule
# (default 1); REPORT: where the report goes (default
# fault-soak-SEED-SECONDSs.json here). Needs the rclpy venv
# (scripts/setup-python.sh). The tests run the 2-minute version.
# FALL_GUARD_SOAK_PROFILE=dev runs the daemon the test suite built (the dev
# profile: dependencies at opt-level 3, fall-guard at 1) instead of a
# release build.
set -euo pipefail
cd "$(dirname "$0")/../.."
seconds=${1:-3600}
seed=${2:-1}
report=${3:-$PWD/fault-soak-$seed-${seconds}s.json}
case $report in /*) ;; *) report=$PWD/$report ;; esac
export FALL_GUARD_REQUIRE_ROS=1
FALL_GUARD_SOAK_S=$seconds FALL_GUARD_SOAK_SEED=$seed FALL_GUARD_SOAK_REPORT=$report \
  cargo test $([ "${FALL_GUARD_SOAK_PROFILE:-release}" = dev ] || echo --release) \
    --test fault_soak -- --nocapture
echo "report: $report"
