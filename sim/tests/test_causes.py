"""Generator 6: the balance feedback, the walk it gives, pushes and obstacles as fall causes."""

from __future__ import annotations

import json

import numpy as np
import pytest

from sim.balance import KH, LIMIT_RAD, Balance
from sim.episode import (CAUSE_WINDOW_TICKS, MIN_PROGRESS_M, PLAN_FUTURE_TICKS, RATE_HZ, Episode, Obstacle, Push,
                         outside_cause_probabilities, simulate_episode)
from sim.gait import gait_waypoints
from sim.robot import JOINT_NAMES

J = {n: i for i, n in enumerate(JOINT_NAMES)}


def _episode(n: int = 300, onset: int | None = None, contacts=None, push_tick: int | None = None,
             touching=None) -> Episode:
    fallen = np.zeros(n, bool)
    if onset is not None:
        fallen[onset:] = True
    return Episode(seed=0, sigma=0.005, params=None, n_ticks=n, joints_rad=np.zeros((n, 25)),
                   plan_rad=np.zeros((n, 25)), head_height_m=np.ones(n), fallen=fallen, jpeg_frames=[],
                   standing_head_height_m=0.7176, contacts=dict(contacts or {}), touching_at_onset=dict(touching or {}),
                   push=None if push_tick is None else Push(push_tick, 0.0, 1.0))


