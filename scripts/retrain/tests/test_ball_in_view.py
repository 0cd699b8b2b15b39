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


def test_only_the_balls_collisions_are_counted():
    hazard = json.dumps({"launched": True, "launch_tick": 60, "rgb": [0.9, 0.1, 0.1]})
    ball = {"fall_cause": "collision", "hazard": hazard, "contacts_ns": json.dumps({"ball": 5_000_000_000})}
    assert ball_in_view.ball_fall(ball)
    # Generator 6: a collision with furniture, the ball launched elsewhere or never, is not the ball's.
    assert not ball_in_view.ball_fall({**ball, "contacts_ns": json.dumps({"chair": 5_000_000_000})})
    assert not ball_in_view.ball_fall({**ball, "hazard": "null", "contacts_ns": json.dumps({"sofa": 1})})
    assert not ball_in_view.ball_fall({**ball, "hazard": json.dumps({"launched": False})})
    # A push or an obstacle fall in an episode with the ball is not the ball's either.
    assert not ball_in_view.ball_fall({**ball, "fall_cause": "push"})
    assert not ball_in_view.ball_fall({**ball, "fall_cause": "obstacle"})
    # Generator 5 and older list no contacts: a collision with the ball launched is the ball's.
    assert ball_in_view.ball_fall({"fall_cause": "collision", "hazard": hazard})
