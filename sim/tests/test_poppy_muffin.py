"""The poppy-muffin converter (sim/poppy_muffin.py, docs/real-recordings.md).

A synthetic buffer in walkscratch.py's structure (pypot's motor order,
degrees, one goto per step) goes through the converter and comes back
through an independent reader (rosbags) equal to the buffer: units, signs,
joint order, times, the plan, the labels. The committed real walk is
checked against the model: its angles inside the joint limits and its poses
physically consistent (feet, head, weight), which a wrong sign would break.
"""

from __future__ import annotations

import hashlib
import os
import pickle
import tomllib
from pathlib import Path

import numpy as np
import pybullet as pb
import pytest

from sim import poppy_muffin as pm
from sim.robot import JOINT_NAMES, Robot
from sim.tests.readback import read_metadata, read_recording

REPO = Path(__file__).resolve().parents[2]
FIXTURE = REPO / "tests" / "fixtures" / "real" / "poppy_muffin_walk.mcap"
#: The motor order of the real buffer (pypot's, from poppy_humanoid.json), not the model's.
PYPOT_ORDER = (
    "abs_y", "abs_x", "abs_z", "bust_y", "bust_x", "head_z", "head_y",
    "l_shoulder_y", "l_shoulder_x", "l_arm_z", "l_elbow_y",
    "r_shoulder_y", "r_shoulder_x", "r_arm_z", "r_elbow_y",
    "l_hip_x", "l_hip_z", "l_hip_y", "l_knee_y", "l_ankle_y",
    "r_hip_x", "r_hip_z", "r_hip_y", "r_knee_y", "r_ankle_y",
)


def ns(t) -> int:
    return t.sec * 1_000_000_000 + t.nanosec


def goto_step(rng, start_deg, goal_deg, duration, success=True):
    """One step as poppy_wrapper.goto_position returns it: 10 samples of the six registers."""
    elapsed = np.linspace(0, duration, 10) + 0.002 + rng.uniform(0, 0.001, 10)
    w = np.linspace(0, 1, 10)[:, None]
    position = (1 - w) * start_deg + w * goal_deg + rng.normal(0, 0.3, (10, 25))
    buffers = {"position": position, "target": np.tile(goal_deg, (10, 1)),
               "load": rng.normal(0, 10, (10, 25)), "speed": rng.normal(0, 5, (10, 25)),
               "voltage": np.full((10, 25), 12.0), "temperature": np.full((10, 25), 40.0)}
    return (success, buffers, elapsed)


def synthetic_runs(seed=0):
    """(motor_names, runs): run 0 the initial move, then two walking runs of 3 and 2 steps."""
    rng = np.random.default_rng(seed)
    init = rng.uniform(-20, 20, 25)
    runs = [[goto_step(rng, np.zeros(25), init, 1.0)]]
    prev = init
    for n_steps in (3, 2):
        run = []
        for _ in range(n_steps):
            goal = prev + rng.uniform(-15, 15, 25)
            run.append(goto_step(rng, prev, goal, float(rng.uniform(0.3, 2.2))))
            prev = goal
        runs.append(run)
    return PYPOT_ORDER, runs


def write_buffer(path: Path, names, runs) -> Path:
    with open(path, "wb") as f:
        pickle.dump((names, runs), f, protocol=2)  # as Python 2.7 on the robot wrote it
    return path


@pytest.fixture(scope="module")
def converted(tmp_path_factory):
    d = tmp_path_factory.mktemp("poppy_muffin")
    names, runs = synthetic_runs()
    buf = write_buffer(d / "scratchbuf.pkl", names, runs)
    out = d / "walk.mcap"
    summary = pm.convert(buf, out, source_commit="0" * 40)
    return names, runs, buf, out, summary


def walk_samples(names, runs):
    """The walk's samples as the buffer holds them: (times s, positions deg [n, 25] in pypot order)."""
    times, positions, clock = [], [], 0.0
    for run in runs[1:]:
        for _, b, elapsed in run:
            times.append(clock + elapsed)
            positions.append(b["position"])
            clock += elapsed[-1]
    return np.concatenate(times), np.vstack(positions)


