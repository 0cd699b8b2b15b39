"""scripts/heldout_set.py on the repository's fixture data set."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
FIXTURES = REPO / "tests" / "fixtures"


def test_every_episode_of_the_set_becomes_its_test_split(tmp_path):
    out = tmp_path / "heldout"
    subprocess.run([sys.executable, str(REPO / "scripts" / "heldout_set.py"), str(FIXTURES), str(out)],
                   check=True, capture_output=True)
    m = json.loads((out / "manifest.json").read_text())
    src = json.loads((FIXTURES / "manifest.json").read_text())
    assert m["train"] == [] and m["validation"] == []
    assert m["test"] == sorted(src["train"] + src["validation"] + src["test"])
    assert len(m["test"]) == 8
    assert m["generator"]["seed"] == src["generator"]["seed"] and m["generator"]["subset"]
    for episode in m["test"]:
        assert (out / episode).resolve() == (FIXTURES / episode).resolve()


def test_a_set_without_episodes_is_refused(tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "manifest.json").write_text(json.dumps({"train": [], "validation": [], "test": []}))
    r = subprocess.run([sys.executable, str(REPO / "scripts" / "heldout_set.py"), str(empty), str(tmp_path / "o")],
                       capture_output=True, text=True)
    assert r.returncode == 1 and "lists no episodes" in r.stderr
    assert not (tmp_path / "o").exists()
