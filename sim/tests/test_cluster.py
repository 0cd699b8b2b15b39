"""Generation on a Ray cluster of two nodes on this machine: the same bytes as the local generator, resumable.

Needs the ray package (sim/requirements-ray.txt, installed by scripts/setup-python.sh);
skipped without it unless FALL_GUARD_REQUIRE_RAY=1 (CI), where a missing ray fails.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from sim.cluster import local_cluster
from sim.dataset import generate

REPO_ROOT = Path(__file__).resolve().parents[2]

try:
    import ray  # noqa: F401
except ImportError:
    if os.environ.get("FALL_GUARD_REQUIRE_RAY") == "1":
        raise
    pytest.skip("ray is not installed (pip install -r sim/requirements-ray.txt)", allow_module_level=True)

SET = ["--episodes", "6", "--seed", "5", "--duration", "1.5"]


@pytest.fixture(scope="module")
def cluster():
    """A head and one worker node, one CPU each."""
    with local_cluster(worker_nodes=1, head_cpus=1) as address:
        yield address


@pytest.fixture(scope="module")
def local_set(tmp_path_factory):
    out = tmp_path_factory.mktemp("local")
    generate(out, episodes=6, seed=5, jobs=1, duration_s=1.5, progress=False)
    return out


def files(directory: Path) -> dict[str, bytes]:
    return {str(p.relative_to(directory)): p.read_bytes() for p in sorted(directory.rglob("*")) if p.is_file()}


def sim_cli(*args: str, **kw) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "sim", "generate", *args], cwd=REPO_ROOT, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, **kw)


def test_a_set_made_on_two_nodes_is_the_local_set_byte_for_byte(cluster, local_set, tmp_path):
    out = tmp_path / "ray"
    p = sim_cli("--out", str(out), *SET, "--ray", cluster)
    stdout, stderr = p.communicate(timeout=600)
    assert p.returncode == 0, stderr
    assert '"made": 6' in stdout
    assert "6/6" in stderr, "the progress bar counts episodes"
    assert files(out) == files(local_set)


def test_a_stopped_ray_run_resumes_to_the_same_set(cluster, local_set, tmp_path):
    out = tmp_path / "ray"
    p = sim_cli("--out", str(out), *SET, "--ray", cluster, "--quiet")
    deadline = time.monotonic() + 600
    while not list(out.glob("episode_*.mcap")):
        assert p.poll() is None, p.communicate()[1]
        assert time.monotonic() < deadline
        time.sleep(0.05)
    p.send_signal(signal.SIGINT)
    p.communicate(timeout=60)
    made_before = len(list(out.glob("episode_*.mcap")))
    assert made_before < 6, "the run was stopped before it finished"
    time.sleep(2)  # the stopped driver's tasks end with it
    p = sim_cli("--out", str(out), *SET, "--ray", cluster, "--quiet")
    stdout, stderr = p.communicate(timeout=600)
    assert p.returncode == 0, stderr
    assert f'"already_there": {made_before}' in stdout
    assert files(out) == files(local_set)


def test_an_unreachable_cluster_is_a_clear_error(tmp_path):
    p = sim_cli("--out", str(tmp_path / "d"), "--episodes", "1", "--ray", "127.0.0.1:1", "--quiet")
    _, stderr = p.communicate(timeout=120)
    assert p.returncode == 2
    assert "cannot join the Ray cluster" in stderr
