"""scripts/retrain/reports.py: the retrain's questions about a warnings report, a shipped file, a threshold choice."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[3]
SCRIPT = REPO / "scripts" / "retrain" / "reports.py"
MIXED = ("simv6-mixed (sim generator 6: 2,000 dynamic-gait episodes, seed 1, and 400 hardware-gait episodes, "
         "seed 21; simulated data)")


def reports(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPT), *map(str, args)], capture_output=True, text=True)


def test_a_report_is_current_only_for_its_model_horizon_and_hold(tmp_path):
    (tmp_path / "runs").mkdir()
    model = tmp_path / "runs" / "emp-pp-s3.cal.bpk"
    model.write_bytes(b"")
    report = tmp_path / "warnings.json"
    report.write_text(json.dumps({"model": "runs/emp-pp-s3.cal.bpk", "horizon_ms": 2000, "release_hold_ms": 1000}))
    assert reports("current", report, model, 2000, 1000, tmp_path).returncode == 0
    assert reports("current", report, model, 1000, 1000, tmp_path).returncode == 1
    assert reports("current", report, model, 2000, 500, tmp_path).returncode == 1
    assert reports("current", report, tmp_path / "runs" / "mp-pp-s1.cal.bpk", 2000, 1000, tmp_path).returncode == 1
    # An older report names its model by its absolute path: taken too.
    report.write_text(json.dumps({"model": str(model), "horizon_ms": 2000, "release_hold_ms": 1000}))
    assert reports("current", report, model, 2000, 1000, tmp_path).returncode == 0


def test_a_shipped_file_names_its_run():
    r = reports("shipped-run", REPO / "models" / "p.bpk", MIXED)
    assert r.returncode == 0, r.stderr
    # P's seed 2 early-stopped (best epoch 2 of 5): the plan's run, restored in a new data directory.
    assert r.stdout.split() == ["True", "p", "2", "planned", "-pp"]
    assert reports("shipped-run", REPO / "models" / "p.bpk", "another set").stdout.split()[0] == "False"
    # EMP was written after 3 of its epochs, the loss still falling: its run resumes instead.
    assert reports("shipped-run", REPO / "models" / "emp.bpk", MIXED).stdout.split()[:2] == ["False", "emp"]


def test_the_chosen_pair_or_the_highest_trigger(tmp_path):
    f = tmp_path / "t.json"
    grid = [{"trigger": 0.7, "release": 0.4}, {"trigger": 0.9, "release": 0.6}]
    f.write_text(json.dumps({"chosen": {"trigger": 0.7, "release": 0.4}, "grid": grid}))
    assert reports("chosen-pair", f).stdout.split() == ["0.7", "0.4"]
    f.write_text(json.dumps({"chosen": None, "grid": grid}))
    assert reports("chosen-pair", f).stdout.split() == ["0.9", "0.6"]


def test_warned_ahead_is_the_chosen_pairs_or_the_highest_triggers(tmp_path):
    f = tmp_path / "t.json"
    grid = [
        {"trigger": 0.7, "release": 0.4, "warned_by_0_5s": 90},
        {"trigger": 0.9, "release": 0.6, "warned_by_0_5s": 40},
    ]
    f.write_text(json.dumps({"chosen": grid[0], "grid": grid}))
    assert reports("warned-ahead", f).stdout.strip() == "90"
    f.write_text(json.dumps({"chosen": None, "grid": grid}))
    assert reports("warned-ahead", f).stdout.strip() == "40"


def test_a_bad_call_says_how_to_call_it():
    r = reports("nothing")
    assert r.returncode == 2 and "usage" in r.stderr


def test_the_causes_are_the_test_splits_most_falls_first(tmp_path):
    (tmp_path / "causes.json").write_text(json.dumps({"causes": {"perturbation": {}, "push": {}, "obstacle": {}}}))
    assert reports("causes", tmp_path).stdout.split() == ["perturbation", "push", "obstacle"]
    (tmp_path / "causes.json").write_text(json.dumps({"causes": {}}))
    r = reports("causes", tmp_path)
    assert r.returncode == 0 and r.stdout.strip() == ""
