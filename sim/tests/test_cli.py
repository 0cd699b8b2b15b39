"""The command line: clear errors for bad arguments, resumable and deterministic generation."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def run_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "sim", *args], cwd=REPO, capture_output=True, text=True,
                          timeout=300)


def test_negative_episodes_is_a_clear_error(tmp_path):
    r = run_cli("generate", "--out", str(tmp_path / "d"), "--episodes", "-3")
    assert r.returncode == 2
    assert "--episodes must be at least 1 (got -3)" in r.stderr
    assert "Traceback" not in r.stderr


def test_unwritable_out_is_a_clear_error(tmp_path):
    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    r = run_cli("generate", "--out", str(blocker / "d"), "--episodes", "1")
    assert r.returncode == 2
    assert f"--out {blocker / 'd'}: cannot create the directory" in r.stderr
    r = run_cli("generate", "--out", str(blocker), "--episodes", "1")
    assert r.returncode == 2 and "exists and is not a directory" in r.stderr
    if os.geteuid() != 0:  # root writes anywhere
        ro = tmp_path / "ro"
        ro.mkdir()
        ro.chmod(0o500)
        r = run_cli("generate", "--out", str(ro), "--episodes", "1")
        assert r.returncode == 2 and "not writable" in r.stderr


def test_bad_jobs_and_non_numbers(tmp_path):
    r = run_cli("generate", "--out", str(tmp_path), "--episodes", "1", "--jobs", "0")
    assert r.returncode == 2 and "--jobs must be at least 1" in r.stderr
    r = run_cli("generate", "--out", str(tmp_path), "--episodes", "many")
    assert r.returncode == 2 and "invalid int value: 'many'" in r.stderr


def test_generate_resumes_and_is_deterministic(tmp_path):
    out = tmp_path / "d"
    r = run_cli("generate", "--out", str(out), "--episodes", "2", "--seed", "5", "--duration", "1.5", "--quiet")
    assert r.returncode == 0, r.stderr
    first = {p.name: p.read_bytes() for p in out.glob("*.mcap")}
    assert sorted(first) == ["episode_00000.mcap", "episode_00001.mcap"]
    (out / "episode_00001.mcap").unlink()
    kept_mtime = (out / "episode_00000.mcap").stat().st_mtime_ns
    r = run_cli("generate", "--out", str(out), "--episodes", "2", "--seed", "5", "--duration", "1.5", "--quiet")
    assert r.returncode == 0, r.stderr
    assert '"made": 1' in r.stdout and '"already_there": 1' in r.stdout
    assert (out / "episode_00000.mcap").stat().st_mtime_ns == kept_mtime
    assert (out / "episode_00001.mcap").read_bytes() == first["episode_00001.mcap"]
    r = run_cli("generate", "--out", str(out), "--episodes", "2", "--seed", "6", "--duration", "1.5", "--quiet")
    assert r.returncode == 2 and "made with seed=5" in r.stderr
