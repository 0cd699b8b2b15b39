"""Physics and determinism: the robot stands, kept plans walk, seeds reproduce; the causes of falls."""

from __future__ import annotations

import numpy as np

from sim.episode import (BACKGROUND_SIGMAS, EVENT_GAIN, EVENT_KNOTS, EVENT_START_S, KNOT_TICKS,
                         PERTURBATION_SCALE, PLAN_FUTURE_TICKS, PLAN_PAST_TICKS, RATE_HZ, STEPS_PER_TICK,
                         UNPERTURBED_JOINTS, knot_deviation, knot_sigmas, knot_ticks, perturbation_factor,
                         simulate_episode, stamp_ns)
from sim.gait import gait_waypoints
from sim.robot import JOINT_NAMES

HEAD = [JOINT_NAMES.index(n) for n in UNPERTURBED_JOINTS]


def test_unperturbed_robot_stands_10_s():
    ep = simulate_episode(4242, sigma=0.0, duration_s=10.0, render=False, gait=False)
    assert not ep.fallen.any()
    assert ep.head_height_m.min() > 0.97 * ep.standing_head_height_m
    assert np.abs(ep.joints_rad).max() < 0.05  # holds the zero pose


def test_same_seed_same_arrays():
    a = simulate_episode(77, duration_s=2.0)
    b = simulate_episode(77, duration_s=2.0)
    assert a.sigma == b.sigma and a.params == b.params and a.hazard == b.hazard
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


def test_knot_deviation_is_sparse_smooth_and_spares_the_head():
    n_plan = 200
    ticks = knot_ticks(n_plan)
    eta = np.random.default_rng(0).normal(0, 0.04, (len(ticks), len(JOINT_NAMES)))
    dev = knot_deviation(eta, 0.04, n_plan)
    factor = perturbation_factor(0.04, ticks * STEPS_PER_TICK)
    for j, t in enumerate(ticks[ticks < n_plan]):
        want = PERTURBATION_SCALE * factor[j] * eta[j]
        want[HEAD] = 0.0
        assert np.allclose(dev[t], want), t
        # Between two knots the plan moves monotonically from one knot's value to the next.
        seg = dev[t:min(t + KNOT_TICKS, n_plan)]
        assert np.all(np.diff(seg, axis=0) * np.sign(eta[j + 1] * factor[j + 1] - eta[j] * factor[j])[None] >= -1e-12)
    assert np.all(dev[:, HEAD] == 0.0)
    # Before the ramp (sigma > 0.01), there is nothing; after it, the full amplitude.
    assert np.abs(dev[:2 * RATE_HZ]).max() < 1e-3
    assert np.abs(dev[5 * RATE_HZ:]).std() > 0.5 * PERTURBATION_SCALE * 0.04


def test_an_event_episode_walks_like_a_walking_one_until_its_event(kept_plan):
    """Sigma above BACKGROUND_SIGMA_MAX adds an event of EVENT_KNOTS knots; every other knot
    has a walking episode's sigma, so the joints and the plan's past cannot tell it apart
    before the event."""
    amp = knot_sigmas(0.04, 0.005, 12, 40)
    assert np.all(amp[12:12 + EVENT_KNOTS] == EVENT_GAIN * 0.04)
    assert np.all(np.delete(amp, range(12, 12 + EVENT_KNOTS)) == 0.005)
    assert np.all(knot_sigmas(0.01, 0.01, None, 40) == 0.01)
    ep = simulate_episode(21, sigma=0.04, duration_s=10.0, render=False, hazard=False, plan=kept_plan)
    assert ep.background_sigma in BACKGROUND_SIGMAS
    assert EVENT_START_S[0] * RATE_HZ - KNOT_TICKS <= ep.event_tick <= EVENT_START_S[1] * RATE_HZ
    n_plan = ep.n_ticks + PLAN_FUTURE_TICKS + 1
    deviation = ep.plan_rad[PLAN_PAST_TICKS:] - gait_waypoints(ep.params, n_plan, RATE_HZ)
    body = [i for i in range(len(JOINT_NAMES)) if i not in HEAD]
    before = deviation[:ep.event_tick + 1, body]
    during = deviation[ep.event_tick + KNOT_TICKS:ep.event_tick + KNOT_TICKS * EVENT_KNOTS, body]
    assert before.std() < 1.5 * PERTURBATION_SCALE * ep.background_sigma
    assert during.std() > 0.5 * PERTURBATION_SCALE * EVENT_GAIN * ep.sigma
    # Slow: most of the event's power lies below 1.5 Hz, half the knot rate (white noise per
    # tick, generator 1, spreads evenly to 15 Hz: ~90% above 1.5 Hz).
    span = deviation[ep.event_tick:ep.event_tick + KNOT_TICKS * (EVENT_KNOTS + 1), body]
    spectrum = np.abs(np.fft.rfft(span - span.mean(0), axis=0)) ** 2
    freqs = np.fft.rfftfreq(span.shape[0], 1 / RATE_HZ)
    assert spectrum[freqs > 1.5].sum() < 0.2 * spectrum.sum()
    meta = ep.metadata()
    assert meta["event_ns"] == str(stamp_ns(ep.event_tick))
    assert float(meta["background_sigma"]) == ep.background_sigma
    walking = simulate_episode(21, sigma=0.01, duration_s=4.0, render=False, hazard=False, plan=kept_plan)
    assert walking.event_tick is None and walking.background_sigma == 0.01
    assert "event_ns" not in walking.metadata()