def test_round_trip_joint_states_equal_the_buffer(converted):
    names, runs, _, out, summary = converted
    _, topics = read_recording(out)
    assert set(topics) == {"/joint_states", "/planned_trajectory", "/ground_truth/fallen"}, "no camera topic"
    times, deg = walk_samples(names, runs)
    joints = topics["/joint_states"]
    assert len(joints) == len(times) == 50 == summary["joint_samples"], "the initial move is left out"
    for i, (log, msgtype, msg) in enumerate(joints):
        assert msgtype == "sensor_msgs/msg/JointState"
        # Times: each sample at its own time, the steps joined at the previous step's last sample.
        assert log == ns(msg.header.stamp) == round(times[i] * 1e9)
        # Joint order: the model's, whatever the buffer's; units: radians; signs kept.
        assert list(msg.name) == list(JOINT_NAMES)
        for j, name in enumerate(JOINT_NAMES):
            assert msg.position[j] == np.deg2rad(deg[i, PYPOT_ORDER.index(name)])
        assert len(msg.velocity) == 0 and len(msg.effort) == 0
    fallen = topics["/ground_truth/fallen"]
    assert [log for log, _, _ in fallen] == [log for log, _, _ in joints]
    assert not any(m.data for _, _, m in fallen), "no fall: every step succeeded"


def test_units_signs_and_order_joint_by_joint():
    # One value per motor, each a different magnitude, half of them negative.
    deg = np.array([(-1) ** k * (k + 1) * 1.5 for k in range(25)])
    rad = pm.model_rad(deg, PYPOT_ORDER)
    for j, name in enumerate(JOINT_NAMES):
        k = PYPOT_ORDER.index(name)
        assert rad[j] == pytest.approx(deg[k] * np.pi / 180, abs=1e-15), name
    # e.g. the knees: pypot reports both flexed positive, as the model wants them.
    assert np.rad2deg(pm.model_rad(np.where(np.char.find(PYPOT_ORDER, "knee") >= 0, 40.0, 0.0),
                                   PYPOT_ORDER))[[JOINT_NAMES.index("l_knee_y"),
                                                  JOINT_NAMES.index("r_knee_y")]].tolist() == [40.0, 40.0]
    with pytest.raises(ValueError, match="not the model's 25 joints"):
        pm.model_rad(deg[:24], PYPOT_ORDER[:24])


def plan_at(msg, t_ns: float) -> np.ndarray:
    """The plan message's positions at T_NS, linear between points, held outside (as window.rs)."""
    t0 = ns(msg.header.stamp)
    times = np.array([t0 + ns(p.time_from_start) for p in msg.points], dtype=float)
    q = np.array([p.positions for p in msg.points])
    return np.array([np.interp(t_ns, times, q[:, j]) for j in range(q.shape[1])])


def test_plan_carries_the_commanded_future(converted):
    names, runs, _, out, _ = converted
    _, topics = read_recording(out)
    plans = topics["/planned_trajectory"]
    times, _ = walk_samples(names, runs)
    end_ns = round(times[-1] * 1e9)
    assert [log for log, _, _ in plans] == list(range(0, end_ns + 1, 1_000_000_000)), "every 1 s"
    goals, starts, ends, clock = [], [], [], 0.0
    for run in runs[1:]:
        for _, b, elapsed in run:
            starts.append(clock)
            clock += elapsed[-1]
            ends.append(clock)
            goals.append(np.deg2rad(b["target"][0][[PYPOT_ORDER.index(n) for n in JOINT_NAMES]]))
    init = np.deg2rad(runs[0][0][1]["target"][-1][[PYPOT_ORDER.index(n) for n in JOINT_NAMES]])
    for now, _, msg in plans:
        assert list(msg.joint_names) == list(JOINT_NAMES)
        t0 = ns(msg.header.stamp)
        rel = [ns(p.time_from_start) for p in msg.points]
        assert t0 == now - 2_500_000_000 and rel[0] == 0 and t0 + rel[-1] == now + 3_000_000_000
        assert all(b > a for a, b in zip(rel, rel[1:]))
        # Each step's goal is reached at the step's end, from the previous goal at its start.
        for s, (a, b) in enumerate(zip(starts, ends)):
            for t, want in ((b, goals[s]), (a, goals[s - 1] if s else init)):
                if t0 <= t * 1e9 <= t0 + rel[-1]:
                    np.testing.assert_allclose(plan_at(msg, round(t * 1e9)), want, atol=1e-12)
        # Before the walk the plan holds the initial pose; after it, the last goal.
        if t0 < 0:
            np.testing.assert_array_equal(msg.points[0].positions, init)
        if t0 + rel[-1] > end_ns:
            np.testing.assert_array_equal(msg.points[-1].positions, goals[-1])


