#!/usr/bin/env python3
"""Run commands as tasks on a Ray cluster, each with the CPUs and GPUs it needs.

The retrain (``retrain.sh`` with ``RETRAIN_RAY=ADDRESS``) hands each training,
calibration and evaluation run of a step to this program, one command a line
on standard input; each becomes one Ray task that runs the command in the
repository root of the node it lands on (the same checkout path on every node)
and returns its exit status. The commands write their results, checkpoints and
logs into the data directory, which every node sees at the same path (shared
storage; ``docs/retraining.md``).

    printf '%s\\n' "bash scripts/retrain/retrain.sh task train_one p-s1 --ablation P --seed 1" |
        ray_tasks.py --address HEAD:6379 --cpus 1 --gpus 0 --env FALL_GUARD_DATA

Prints one line per finished task (status, seconds, node, command) and exits
with 1 when any task failed, after every task has ended, 2 on a bad argument
or a cluster it cannot join.
"""

from __future__ import annotations

import argparse
import os
import shlex
import socket
import subprocess
import sys
import time
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO_ROOT))  # sim.cluster: how this checkout joins a cluster


def run_command(argv: list[str], repo: str, env: dict[str, str]) -> tuple[int, float, str]:
    """Run ARGV in REPO with ENV added to the node's environment; returns (status, seconds, node)."""
    t0 = time.monotonic()
    status = subprocess.run(argv, cwd=repo, env={**os.environ, **env}).returncode
    return status, time.monotonic() - t0, socket.gethostname()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--address", default=None,
                   help="the Ray head (HOST:PORT or auto); without it $RAY_ADDRESS, else a local cluster")
    p.add_argument("--cpus", type=float, default=1.0, help="CPUs each task holds (default 1)")
    p.add_argument("--gpus", type=float, default=0.0, help="GPUs each task holds (default 0)")
    p.add_argument("--env", action="append", default=[], metavar="NAME",
                   help="an environment variable of this shell passed to every task (repeatable)")
    args = p.parse_args(argv)
    if args.cpus <= 0 or args.gpus < 0:
        print(f"error: --cpus must be > 0 and --gpus >= 0 (got {args.cpus}, {args.gpus})", file=sys.stderr)
        return 2
    commands = [shlex.split(line) for line in sys.stdin if line.strip()]
    if not commands:
        return 0

    from sim.cluster import ClusterError, connect
    try:
        ray = connect(args.address)
    except ClusterError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    env = {name: os.environ[name] for name in args.env if name in os.environ}
    task = ray.remote(num_cpus=args.cpus, num_gpus=args.gpus, max_retries=0)(run_command)
    pending = {task.remote(c, str(REPO_ROOT), env): c for c in commands}
    failed = 0
    while pending:
        done, _ = ray.wait(list(pending), num_returns=1)
        for ref in done:
            command = pending.pop(ref)
            try:
                status, seconds, node = ray.get(ref)
            except ray.exceptions.RayError as e:  # the node or the worker was lost
                status, seconds, node = -1, 0.0, f"lost ({type(e).__name__})"
            failed += status != 0
            print(f"{'ok' if status == 0 else f'FAILED ({status})'} {seconds:.1f} s on {node}: "
                  f"{shlex.join(command)}", flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
