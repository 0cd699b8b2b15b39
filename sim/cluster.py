"""Generation on a Ray cluster: each plan group (its plan search, then its episodes) is one Ray task.

The driver (``generate(..., ray_address=...)``) decides what is missing exactly as
the local generator does; a task writes its plan and its episodes into the
output directory with the same functions the local workers use (``.partial``,
then renamed), so a set made on a cluster is byte for byte the set made on one
machine, however many nodes ran it. The output directory must be the same path
on every node (shared storage), and every node runs the same checkout and
simulator environment (``docs/retraining.md``, "On a Ray cluster").

A stopped run leaves whole files and ``.partial`` ones; the next run removes the
``.partial`` files and makes only what is missing. Progress is counted per
episode by a small actor the tasks report to, so the bar moves as episodes
finish, not only as groups do.
"""

from __future__ import annotations

import os
import socket
from contextlib import contextmanager
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parent.parent


class ClusterError(Exception):
    """Ray is missing or the cluster cannot be reached, with what to do about it."""


def _ray():
    try:
        import ray
    except ImportError as e:
        raise ClusterError("--ray needs the ray package: sim/.venv/bin/pip install -r sim/requirements-ray.txt") from e
    return ray


def _check_reachable(address: str | None, timeout_s: float = 5.0) -> None:
    """Fail at once on a HOST:PORT nobody listens on (Ray itself retries such an address for minutes)."""
    if not address or address == "auto" or "://" in address or ":" not in address:
        return
    host, _, port = address.rpartition(":")
    try:
        socket.create_connection((host, int(port)), timeout=timeout_s).close()
    except ValueError:
        raise ClusterError(f"--ray {address}: not HOST:PORT") from None
    except OSError as e:
        raise ClusterError(f"--ray {address}: cannot join the Ray cluster ({e.strerror or e}); start it with "
                           "`ray start --head` (docs/retraining.md) or give the head's address") from e


def connect(address: str | None):
    """Join the Ray cluster at ADDRESS (``auto``, ``host:port``; None: RAY_ADDRESS, else a local one-machine cluster).

    Tasks import the ``sim`` package from this checkout's path, which must be
    the same on every node.
    """
    ray = _ray()
    if ray.is_initialized():
        return ray
    _check_reachable(address or os.environ.get("RAY_ADDRESS"))
    # A one-machine cluster started here exports no metrics (nothing reads them)
    # and keeps the accelerator variables as Ray's next versions will.
    os.environ.setdefault("RAY_enable_metrics_collection", "0")
    os.environ.setdefault("RAY_ACCEL_ENV_VAR_OVERRIDE_ON_ZERO", "0")
    env = {"PYTHONPATH": os.pathsep.join(p for p in (str(REPO_ROOT), os.environ.get("PYTHONPATH", "")) if p)}
    try:
        ray.init(address=address, runtime_env={"env_vars": env}, log_to_driver=False,
                 include_dashboard=False, logging_level="WARNING")
    except (ConnectionError, RuntimeError, ValueError) as e:
        raise ClusterError(f"--ray {address or '(local)'}: cannot join the Ray cluster ({e}); "
                           "start it with `ray start --head` (docs/retraining.md)") from e
    return ray


@contextmanager
def local_cluster(worker_nodes: int, head_cpus: int):
    """A Ray cluster on this machine, for tests and measurements; yields its address.

    A head of HEAD_CPUS CPUs and WORKER_NODES nodes of one CPU each: Ray's
    ``ray.cluster_utils.Cluster``, the processes `ray start --head` and a
    joining `ray start` make. Stopped on leaving the block.
    """
    _ray()
    from ray.cluster_utils import Cluster
    os.environ.setdefault("RAY_enable_metrics_collection", "0")
    store = 80 * 2**20
    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": head_cpus, "object_store_memory": store,
                                                            "include_dashboard": False})
    try:
        for _ in range(worker_nodes):
            cluster.add_node(num_cpus=1, object_store_memory=store)
        cluster.wait_for_nodes()
        yield cluster.address
    finally:
        cluster.shutdown()


def _group_task(out: str, seed: int, episodes: int, duration_s: float, group: int, indices: list[int],
                search: bool, sigmas: tuple[float, ...], hazard_probability: float, progress,
                gait: str = "dynamic") -> list[dict]:
    """Search GROUP's plan if SEARCH, then make its episodes INDICES; returns their stats."""
    from . import dataset
    if search:
        dataset.find_plan(out, seed, group, duration_s, gait)
    plan = dataset.read_plan(Path(out), group).as_dict()
    rows = []
    for i in indices:
        rows.append(dataset.make_one(out, i, dataset.episode_seed(seed, i), duration_s, plan, sigmas,
                                     hazard_probability))
        progress.add.remote(1)
    return rows


def make_all(out: Path, seed: int, episodes: int, duration_s: float, todo: list[int], missing_plans: list[int],
             sigmas: tuple[float, ...], hazard_probability: float, address: str | None, bar,
             gait: str = "dynamic") -> list[dict]:
    """Make the TODO episodes (and the MISSING_PLANS) as one Ray task per plan group; returns per-episode stats."""
    from .dataset import plan_group
    ray = connect(address)

    @ray.remote(num_cpus=0)
    class Progress:
        def __init__(self) -> None:
            self.done = 0

        def add(self, n: int) -> None:
            self.done += n

        def get(self) -> int:
            return self.done

    task = ray.remote(num_cpus=1, max_retries=2)(_group_task)
    progress = Progress.remote()
    groups: dict[int, list[int]] = {}
    for i in todo:
        groups.setdefault(plan_group(i, episodes), []).append(i)
    # The groups whose plan must be searched first: they are the longest tasks.
    order = sorted(groups, key=lambda g: (g not in missing_plans, g))
    pending = [task.remote(str(out), seed, episodes, duration_s, g, groups[g], g in missing_plans, sigmas,
                           hazard_probability, progress, gait) for g in order]
    stats: list[dict] = []
    shown = 0
    while pending:
        done, pending = ray.wait(pending, num_returns=1, timeout=0.5)
        for ref in done:
            stats.extend(ray.get(ref))
        now = ray.get(progress.get.remote())
        if now > shown:
            bar.update(now - shown)
            shown = now
    return stats
