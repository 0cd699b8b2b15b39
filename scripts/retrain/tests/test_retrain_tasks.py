"""A unit of the retrain's work queued for Ray (`job`) runs on the data set its step was on.

The evaluation step runs its units on subsets (the test falls of one cause, the
held-out set) by setting SET for them. With RETRAIN_RAY each unit is queued as
a command line that calls `retrain.sh task ...` again on a node; that command
must carry the subset, or the node evaluates the whole training set under the
subset's name. Here a unit is queued as the evaluation step queues it, and its
command line is run as `ray_tasks.py` runs it (split with shlex, in the
checkout), with a recording lab binary in the real one's place: the test is of
the script's plumbing, not of the lab.
"""

from __future__ import annotations

import os
import shlex
import subprocess
from pathlib import Path

REPO = Path(__file__).resolve().parents[3]
RETRAIN = REPO / "scripts" / "retrain" / "retrain.sh"

# Records its arguments and writes the report directory `eval` is asked for.
RECORDING_LAB = """#!/usr/bin/env bash
printf '%s\\n' "$@" >"$LAB_ARGS"
while [ $# -gt 0 ]; do
  if [ "$1" = --out ]; then mkdir -p "$2" && echo '{}' >"$2/metrics.json"; fi
  shift
done
"""


def lab_env(tmp_path: Path, data: Path) -> tuple[dict[str, str], Path]:
    """This machine's environment with the recording lab in the real one's place, no RETRAIN_SET and
    no RETRAIN_RAY; and the file the lab writes its arguments to."""
    lab = tmp_path / "lab"
    lab.write_text(RECORDING_LAB)
    lab.chmod(0o755)
    args = tmp_path / "lab-args.txt"
    env = {k: v for k, v in os.environ.items() if k not in ("RETRAIN_SET", "RETRAIN_RAY")}
    return {**env, "FALL_GUARD_DATA": str(data), "FALL_GUARD_LAB_BIN": str(lab), "LAB_ARGS": str(args)}, args


def data_argument(args: Path) -> str:
    """The `--data` the lab was given."""
    recorded = args.read_text().splitlines()
    return recorded[recorded.index("--data") + 1]


def test_a_queued_evaluation_runs_on_the_subset_its_step_set(tmp_path):
    data = tmp_path / "data"
    subset = data / "bycause" / "push"
    subset.mkdir(parents=True)
    model = tmp_path / "emp-pp-s1.cal.bpk"
    model.write_bytes(b"")
    node_env, args = lab_env(tmp_path, data)

    # The step's shell with SET on the subset, queueing one evaluation.
    queued = subprocess.run(["bash", str(RETRAIN), "task", "job", "eval_group", "emp-pp-push", "paper", str(model)],
                            cwd=REPO, env={**node_env, "RETRAIN_RAY": "127.0.0.1:1", "RETRAIN_SET": str(subset)},
                            capture_output=True, text=True)
    assert queued.returncode == 0, queued.stderr
    queues = list(data.glob(".ray-jobs.*"))
    assert len(queues) == 1, "one queue file"
    lines = [line for line in queues[0].read_text().splitlines() if line.strip()]
    assert len(lines) == 1, lines

    # The node: the command line alone, in an environment without the subset.
    ran = subprocess.run(shlex.split(lines[0]), cwd=REPO, env=node_env, capture_output=True, text=True)
    assert ran.returncode == 0, ran.stderr
    assert args.read_text().splitlines()[0] == "eval"
    assert data_argument(args) == str(subset)
    assert (data / "reports" / "eval-emp-pp-push-paper" / "metrics.json").is_file()


def test_without_a_subset_the_task_runs_on_the_training_set(tmp_path):
    data = tmp_path / "data"
    model = tmp_path / "mp-pp-s1.cal.bpk"
    model.write_bytes(b"")
    env, args = lab_env(tmp_path, data)
    ran = subprocess.run(["bash", str(RETRAIN), "task", "eval_group", "mp-pp", "paper", str(model)],
                         cwd=REPO, env=env, capture_output=True, text=True)
    assert ran.returncode == 0, ran.stderr
    assert data_argument(args) == str(data / "simv6-mixed")
