"""The hardware gait: the real Poppy walk's step, randomised."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from sim.dataset import DatasetError, check_args, generate
from sim.episode import KeptPlan, search_plan, simulate_episode
from sim.gait import (HARDWARE_RANGES, J, GaitParams, HardwareGaitParams, hardware_waypoints, load_step_knots,
                      mirrored, params_from_dict)
from sim.poppy_muffin import step_knots

REAL = Path(__file__).resolve().parents[2] / "tests" / "fixtures" / "real" / "poppy_muffin_walk.mcap"
UNSCALED = HardwareGaitParams(time_scale=1.0, trunk_scale=1.0, arm_scale=1.0, leg_scale=1.0, lean_scale=1.0,
                              mirrored=0.0)


def test_the_committed_step_is_the_real_walks_plan():
    t, q = load_step_knots()
    fresh = step_knots(REAL)
    assert fresh["time_s"] == [round(x, 3) for x in t.tolist()]
    assert np.allclose(fresh["angles_rad"], q, atol=1e-6)
    # One step: from the initial pose to its mirror image, 25.59 s, the trunk at +-36 deg on the way.
    assert t[0] == 0.0 and t[-1] == pytest.approx(25.59)
    assert np.allclose(q[-1], mirrored(q[0]), atol=np.deg2rad(0.05))
    assert np.rad2deg(q[:, J["abs_x"]]).max() == pytest.approx(36.0, abs=0.1)
    assert np.rad2deg(q[:, J["l_knee_y"]]).max() == pytest.approx(46.3, abs=0.1)


def test_mirror_swaps_sides_and_flips_roll_and_yaw():
    q = np.arange(25, dtype=float)
    m = mirrored(q)
    assert np.array_equal(mirrored(m), q)
    assert m[J["l_hip_y"]] == q[J["r_hip_y"]] and m[J["r_knee_y"]] == q[J["l_knee_y"]]
    assert m[J["l_shoulder_x"]] == -q[J["r_shoulder_x"]] and m[J["abs_x"]] == -q[J["abs_x"]]
    assert m[J["abs_y"]] == q[J["abs_y"]] and m[J["head_y"]] == q[J["head_y"]]


def test_unscaled_gait_is_the_real_path_then_its_mirror():
    t, q = load_step_knots()
    rate = 30.0
    w = hardware_waypoints(UNSCALED, int(2 * t[-1] * rate), rate)
    ticks = np.arange(len(w)) / rate
    first = ticks < t[-1]
    path = np.column_stack([np.interp(ticks[first], t, q[:, j]) for j in range(25)])
    assert np.allclose(w[first], path, atol=1e-9)
    second = ~first
    back = np.column_stack([np.interp(ticks[second] - t[-1], t, q[:, j]) for j in range(25)])
    assert np.allclose(w[second], mirrored(back), atol=1e-9)
    # Mirrored first: the other leg's step.
    flipped = hardware_waypoints(HardwareGaitParams(**{**UNSCALED.__dict__, "mirrored": 1.0}), len(w), rate)
    assert np.allclose(flipped[first], mirrored(path), atol=1e-9)


def test_scales_act_around_the_start_pose():
    t, q = load_step_knots()
    p = HardwareGaitParams(time_scale=0.5, trunk_scale=1.1, arm_scale=0.5, leg_scale=0.9, lean_scale=1.0,
                           mirrored=0.0, head_y_rad=0.1)
    w = hardware_waypoints(p, int(t[-1] * 0.5 * 30), 30.0)
    assert np.rad2deg(w[:, J["abs_x"]]).max() == pytest.approx(36.0 * 1.1, abs=0.2)
    assert np.rad2deg(w[:, J["l_shoulder_x"]]).max() == pytest.approx(18.0, abs=0.2)
    assert w[0, J["l_hip_y"]] == pytest.approx(q[0, J["l_hip_y"]])
    assert w[0, J["head_y"]] == pytest.approx(0.1)


def test_plans_of_either_family_read_back():
    rng = np.random.default_rng(4)
    hw = HardwareGaitParams.propose(rng)
    for name, (lo, hi) in HARDWARE_RANGES.items():
        assert lo <= getattr(hw, name) <= hi
    assert hw.mirrored in (0.0, 1.0)
    assert KeptPlan.from_dict(json.loads(json.dumps(KeptPlan(hw, 1, 0.01, "9:0").as_dict()))).params == hw
    dyn = GaitParams.propose(rng)
    assert "family" not in dyn.as_dict()  # a dynamic plan's file is as it was
    assert params_from_dict(dyn.as_dict()) == dyn
    with pytest.raises(ValueError, match="unknown gait family"):
        params_from_dict({"family": "crawl"})


def test_a_hardware_plan_stands_its_step(tmp_path):
    plan = search_plan(np.random.default_rng([77, 31, 1]), 4.0, "77:1", family="hardware")
    assert isinstance(plan.params, HardwareGaitParams)
    ep = simulate_episode(5, sigma=0.0, duration_s=4.0, render=False, plan=plan, hazard=False, push=False,
                          obstacle=False, daemon_view=False)
    assert ep.fall_onset_tick is None
    # The trunk swings as the plan asks (the servo lags the slow ramp by little).
    planned = hardware_waypoints(plan.params, ep.n_ticks, 30.0)[:, J["abs_x"]]
    assert np.abs(ep.joints_rad[:, J["abs_x"]] - planned).max() < np.deg2rad(3)


def test_gait_argument_is_checked(tmp_path):
    with pytest.raises(DatasetError, match="--gait must be one of dynamic, hardware"):
        check_args(tmp_path / "x", 2, 1, 1, 4.0, gait="crawl")
    generate(tmp_path / "hw", episodes=1, seed=4, jobs=1, duration_s=2.0, progress=False, gait="hardware")
    with pytest.raises(DatasetError, match="gait=hardware, asked gait=dynamic"):
        generate(tmp_path / "hw", episodes=1, seed=4, jobs=1, duration_s=2.0, progress=False)

