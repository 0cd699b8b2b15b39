"""Physics and determinism: the robot stands, kept plans walk, seeds reproduce."""

from __future__ import annotations

import numpy as np

from sim.episode import perturbation_factor, simulate_episode


def test_unperturbed_robot_stands_10_s():
    ep = simulate_episode(4242, sigma=0.0, duration_s=10.0, render=False, gait=False)
    assert not ep.fallen.any()
    assert ep.head_height_m.min() > 0.97 * ep.standing_head_height_m
    assert np.abs(ep.joints_rad).max() < 0.05  # holds the zero pose


def test_unperturbed_kept_plan_walks_without_falling():
    for seed in (11, 12):
        ep = simulate_episode(seed, sigma=0.0, duration_s=10.0, render=False)
        assert ep.fall_onset_tick is None, f"seed {seed} fell"
        assert ep.progress_m >= 0.04, f"seed {seed} walked only {ep.progress_m:.3f} m"


def test_same_seed_same_arrays():
    a = simulate_episode(77, duration_s=2.0)
    b = simulate_episode(77, duration_s=2.0)
    assert a.sigma == b.sigma and a.params == b.params
    assert np.array_equal(a.joints_rad, b.joints_rad)
    assert np.array_equal(a.plan_rad, b.plan_rad)
    assert np.array_equal(a.head_height_m, b.head_height_m)
    assert a.jpeg_frames == b.jpeg_frames
    c = simulate_episode(78, duration_s=2.0)
    assert not np.array_equal(a.plan_rad, c.plan_rad)


def test_perturbation_ramp_counts_physics_steps():
    rho = np.array([0, 480, 720, 960, 2400])  # 0 s, 2 s, 3 s, 4 s, 10 s at 240 Hz
    f = perturbation_factor(0.04, rho)
    assert f[0] < 1e-30 and abs(f[2] - 0.75) < 1e-12 and f[3] > 1.4 and abs(f[4] - 1.5) < 1e-12
    assert np.all(perturbation_factor(0.01, rho) == 1.0)
