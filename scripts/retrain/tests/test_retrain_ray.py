"""The retrain's training step through Ray (RETRAIN_RAY) writes the model files the local step writes.

A two-run sweep (P seeds 1 and 2, one epoch each, on the fixture data set) is
trained by `retrain.sh train` on this machine, then again on a two-node Ray
cluster on this machine, in the same data directory; the model files are
compared byte for byte. Needs the lab binary (target/debug/fall-guard-lab, which
`cargo test --workspace` builds before the Python suites run, or
FALL_GUARD_LAB_BIN) and ray (sim/requirements-ray.txt); skipped without them
unless FALL_GUARD_REQUIRE_RAY=1 (CI), where either missing fails.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[3]
RETRAIN = REPO / "scripts" / "retrain" / "retrain.sh"
sys.path.insert(0, str(REPO))
from sim.cluster import local_cluster  # noqa: E402
FIXTURES = REPO / "tests" / "fixtures"
LAB = Path(os.environ.get("FALL_GUARD_LAB_BIN", REPO / "target" / "debug" / "fall-guard-lab"))
REQUIRED = os.environ.get("FALL_GUARD_REQUIRE_RAY") == "1"

try:
    import ray  # noqa: F401
except ImportError:
    if REQUIRED:
        raise
    pytest.skip("ray is not installed (pip install -r sim/requirements-ray.txt)", allow_module_level=True)

if not LAB.is_file():
    if REQUIRED:
        raise FileNotFoundError(f"{LAB}: build the lab binary first (cargo build -p fall-guard-lab)")
    pytest.skip(f"{LAB} is not built", allow_module_level=True)

RUNS = ("p-s1", "p-s2")


@pytest.fixture(scope="module")
def cluster():
    """A head and one worker node, one CPU each."""
    with local_cluster(worker_nodes=1, head_cpus=1) as address:
        yield address


def retrain_train(data: Path, **env: str) -> subprocess.CompletedProcess:
    full = {**os.environ, "FALL_GUARD_DATA": str(data), "FALL_GUARD_LAB_BIN": str(LAB),
            "SIM_PYTHON": sys.executable, "RETRAIN_RUNS": " ".join(RUNS), "RETRAIN_TRAIN_ARGS": "--epochs 1",
            **env}
    return subprocess.run(["bash", str(RETRAIN), "train"], cwd=REPO, env=full, capture_output=True, text=True,
                          timeout=900)


def test_a_training_sweep_through_ray_writes_the_local_model_files(cluster, tmp_path):
    data = tmp_path / "data"
    shutil.copytree(FIXTURES, data / "simv6-mixed", ignore=shutil.ignore_patterns("real"))
    (data / "simv6-mixed" / ".complete").touch()

    local = retrain_train(data, RETRAIN_PARALLEL="2")
    assert local.returncode == 0, local.stderr
    runs = data / "runs"
    here = {name: (runs / f"{name}.bpk").read_bytes() for name in RUNS}
    for name in RUNS:
        for f in runs.glob(f"{name}.*"):
            shutil.rmtree(f) if f.is_dir() else f.unlink()

    on_ray = retrain_train(data, RETRAIN_RAY=cluster)
    assert on_ray.returncode == 0, on_ray.stderr
    assert "on Ray" in on_ray.stderr, "the runs went to the cluster"
    for name in RUNS:
        assert (runs / f"{name}.bpk").read_bytes() == here[name], f"{name}: not the local run's bytes"
        assert (runs / f"{name}.done").exists()