def test_metadata_says_real_robot_no_fall_and_where_from(converted):
    _, _, buf, out, summary = converted
    meta = read_metadata(out)
    assert meta["source"] == "robot" and meta["robot"] == "poppy_humanoid" and meta["rate_hz"] == "30"
    assert "fall_onset_ns" not in meta and meta["fall_label"] == "no fall"
    assert meta["origin_repository"] == "https://github.com/garrettkatz/poppy-muffin"
    assert meta["origin_commit"] == "0" * 40 and meta["origin_file"] == "scripts/scratchbuf.real.pkl"
    assert meta["origin_sha256"] == hashlib.sha256(buf.read_bytes()).hexdigest() == summary["sha256_of_buffers"]
    assert meta["camera"] == "none" and meta["steps"] == "5" and meta["runs"] == "[3, 2]"


def test_conversion_is_deterministic(converted, tmp_path):
    _, _, buf, out, _ = converted
    again = tmp_path / "again.mcap"
    pm.convert(buf, again, source_commit="0" * 40)
    assert again.read_bytes() == out.read_bytes()


def test_a_failed_step_or_a_moving_target_is_refused(tmp_path):
    names, runs = synthetic_runs(1)
    ok, b, e = runs[2][1]
    runs[2][1] = (False, b, e)
    with pytest.raises(ValueError, match="run 2 step 1: the step failed"):
        pm.load_scratchbuf(write_buffer(tmp_path / "failed.pkl", names, runs))
    names, runs = synthetic_runs(2)
    runs[1][0][1]["target"][5] += 1.0
    with pytest.raises(ValueError, match="run 1 step 0: the target changes"):
        pm.load_scratchbuf(write_buffer(tmp_path / "moving.pkl", names, runs))
    assert not list(tmp_path.glob("*.mcap*"))


# --- the committed real walk ---


def fixture_walk():
    """(joint positions [n, 25] rad, joint times ns, the commanded poses: initial + step goals)."""
    _, topics = read_recording(FIXTURE)
    q = np.array([m.position for _, _, m in topics["/joint_states"]])
    t = np.array([log for log, _, _ in topics["/joint_states"]])
    poses = {}
    for _, _, msg in topics["/planned_trajectory"]:
        t0 = ns(msg.header.stamp)
        for p in msg.points[1:-1]:  # the knots (the two ends are the span's, interpolated)
            poses[t0 + ns(p.time_from_start)] = np.array(p.positions)
    return q, t, np.array([poses[k] for k in sorted(poses)])


def test_the_committed_real_walk_is_the_buffer_it_names():
    meta = read_metadata(FIXTURE)
    assert meta["origin_commit"] == pm.SOURCE_COMMIT and meta["origin_sha256"] == pm.SCRATCHBUF_SHA256
    assert meta["source"] == "robot" and "fall_onset_ns" not in meta
    q, t, knots = fixture_walk()
    assert q.shape == (600, 25) and len(knots) == 61, "60 walking steps of 10 samples, 61 knots"
    assert np.all(np.diff(t) > 0) and t[-1] == pytest.approx(35.605e9, abs=1e6)
    # The replay config's staleness bound covers the largest gap between samples.
    config = tomllib.loads((FIXTURE.parent / "replay.toml").read_text())
    assert np.diff(t).max() / 1e6 < config["streams"]["joints_stale_ms"]
    assert config["streams"]["camera"] == "none"


@pytest.mark.skipif(not os.environ.get("POPPY_MUFFIN_SCRATCHBUF"),
                    reason="needs poppy-muffin's scripts/scratchbuf.real.pkl (POPPY_MUFFIN_SCRATCHBUF)")
def test_the_fetched_buffer_converts_to_the_committed_fixture(tmp_path):
    out = tmp_path / "walk.mcap"
    pm.convert(Path(os.environ["POPPY_MUFFIN_SCRATCHBUF"]), out)
    assert out.read_bytes() == FIXTURE.read_bytes()


@pytest.fixture(scope="module")
def model():
    client = pb.connect(pb.DIRECT)
    robot = Robot(client)
    yield client, robot
    pb.disconnect(client)


def link_rotation(client, robot, q, link):
    """Rotation of LINK relative to the pelvis at joint angles Q (rad, model order)."""
    for j, a in zip(robot.joint_indices, q):
        pb.resetJointState(robot.body, j, float(a), 0.0, physicsClientId=client)
    base = pb.getBasePositionAndOrientation(robot.body, physicsClientId=client)[1]
    st = pb.getLinkState(robot.body, link, computeForwardKinematics=True, physicsClientId=client)
    b = np.array(pb.getMatrixFromQuaternion(base)).reshape(3, 3)
    return b.T @ np.array(pb.getMatrixFromQuaternion(st[5])).reshape(3, 3), np.array(st[4])


