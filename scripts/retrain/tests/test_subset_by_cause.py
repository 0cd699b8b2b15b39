"""scripts/subset_by_cause.py on the repository's fixture data set."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[3]
FIXTURES = REPO / "tests" / "fixtures"


def test_the_subsets_hold_each_cause_with_the_walks(tmp_path):
    # The fixtures' test split: episode 6 walks (sigma 0.01), episode 7 falls
    # by collision (sigma 0.035); validation: 4 walks, 5 falls by perturbation.
    out = tmp_path / "bycause"
    subprocess.run([sys.executable, str(REPO / "scripts" / "retrain" / "subset_by_cause.py"), str(FIXTURES), str(out)],
                   check=True, capture_output=True)

    def test_split(name: str) -> list[str]:
        m = json.loads((out / name / "manifest.json").read_text())
        assert m["train"] == [] and m["validation"] == []
        assert m["generator"]["seed"] == 7 and m["generator"]["subset"]
        for episode in m["test"]:
            assert (out / name / episode).resolve() == (FIXTURES / episode).resolve()
        return m["test"]

    assert test_split("collision") == ["episode_00006.mcap", "episode_00007.mcap"]
    assert test_split("perturbation") == ["episode_00006.mcap"]
    assert test_split("high-sigma") == ["episode_00007.mcap"]
    assert test_split("validation-collision") == ["episode_00004.mcap"]