def test_published_plan_carries_the_event_seconds_before_it_acts(kept_plan):
    ep = simulate_episode(21, sigma=0.04, duration_s=10.0, render=False, hazard=False, plan=kept_plan)
    # The first plan message (one a second, reaching 3 s ahead) that holds the event's first
    # knot was published 2-3 s before that knot, with exactly the waypoints commanded then.
    knot = ep.event_tick + KNOT_TICKS
    published = -(-(knot - PLAN_FUTURE_TICKS) // RATE_HZ) * RATE_HZ
    assert 2 * RATE_HZ <= knot - published <= 3 * RATE_HZ
    first, points = ep.plan_message_points(published)
    assert first == published - PLAN_PAST_TICKS
    assert np.array_equal(points[knot - first], ep.plan_rad[PLAN_PAST_TICKS + knot])
    assert np.array_equal(points[PLAN_PAST_TICKS:],
                          ep.plan_rad[PLAN_PAST_TICKS + published:][:PLAN_FUTURE_TICKS + 1])


def test_counterfactual_redraw_moves_or_averts_perturbation_falls(kept_plan):
    """The cause of a fall lies in the plan's last 1.5 s: with the knots from 1.5 s before the
    onset on redrawn at the episode's background sigma (its event taken out there), at least
    half of the falls among a fixed seed range are averted or move by more than 15 ticks
    (generator 1, white noise per tick, moved none of 32). Redrawn from their own
    distribution instead (the event kept, new values), the event still throws the robot
    over at about the same time: an event of this size topples it whatever its draw. The
    full measurement, on more falls, is `python -m sim stats --counterfactual`
    (sim/README.md has its figures).
    """
    plan = kept_plan  # one plan, as a data set shares it
    shares = {}
    for walking in (True, False):
        changed, falls = 0, 0
        for seed in range(1000, 1008):
            ep = simulate_episode(seed, sigma=0.04, duration_s=10.0, render=False, hazard=False, push=False,
                                  obstacle=False, counterfactual_lead_ticks=45, plan=plan, counterfactual_walking=walking)
            if ep.fall_onset_tick is None:
                continue
            falls += 1
            assert ep.counterfactual_from_tick == ep.fall_onset_tick - 45
            cf = ep.counterfactual_onset_tick
            changed += cf is None or abs(cf - ep.fall_onset_tick) > 15
        assert falls >= 6
        shares[walking] = changed / falls
    assert shares[True] >= 0.5, shares
    assert shares[True] > shares[False], shares


def test_a_ball_rolled_at_the_robot_is_seen_before_it_hits(kept_plan):
    # Seed 4 draws a ball; the same episode without it is identical until the launch.
    kw = dict(sigma=0.005, duration_s=10.0, plan=kept_plan, push=False, obstacle=False)
    with_ball = simulate_episode(4, hazard=True, **kw)
    without = simulate_episode(4, hazard=False, **kw)
    launch, contact = with_ball.hazard.launch_tick, with_ball.first_contact_tick
    assert with_ball.contact_with == "ball" and launch < contact
    assert with_ball.fall_cause == "collision" and without.fall_onset_tick is None
    assert with_ball.jpeg_frames[:launch] == without.jpeg_frames[:launch]
    assert np.array_equal(with_ball.joints_rad[:contact], without.joints_rad[:contact])
    # The camera shows the ball between the launch and the hit: the frames differ there.
    differ = [k for k in range(launch, contact) if with_ball.jpeg_frames[k] != without.jpeg_frames[k]]
    assert len(differ) >= (contact - launch) // 2


def test_validation_draws_resumed_from_the_unperturbed_state_equal_full_runs():
    """search_plan starts each validation draw from the unperturbed run's state at
    VALIDATION_FROM_TICK: exactly the run from tick 0 with the same plan."""
    import math

    import pybullet as pb

    from sim.episode import (VALIDATION_FROM_TICK, VALIDATION_SIGMA, World, _rollout, joint_limits,
                             standing_head_height_m)
    from sim.gait import GaitParams
    from sim.robot import FALL_FRACTION, Robot

    n_ticks = 150
    n_plan = n_ticks + PLAN_FUTURE_TICKS + 1
    threshold = round(FALL_FRACTION * standing_head_height_m(), 4)
    rng = np.random.default_rng(5)
    base = gait_waypoints(GaitParams.propose(rng), n_plan, RATE_HZ)
    world = World()
    try:
        plane = pb.createCollisionShape(pb.GEOM_PLANE, physicsClientId=world.client)
        pb.createMultiBody(0, plane, physicsClientId=world.client)
        robot = Robot(world.client)
        robot.start_xy, robot.start_yaw, robot.start_dir = np.zeros(2), 0.0, np.array([0.0, -1.0])
        lo, hi = joint_limits(robot)
        start = pb.saveState(physicsClientId=world.client)
        first = _rollout(world, robot, base, n_ticks, threshold, False, None, save_at=VALIDATION_FROM_TICK)
        eta = rng.normal(0.0, VALIDATION_SIGMA * 4, (len(knot_ticks(n_plan)), len(JOINT_NAMES)))
        eta[knot_ticks(n_plan) <= VALIDATION_FROM_TICK] = 0.0
        plan = np.clip(base + knot_deviation(eta, VALIDATION_SIGMA * 4, n_plan), lo, hi)
        assert np.array_equal(plan[:VALIDATION_FROM_TICK + 1], base[:VALIDATION_FROM_TICK + 1])
        pb.restoreState(start, physicsClientId=world.client)
        full = _rollout(world, robot, plan, n_ticks, threshold, False, None)
        resumed = _rollout(world, robot, plan, n_ticks, threshold, False, None,
                           resume=(first.saved, VALIDATION_FROM_TICK))
    finally:
        world.close()
    assert np.array_equal(np.array(full.joints[VALIDATION_FROM_TICK:]), np.array(resumed.joints))
    assert full.heights[VALIDATION_FROM_TICK:] == resumed.heights
    assert math.isfinite(resumed.heights[-1])