def angle_deg(r) -> float:
    return float(np.rad2deg(np.arccos(np.clip((np.trace(r) - 1) / 2, -1, 1))))


def test_real_angles_lie_inside_the_models_joint_limits(model):
    # pypot's sign convention is the model's: with a flipped sign the knees
    # (-3.5..134 deg) and r_shoulder_x (-191..16 deg) would leave their limits.
    from sim.episode import joint_limits
    client, robot = model
    lo, hi = joint_limits(robot)
    q, _, knots = fixture_walk()
    for angles in (q, knots):
        for j, name in enumerate(JOINT_NAMES):
            assert lo[j] - 1e-2 <= angles[:, j].min() and angles[:, j].max() <= hi[j] + 1e-2, name


def test_real_poses_are_physically_consistent_in_the_model(model):
    client, robot = model
    _, _, knots = fixture_walk()
    feet = robot.foot_links
    zero = [link_rotation(client, robot, np.zeros(25), f)[0] for f in feet]

    def between_feet(q) -> float:
        r = [link_rotation(client, robot, q, f)[0] @ z.T for f, z in zip(feet, zero)]
        return angle_deg(r[0].T @ r[1])

    # The initial pose (the robot stood on both feet in it): soles parallel.
    # A flipped hip_y or ankle_y (3.6 deg there) would tilt one foot by 7.2 deg.
    init = knots[0]
    assert between_feet(init) < 0.1
    for name in ("l_hip_y", "l_ankle_y", "r_hip_y", "r_ankle_y"):
        flipped = init.copy()
        flipped[JOINT_NAMES.index(name)] *= -1
        assert between_feet(flipped) > 7.0, name
    # The sway (abs_x +-36 deg, bust_x -+36 deg) keeps the head level: no more
    # tilt than the forward lean (abs_y, up to 11.3 deg); a flipped bust_x tilts it 72 deg.
    head0 = link_rotation(client, robot, np.zeros(25), robot.head_link)[0]
    tilt = [angle_deg(head0.T @ link_rotation(client, robot, g, robot.head_link)[0]) for g in knots]
    assert max(tilt) < 11.5
    # With the left knee lifted highest, the left foot is above the right one.
    g = knots[np.argmax(knots[:, JOINT_NAMES.index("l_knee_y")])]
    left, right = (link_rotation(client, robot, g, f)[1] for f in feet)
    assert left[2] > right[2] + 0.01


def test_command_line_converts_and_needs_an_output(converted, tmp_path, capsys):
    from sim.__main__ import main
    _, _, buf, out, _ = converted
    assert main(["poppy-muffin", "--buffers", str(buf)]) == 2
    assert "give --out, --tracking or both" in capsys.readouterr().err
    again = tmp_path / "cli.mcap"
    assert main(["poppy-muffin", "--buffers", str(buf), "--out", str(again), "--commit", "0" * 40]) == 0
    assert again.read_bytes() == out.read_bytes()


def test_tracking_compares_the_real_servos_with_the_simulators_on_one_path():
    # Standing still, commanded: the real positions are the goal plus a known offset.
    rng = np.random.default_rng(3)
    zero = np.zeros(25)
    runs = [[goto_step(rng, zero, zero, 1.0)], [goto_step(rng, zero, zero, 0.5) for _ in range(2)],
            [goto_step(rng, zero, zero, 0.05)]]
    for run in runs[1:]:
        for _, b, _ in run:
            b["position"][:] = 0.5  # degrees off, every joint
    walk = pm.walk_from_runs(PYPOT_ORDER, runs)
    report = pm.tracking_report(walk)
    assert (report["samples"], report["steps"], report["fast_steps"]) == (30, 3, 1)
    for group in pm.GROUPS:
        for measure in ("all_samples", "step_ends", "from_path", "from_path_fast_steps"):
            assert report["real"][measure][group] == {"mean_deg": 0.5, "p95_deg": 0.5}
    assert not report["sim"]["fell"]
    assert report["sim"]["step_ends"]["legs"]["p95_deg"] < 1.0, "the simulator stands in the zero pose"
    assert sorted(sum(pm.GROUPS.values(), ())) == sorted(JOINT_NAMES)