def test_fall_cause_is_the_last_outside_cause_within_two_seconds():
    assert _episode(onset=None, push_tick=100).fall_cause is None
    assert _episode(onset=200).fall_cause == "perturbation"
    assert _episode(onset=200, push_tick=150).fall_cause == "push"
    assert _episode(onset=200, push_tick=150).fall_cause_tick == 150
    # A push more than 2 s before the onset is not its cause.
    assert _episode(onset=200, push_tick=200 - CAUSE_WINDOW_TICKS - 1).fall_cause == "perturbation"
    assert _episode(onset=200, contacts={"obstacle": 170}).fall_cause == "obstacle"
    assert _episode(onset=200, contacts={"ball": 170}, push_tick=160).fall_cause == "collision"
    assert _episode(onset=200, contacts={"obstacle": 150}, push_tick=180).fall_cause == "push"
    assert _episode(onset=200, contacts={"table": 190}).fall_cause == "collision"
    # Held by an obstacle for seconds: its touch counts until the onset, its time is the first touch.
    held = _episode(onset=200, contacts={"obstacle": 50}, touching={"obstacle": 190})
    assert held.fall_cause == "obstacle" and held.fall_cause_tick == 50
    assert _episode(onset=200, contacts={"obstacle": 50}, touching={"obstacle": 100}).fall_cause == "perturbation"
    meta = _episode(onset=200, push_tick=150).metadata()
    assert meta["fall_cause"] == "push" and meta["cause_ns"] == str(150 * 10**9 // RATE_HZ)
    assert json.loads(meta["push"])["impulse_ns"] == 1.0


def test_walking_set_has_no_outside_cause():
    assert outside_cause_probabilities(0.0) == {"push_probability": 0.0, "obstacle_probability": 0.0}
    assert min(outside_cause_probabilities(0.2).values()) > 0


def test_balance_brings_the_stance_hips_under_a_forward_fall_and_spares_the_swing_leg():
    plan = np.zeros((10, 25))
    plan[:, J["l_knee_y"]] = 0.3  # the plan lifts the left leg
    b = Balance(plan)
    b.measure = lambda: (0.1, 0.0, 0.0, 0.0)  # leaning 0.1 rad forward, still
    out = b.correct(3, plan[3])
    assert out[J["r_hip_y"]] == pytest.approx(KH * 0.1)
    assert out[J["l_hip_y"]] == 0.0
    b.measure = lambda: (5.0, 50.0, 0.0, 0.0)
    assert b.correct(3, plan[3])[J["r_hip_y"]] == pytest.approx(LIMIT_RAD)
    b.measure = lambda: (0.0, 0.0, 0.1, 0.0)  # leaning left: both hips roll
    out = b.correct(3, plan[3])
    assert out[J["l_hip_x"]] == out[J["r_hip_x"]] != 0.0


def test_kept_plan_walks_with_the_feedback(kept_plan):
    """A kept plan walks MIN_PROGRESS_M or more in 10 s unperturbed, in a room from its own
    start pose; the published plan is the gait's, untouched by the feedback."""
    ep = simulate_episode(11, sigma=0.0, render=False, hazard=False, push=False, obstacle=False, plan=kept_plan)
    assert ep.fall_onset_tick is None
    assert ep.distance_m >= MIN_PROGRESS_M, ep.distance_m
    n_plan = ep.n_ticks + PLAN_FUTURE_TICKS + 1
    assert np.allclose(ep.plan_rad[-n_plan:], gait_waypoints(kept_plan.params, n_plan, RATE_HZ))
    # The joints carry the feedback's corrections: the hips leave the plan, the arms do not.
    planned = ep.plan_rad[-n_plan:][:ep.n_ticks]
    hips = [J[n] for n in ("l_hip_y", "r_hip_y")]
    assert np.abs(ep.joints_rad[:, hips] - planned[:, hips]).max() > 0.02


def test_a_push_is_its_own_cause_and_changes_nothing_before_it(kept_plan):
    kw = dict(sigma=0.005, render=False, hazard=False, obstacle=False, plan=kept_plan)
    pushed = simulate_episode(5, push=True, **kw)
    calm = simulate_episode(5, push=False, **kw)
    t = pushed.push.tick
    assert np.array_equal(pushed.joints_rad[:t], calm.joints_rad[:t])
    assert np.array_equal(pushed.plan_rad, calm.plan_rad)  # the plan does not know of it
    assert not np.allclose(pushed.joints_rad[t + 3:t + 30], calm.joints_rad[t + 3:t + 30])
    meta = pushed.metadata()
    assert json.loads(meta["push"])["tick"] == t and json.loads(calm.metadata()["push"]) is None
    # A strong push from behind throws the walking robot over, and is named as the cause.
    hard = simulate_episode(5, push=Push(t, 0.0, 2.0), **kw)
    assert hard.fall_onset_tick is not None and hard.fall_cause == "push"
    assert 0 <= hard.fall_onset_tick - t <= CAUSE_WINDOW_TICKS


def test_an_obstacle_is_in_view_and_in_the_way(kept_plan):
    kw = dict(sigma=0.005, hazard=False, push=False, plan=kept_plan, duration_s=10.0)
    block = simulate_episode(3, obstacle=Obstacle("panel", 0.25, 0.0, (0.8, 0.05, 0.7), 0.0, (0.9, 0.1, 0.1)), **kw)
    free = simulate_episode(3, obstacle=False, **kw)
    assert np.array_equal(block.plan_rad, free.plan_rad)  # the planner does not know of it
    assert "obstacle" in block.contacts
    assert json.loads(block.metadata()["obstacle"])["kind"] == "panel"
    # The camera sees it from the first frame, long before the robot touches it.
    assert block.jpeg_frames[0] != free.jpeg_frames[0]
    assert block.contacts["obstacle"] > RATE_HZ


def test_the_daemons_view_of_joints_and_camera():
    """Joints read at the buses' 50 Hz cycle (each at its own bus's read, a missed reply held),
    camera frames dropped or frozen: drawn from a stream of their own, so the physics is the
    episode's either way."""
    from sim.sensors import CYCLE_NS, draw_camera, draw_reads

    seen = simulate_episode(9, sigma=0.005, duration_s=3.0, hazard=False, push=False, obstacle=False)
    plain = simulate_episode(9, sigma=0.005, duration_s=3.0, hazard=False, push=False, obstacle=False,
                             daemon_view=False)
    assert np.array_equal(seen.joints_rad, plain.joints_rad) and plain.joint_messages is None
    reads = draw_reads(9, seen.n_ticks, RATE_HZ)
    assert len(seen.joint_messages) == reads.read_ns.shape[0] == (seen.n_ticks - 1) * 50 // RATE_HZ + 1
    # Each value is the angle at its own read (the last 240 Hz step at or before it): a read
    # that falls in a tick's first step holds exactly that tick's angle.
    exact = 0
    for c, (stamp, positions) in enumerate(seen.joint_messages[1:-1], start=1):
        assert c * CYCLE_NS <= stamp < (c + 1) * CYCLE_NS
        for j in np.flatnonzero(reads.read_ns[c] >= 0):
            step = int(reads.read_ns[c, j]) * 240 // 10**9
            if step % 8 == 0:
                assert positions[j] == seen.joints_rad[step // 8, j]
                exact += 1
        for j in np.flatnonzero(reads.read_ns[c] < 0):  # missed: the last read's value held
            assert positions[j] == seen.joint_messages[c - 1][1][j]
    assert exact > 100
    assert 0 < seen.sensors["missed"] < 0.05 * reads.read_ns.size
    sent = draw_camera(1, 3000)
    assert 0 < sum(s < 0 for s in sent) < 100 and sum(0 <= s != k for k, s in enumerate(sent)) > 0
    assert seen.metadata()["sensors"] and json.loads(seen.metadata()["sensors"])["joint_read_hz"] == 50


def test_a_table_is_a_top_on_four_legs_ahead_of_the_robot():
    import pybullet as pb

    from sim.episode import TABLE_BOARD_M, World

    world = World()
    try:
        world.add_floor()
        table = Obstacle("table", 0.2, 0.0, (0.8, 0.5, 0.5), 0.0, (0.5, 0.5, 0.5))
        body = table.add(world.client, (0.0, 0.0), (0.0, -1.0))
        shapes = pb.getCollisionShapeData(body, -1, physicsClientId=world.client)
        lo, hi = pb.getAABB(body, -1, physicsClientId=world.client)
    finally:
        world.close()
    assert len(shapes) == 5  # the top and four legs
    assert abs(hi[2] - 0.5) < 1e-3 and abs(lo[2]) < 1e-3
    # Its nearest edge 0.2 m ahead (facing -y), centred on the path; the camera's points on its top.
    assert abs(hi[1] + 0.2) < 1e-3 and abs(lo[1] + 0.7) < 1e-3 and abs(lo[0] + hi[0]) < 1e-6
    assert np.all(table.surface[:, 2] >= 0.5 - TABLE_BOARD_M - 1e-9)
