"""scripts/ball_in_view.py on the fixture collision fall (episode 7)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[3]
sys.path.insert(0, str(REPO / "scripts" / "retrain"))
sys.path.insert(0, str(REPO))
import ball_in_view  # noqa: E402
from sim.stats import read_episode_metadata  # noqa: E402

EPISODE = REPO / "tests" / "fixtures" / "episode_00007.mcap"


def test_the_ball_is_seen_from_its_launch_and_only_in_its_colour():
    meta = read_episode_metadata(EPISODE)
    assert meta["fall_cause"] == "collision"
    r = ball_in_view.seen_frames(EPISODE, meta)
    assert r["launch"] < r["contact"] <= r["onset"]
    assert r["seen"] and r["seen"][0] == r["launch"]
    assert set(r["seen_by_1s_stop_line"]) <= set(r["seen"])
    assert all(t <= r["onset"] - 30 for t in r["seen_by_1s_stop_line"])
    # The same frames searched for a ball of another colour: nothing is seen.
    hazard = json.loads(meta["hazard"])
    hazard["rgb"] = [0.1, 0.9, 0.9] if hazard["rgb"][1] < 0.5 else [0.9, 0.1, 0.1]
    assert ball_in_view.seen_frames(EPISODE, {**meta, "hazard": json.dumps(hazard)})["seen"] == []
