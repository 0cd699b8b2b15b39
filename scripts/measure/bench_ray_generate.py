#!/usr/bin/env python3
"""Wall time of `sim generate --ray` on a cluster of 1 and of 2 worker nodes on this machine.

Each round starts a Ray cluster on this machine (Ray's `ray.cluster_utils.Cluster`:
a head that runs no task, and N worker nodes of one CPU each, the processes
`ray start` makes), generates the same set into a fresh directory through it,
and stops it; the rounds alternate 1, 2, 1, 2, ... so that a change in the
machine's load falls on both. Prints one JSON line per round and a summary with
the median wall time of each and their ratio (the speed-up of the second node).

    sim/.venv/bin/python scripts/measure/bench_ray_generate.py --episodes 20 --rounds 2 --json OUT.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))
from sim.cluster import local_cluster  # noqa: E402


def one_round(nodes: int, episodes: int, seed: int, duration_s: float) -> dict:
    with local_cluster(worker_nodes=nodes, head_cpus=0) as address, tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        r = subprocess.run([sys.executable, "-m", "sim", "generate", "--out", str(Path(tmp) / "set"),
                            "--episodes", str(episodes), "--seed", str(seed), "--duration", str(duration_s),
                            "--ray", address, "--quiet"], cwd=REPO, capture_output=True, text=True)
        wall = time.perf_counter() - t0
    if r.returncode != 0:
        raise RuntimeError(f"generate failed: {r.stderr[-2000:]}")
    return {"worker_nodes": nodes, "episodes": episodes, "wall_s": round(wall, 2)}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--episodes", type=int, default=20)
    p.add_argument("--seed", type=int, default=21)
    p.add_argument("--duration", type=float, default=10.0)
    p.add_argument("--rounds", type=int, default=2, help="rounds of each cluster size")
    p.add_argument("--json", type=Path, default=None)
    args = p.parse_args()
    rows = []
    for _ in range(args.rounds):
        for nodes in (1, 2):
            load = os.getloadavg()[0]
            row = {**one_round(nodes, args.episodes, args.seed, args.duration), "load_avg_1min_before": load}
            print(json.dumps(row), flush=True)
            rows.append(row)
    med = {n: statistics.median(r["wall_s"] for r in rows if r["worker_nodes"] == n) for n in (1, 2)}
    summary = {"machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs",
               "episodes": args.episodes, "duration_s": args.duration, "rounds": rows,
               "median_wall_s": {str(n): med[n] for n in med}, "speed_up_2_over_1": round(med[1] / med[2], 2)}
    print(json.dumps({k: summary[k] for k in ("median_wall_s", "speed_up_2_over_1")}))
    if args.json:
        args.json.write_text(json.dumps(summary, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
