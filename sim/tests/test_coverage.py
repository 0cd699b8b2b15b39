"""sim coverage: the real walk's joint readings against a generated set's range."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from sim.__main__ import main
from sim.coverage import coverage, joint_positions, markdown
from sim.robot import JOINT_NAMES

REAL = Path(__file__).resolve().parents[2] / "tests" / "fixtures" / "real" / "poppy_muffin_walk.mcap"


@pytest.mark.skipif(not REAL.exists(), reason="needs tests/fixtures/real/poppy_muffin_walk.mcap")
def test_coverage_compares_every_joint_and_says_what_lies_outside(small_dataset):
    out, _ = small_dataset
    report = coverage(out, REAL)
    assert [t["joint"] for t in report["joints"]] == list(JOINT_NAMES)
    walk = np.rad2deg(joint_positions(REAL))
    assert report["real_readings"] == len(walk) > 500
    for j, t in enumerate(report["joints"]):
        assert t["set_p0.1_deg"] <= t["set_p99.9_deg"]
        assert t["real_min_deg"] == round(float(walk[:, j].min()), 2)
        inside = t["set_p0.1_deg"] <= t["real_min_deg"] and t["real_max_deg"] <= t["set_p99.9_deg"]
        # (rounded figures: a reading within 0.01 deg of a bound may go either way)
        if min(abs(t["real_min_deg"] - t["set_p0.1_deg"]), abs(t["real_max_deg"] - t["set_p99.9_deg"])) > 0.02:
            assert t["real_inside"] == inside, t
        assert (t["real_share_inside"] == 1.0) == t["real_inside"]
    # Two 4 s episodes cannot hold a trunk swaying 36 deg: the report says so.
    assert not next(t for t in report["joints"] if t["joint"] == "abs_x")["real_inside"]
    assert report["joints_inside"] == sum(t["real_inside"] for t in report["joints"])
    assert markdown(report).count("\n") == len(JOINT_NAMES) + 1


def test_coverage_bad_arguments_are_clear_errors(tmp_path, capsys):
    assert main(["coverage", str(tmp_path), "--max-episodes", "0"]) == 2
    assert "--max-episodes" in capsys.readouterr().err
    assert main(["coverage", str(tmp_path)]) == 1
    assert "no .mcap recordings" in capsys.readouterr().err
