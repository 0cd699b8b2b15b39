"""scripts/compose_set.py on the repository's fixture data set."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[3]
FIXTURES = REPO / "tests" / "fixtures"
SCRIPT = REPO / "scripts" / "retrain" / "compose_set.py"


def compose(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPT), *map(str, args)], capture_output=True, text=True)


def test_every_episode_of_one_set_becomes_the_test_split(tmp_path):
    out = tmp_path / "heldout"
    assert compose(out, "--test", FIXTURES).returncode == 0
    m = json.loads((out / "manifest.json").read_text())
    src = json.loads((FIXTURES / "manifest.json").read_text())
    assert m["train"] == [] and m["validation"] == []
    assert m["test"] == sorted(src["train"] + src["validation"] + src["test"]) and len(m["test"]) == 8
    assert m["generator"]["seed"] == src["generator"]["seed"] and m["generator"]["subset"]
    for episode in m["test"]:
        assert (out / episode).resolve() == (FIXTURES / episode).resolve()


def test_splits_of_two_sets_are_joined_under_prefixed_names(tmp_path):
    other = tmp_path / "calib"
    shutil.copytree(FIXTURES, other, ignore=shutil.ignore_patterns("real", "*.json"))
    (other / "manifest.json").write_text(json.dumps({"train": [], "validation": ["episode_00000.mcap"],
                                                     "test": ["episode_00001.mcap"]}))
    out = tmp_path / "cal"
    r = compose(out, "--validation", f"{FIXTURES}:validation", "--validation", other)
    assert r.returncode == 0, r.stderr
    m = json.loads((out / "manifest.json").read_text())
    src = json.loads((FIXTURES / "manifest.json").read_text())
    assert m["train"] == [] and m["test"] == []
    assert m["validation"] == sorted([f"fixtures_{n}" for n in src["validation"]]
                                     + ["calib_episode_00000.mcap", "calib_episode_00001.mcap"])
    assert (out / "calib_episode_00001.mcap").resolve() == (other / "episode_00001.mcap").resolve()
    assert (out / f"fixtures_{src['validation'][0]}").resolve() == (FIXTURES / src["validation"][0]).resolve()


def test_an_episode_named_twice_or_an_unknown_split_is_refused(tmp_path):
    r = compose(tmp_path / "o", "--validation", f"{FIXTURES}:validation", "--test", FIXTURES)
    assert r.returncode == 1 and "named twice" in r.stderr
    assert not (tmp_path / "o").exists()
    r = compose(tmp_path / "o", "--test", f"{FIXTURES}:tests")
    assert r.returncode == 2 and "unknown split 'tests'" in r.stderr
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "manifest.json").write_text(json.dumps({"train": [], "validation": [], "test": []}))
    r = compose(tmp_path / "o", "--test", empty)
    assert r.returncode == 1 and "list no episodes" in r.stderr
