"""scripts/retrain/ship_thresholds.py: the pairs chosen on validation, into a config."""

from __future__ import annotations

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from ship_thresholds import chosen_pairs, rewrite  # noqa: E402


def grid(*triggers: float) -> list[dict]:
    return [{"trigger": t, "release": round(t - 0.3, 3)} for t in triggers]


def test_top_of_grid_pairs_keep_three_places_and_a_missed_budget_is_said(tmp_path):
    (tmp_path / "selected.txt").write_text("mp mp-pp-s1 0.5\np p-pp-s1 0.6\n")
    # As the lab writes an f32 0.995: 0.9950000047683716 (two places would round it to 1.0: never on).
    (tmp_path / "mp-thresholds.json").write_text(json.dumps({
        "chosen": {"trigger": 0.9950000047683716, "release": 0.6950000047683716},
        "grid": grid(0.9, 0.995), "max_false_alarms_per_min": 0.1, "max_held_share": 0.01}))
    (tmp_path / "p-thresholds.json").write_text(json.dumps({
        "chosen": None, "grid": grid(0.9, 0.98, 0.995), "max_false_alarms_per_min": 0.1, "max_held_share": 0.01}))
    pairs = chosen_pairs(tmp_path)
    assert pairs["mp"][:2] == (0.995, 0.695)
    assert "<= 0.1 false alarms / min and <= 1% of walking held on validation" in pairs["mp"][2]
    assert pairs["p"][:2] == (0.995, 0.695) and pairs["p"][2].startswith("no pair kept")
    text = rewrite("[model]\ntrigger = 0.7\nrelease = 0.4\n", pairs)
    assert "mp = [0.995, 0.695]" in text and "trigger = 0.7\n" in text


def test_a_network_not_shipped_keeps_its_line(tmp_path):
    (tmp_path / "selected.txt").write_text("mp mp-pp-s1 0.5\n")
    (tmp_path / "mp-thresholds.json").write_text(json.dumps({
        "chosen": {"trigger": 0.98, "release": 0.68}, "grid": grid(0.98), "max_false_alarms_per_min": 0.1}))
    before = rewrite("[model]\ntrigger = 0.7\nrelease = 0.4\n", {
        "emp": (0.7, 0.4, "a"), "mp": (0.8, 0.5, "b"), "ep": (0.9, 0.6, "c"), "p": (0.95, 0.65, "d")})
    after = rewrite(before, chosen_pairs(tmp_path))
    lines = [x for x in after.splitlines() if x[:3] in ("emp", "mp ", "ep ", "p =")]
    assert lines == ["emp = [0.7, 0.4]     # a", "mp = [0.98, 0.68]    # <= 0.1 false alarms / min on validation",
                     "ep = [0.9, 0.6]      # c", "p = [0.95, 0.65]     # d"]
