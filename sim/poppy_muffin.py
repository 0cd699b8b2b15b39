"""Real Poppy Humanoid walks from poppy-muffin's hardware buffers, as fall-guard recordings.

Data enters as ``scripts/scratchbuf.real.pkl`` of the public repository
garrettkatz/poppy-muffin (MIT licence), written by its ``walkscratch.py`` on
the authors' real robot, and leaves as one MCAP recording in the simulator's
format (``sim.recording``; docs/real-recordings.md has the mapping and
what was checked):

- ``/joint_states``: every buffered ``present_position`` sample at its own
  time, the 25 joints renamed into model order, degrees to radians; the
  signs are kept: pypot's angles and the model's share one convention;
- ``/planned_trajectory``: every 1 s, the commanded path from now - 2.5 s
  to now + 3 s, its points at the knots of the path (each step's goal at
  the step's end) and at the two ends of that span;
- ``/ground_truth/fallen``: ``false`` at every joint sample, as
  ``fall-guard label --no-fall`` writes it; no camera topic;
- metadata ``fall_guard.episode``: ``source = "robot"``, no
  ``fall_onset_ns``, and the source repository, commit, file and its SHA-256.

The buffer, as walkscratch.py writes it: ``(motor_names, runs)``; run 0 is
the move to the initial pose (one step; the operator holds the robot up by
a strap during it, then sets it down and presses Enter, a pause the buffer
does not time); runs 1.. are the walk. Each step is ``(success, buffers,
time_elapsed)``: ``poppy_wrapper.goto_position(goal, duration, bufsize=10)``
sets every motor's goal (``target`` stays the step's goal throughout)
with a moving speed of distance / duration and samples the six registers
10 times at ``linspace(0, duration, 10)``; ``time_elapsed[t]`` is measured
from the goto's start right after sample t. The next step starts right after
the previous one's last sample, so the walk's clock joins the steps there,
as walkscratch.py's own plot does.

Run: ``python -m sim poppy-muffin --buffers scratchbuf.real.pkl --out R.mcap``.
"""

from __future__ import annotations

import hashlib
import json
import os
import pickle
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from mcap_ros2.writer import Writer

from .recording import (METADATA_NAME, SCHEMAS, TOPIC_FALLEN, TOPIC_JOINTS, TOPIC_PLAN, TOPIC_TYPES,
                        header, ros_time)
from .robot import JOINT_NAMES, ROBOT_NAME

SOURCE_REPOSITORY = "https://github.com/garrettkatz/poppy-muffin"
#: The commit the committed fixture was converted from.
SOURCE_COMMIT = "da8122b4484c889469fe7e8ead5a50590fc4a3ee"
SCRATCHBUF_PATH = "scripts/scratchbuf.real.pkl"
SCRATCHBUF_SHA256 = "ffb80e9629b5d8a08c155742bb377597a4349a45b0573e7acf7f2796eeffbf49"
SOURCE_LICENCE = "MIT, Copyright (c) 2019 garrettkatz"
RATE_HZ = 30                  # the model's tick rate (the samples come at their own times)
PLAN_PERIOD_NS = 1_000_000_000
PLAN_PAST_NS = 2_500_000_000
PLAN_FUTURE_NS = 3_000_000_000
REGISTERS = ("position", "target", "load", "speed", "voltage", "temperature")
#: Steps shorter than this are the fast ones of the tracking figures (the real walk's kick: 18-53 ms).
FAST_STEP_S = 0.1
#: Joint groups of the tracking figures (sim/README.md).
GROUPS: dict[str, tuple[str, ...]] = {
    "legs": tuple(n for n in JOINT_NAMES if n[:2] in ("l_", "r_") and ("hip" in n or "knee" in n or "ankle" in n)),
    "trunk": ("abs_y", "abs_x", "abs_z", "bust_y", "bust_x"),
    "head": ("head_z", "head_y"),
    "arms": tuple(n for n in JOINT_NAMES if "shoulder" in n or "arm" in n or "elbow" in n),
}


def model_order(motor_names) -> list[int]:
    """Index into MOTOR_NAMES (pypot's order) of each model joint, in model order."""
    names = [str(n) for n in motor_names]
    missing = [n for n in JOINT_NAMES if n not in names]
    if missing or len(names) != len(JOINT_NAMES):
        raise ValueError(f"the buffer's motors {names} are not the model's 25 joints (missing {missing})")
    return [names.index(n) for n in JOINT_NAMES]


def model_rad(deg: np.ndarray, motor_names) -> np.ndarray:
    """Angles [..., 25] in pypot's order and degrees -> model order, radians.

    No sign or offset changes: pypot's ``present_position``/``goal_position``
    are already its user convention (orientation and offset applied), which
    is the model's convention (docs/real-recordings.md, joint by joint).
    """
    return np.deg2rad(np.asarray(deg, dtype=float)[..., model_order(motor_names)])


@dataclass
class RealWalk:
    """The walk of one buffer, in pypot's motor order and degrees, on one clock (s from the walk's start)."""
    motor_names: tuple[str, ...]
    sample_s: np.ndarray        # [n] time of each sample
    step_of_sample: np.ndarray  # [n] step index of each sample
    registers: dict[str, np.ndarray]  # REGISTERS -> [n, 25]
    step_start_s: np.ndarray    # [S]
    step_end_s: np.ndarray      # [S] = the next step's start (the last sample's time)
    goal_deg: np.ndarray        # [S, 25] each step's goal (its constant target)
    start_deg: np.ndarray       # [25] the pose commanded before the first step (the initial pose)
    runs: list[int]             # steps per walking run

    @property
    def duration_s(self) -> float:
        return float(self.sample_s[-1])

    def knots(self) -> tuple[np.ndarray, np.ndarray]:
        """The commanded path's knots: times (ns) and angles [S + 1, 25] (model order, rad).

        Step s moves the goal from step s - 1's goal (the initial pose for the
        first) at its start to its own goal at its end, at constant speed: what
        pypot's goto commands (moving speed = distance / duration, from where
        the motor is); the path starts from the previous goal, as a plan would,
        not from the measured position.
        """
        t = np.concatenate([[0], np.round(self.step_end_s * 1e9).astype(np.int64)])
        q = model_rad(np.vstack([self.start_deg, self.goal_deg]), self.motor_names)
        return t, q


def _step(step, where: str):
    try:
        success, buffers, elapsed = step
    except (TypeError, ValueError):
        raise ValueError(f"{where}: not a (success, buffers, time_elapsed) step") from None
    missing = [k for k in REGISTERS if k not in buffers]
    if missing:
        raise ValueError(f"{where}: registers {missing} missing from the step's buffers")
    n = len(buffers["position"])
    regs = {k: np.asarray(buffers[k], dtype=float)[:n] for k in REGISTERS}
    elapsed = np.asarray(elapsed, dtype=float)[:n]
    if n == 0 or any(r.shape != (n, 25) for r in regs.values()) or elapsed.shape != (n,):
        raise ValueError(f"{where}: registers must be [samples, 25] with one time per sample")
    if not np.all(np.diff(elapsed) > 0) or elapsed[0] < 0:
        raise ValueError(f"{where}: sample times must start at or after 0 and increase")
    return bool(success), regs, elapsed


def load_scratchbuf(path: Path) -> RealWalk:
    """Read walkscratch.py's buffer (a Python 2 pickle: latin1) into a RealWalk.

    Refuses a buffer with a failed step: a failure is when walkscratch.py
    stops (the operator interrupted the motion, or the bus failed), and
    "no fall" would then not be supported by the buffer.
    """
    with open(path, "rb") as f:
        motor_names, runs = pickle.load(f, encoding="latin1")
    return walk_from_runs(tuple(str(n) for n in motor_names), runs, str(path))


def walk_from_runs(motor_names: tuple[str, ...], runs, where: str = "buffer") -> RealWalk:
    """RUNS as walkscratch.py stores them: run 0 the initial move, then the walk."""
    model_order(motor_names)
    if len(runs) < 2 or len(runs[0]) != 1:
        raise ValueError(f"{where}: expected run 0 = the initial move (one step) and at least one walking run")
    _, init, _ = _step(runs[0][0], f"{where}: run 0")
    start_deg = init["target"][-1]
    samples, steps_of, regs, starts, ends, goals, per_run = [], [], {k: [] for k in REGISTERS}, [], [], [], []
    clock = 0.0
    for r, run in enumerate(runs[1:], start=1):
        per_run.append(len(run))
        for s, step in enumerate(run):
            here = f"{where}: run {r} step {s}"
            success, b, elapsed = _step(step, here)
            if not success:
                raise ValueError(f"{here}: the step failed (walkscratch.py stopped there): "
                                 "the buffer does not support a no-fall label")
            if np.ptp(b["target"], axis=0).max() > 1e-9:
                raise ValueError(f"{here}: the target changes within the step (not one goto per step)")
            starts.append(clock)
            goals.append(b["target"][0])
            samples.append(clock + elapsed)
            steps_of.append(np.full(len(elapsed), len(starts) - 1))
            for k in REGISTERS:
                regs[k].append(b[k])
            clock += float(elapsed[-1])
            ends.append(clock)
    return RealWalk(
        motor_names=motor_names,
        sample_s=np.concatenate(samples),
        step_of_sample=np.concatenate(steps_of),
        registers={k: np.vstack(v) for k, v in regs.items()},
        step_start_s=np.array(starts), step_end_s=np.array(ends),
        goal_deg=np.array(goals), start_deg=np.asarray(start_deg, dtype=float),
        runs=per_run)


def sample_ns(walk: RealWalk) -> np.ndarray:
    ns = np.round(walk.sample_s * 1e9).astype(np.int64)
    if not np.all(np.diff(ns) > 0):
        raise ValueError("sample times do not increase at ns resolution")
    return ns


def plan_points(walk: RealWalk, now_ns: int) -> tuple[np.ndarray, np.ndarray]:
    """The plan published at NOW_NS: times (ns) and angles [P, 25] of its points.

    The points are the path's knots inside [now - 2.5 s, now + 3 s] and the
    path at the span's two ends (it holds the initial pose before the walk
    and the last goal after it); linear between points is the path itself.
    """
    t, q = walk.knots()
    lo, hi = now_ns - PLAN_PAST_NS, now_ns + PLAN_FUTURE_NS
    inside = (t > lo) & (t < hi)
    times = np.concatenate([[lo], t[inside], [hi]])
    at = np.column_stack([np.interp(times, t, q[:, j]) for j in range(q.shape[1])])
    at[1:-1] = q[inside]  # the knots exactly, not re-interpolated
    return times, at


def metadata(walk: RealWalk, source_commit: str, source_file: str, sha256: str) -> dict[str, str]:
    gaps = np.diff(walk.sample_s)
    return {
        "source": "robot",
        "robot": ROBOT_NAME,
        "rate_hz": str(RATE_HZ),
        "duration_s": f"{walk.duration_s:.3f}",
        "origin": "poppy-muffin walkscratch.py buffer, converted by python -m sim poppy-muffin",
        "origin_repository": SOURCE_REPOSITORY,
        "origin_commit": source_commit,
        "origin_file": source_file,
        "origin_sha256": sha256,
        "origin_licence": SOURCE_LICENCE,
        "fall_label": "no fall",
        "fall_label_basis": ("every step of the buffer reports success: walkscratch.py went through the "
                             "whole walk without the operator interrupting it or a bus error; the buffer "
                             "holds no fall and no measure of one"),
        "steps": str(len(walk.step_start_s)),
        "runs": json.dumps(walk.runs),
        "left_out": ("run 0, the move to the initial pose made with the robot held up by a strap, and "
                     "the untimed pause after it; the clock starts at the first walking step"),
        "camera": "none",
        "joint_samples": str(len(walk.sample_s)),
        "joint_gap_max_ms": f"{gaps.max() * 1e3:.1f}",
        "joint_gap_median_ms": f"{np.median(gaps) * 1e3:.1f}",
    }


def write_recording(path: Path, walk: RealWalk, meta: dict[str, str]) -> None:
    """Write WALK to PATH atomically (temp file + rename), messages in log-time order."""
    names = list(JOINT_NAMES)
    times = sample_ns(walk)
    joints = model_rad(walk.registers["position"], walk.motor_names)
    plans_at = np.arange(0, times[-1] + 1, PLAN_PERIOD_NS, dtype=np.int64)
    events = sorted([(int(t), 0, i) for i, t in enumerate(plans_at)]
                    + [(int(t), 1, i) for i, t in enumerate(times)])
    tmp = path.with_name(path.name + ".partial")
    with open(tmp, "wb") as f:
        writer = Writer(f)
        topics = (TOPIC_PLAN, TOPIC_JOINTS, TOPIC_FALLEN)
        schemas = {TOPIC_TYPES[t]: writer.register_msgdef(TOPIC_TYPES[t], SCHEMAS[TOPIC_TYPES[t]])
                   for t in topics}
        seq = {t: 0 for t in topics}

        def put(topic: str, msg: dict, log_ns: int) -> None:
            writer.write_message(topic, schemas[TOPIC_TYPES[topic]], msg,
                                 log_time=log_ns, publish_time=log_ns, sequence=seq[topic])
            seq[topic] += 1

        for now, kind, i in events:
            if kind == 0:
                pt, pq = plan_points(walk, now)
                put(TOPIC_PLAN, {
                    "header": header(int(pt[0]), "base"),
                    "joint_names": names,
                    "points": [{
                        "positions": [float(a) for a in row],
                        "velocities": [], "accelerations": [], "effort": [],
                        "time_from_start": ros_time(int(t) - int(pt[0])),
                    } for t, row in zip(pt, pq)],
                }, now)
            else:
                put(TOPIC_JOINTS, {
                    "header": header(now, "base"),
                    "name": names,
                    "position": [float(a) for a in joints[i]],
                    "velocity": [], "effort": [],
                }, now)
                put(TOPIC_FALLEN, {"data": False}, now)
        writer._writer.add_metadata(METADATA_NAME, meta)
        writer.finish()
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def convert(buffers: Path, out: Path, source_commit: str = SOURCE_COMMIT,
            source_file: str = SCRATCHBUF_PATH) -> dict:
    """Convert walkscratch.py's buffer BUFFERS to the recording OUT; returns a summary."""
    sha256 = hashlib.sha256(Path(buffers).read_bytes()).hexdigest()
    walk = load_scratchbuf(buffers)
    meta = metadata(walk, source_commit, source_file, sha256)
    write_recording(Path(out), walk, meta)
    return {"out": str(out), "sha256_of_buffers": sha256,
            "expected_sha256": SCRATCHBUF_SHA256 if source_file == SCRATCHBUF_PATH else None,
            "steps": len(walk.step_start_s), "joint_samples": len(walk.sample_s),
            "duration_s": round(walk.duration_s, 3), "bytes": Path(out).stat().st_size}


# --- tracking: the real servos against the simulator's on the same commanded path ---


def step_knots(recording: Path) -> dict:
    """One step of the walk's commanded path, from a converted recording's published plan:
    the knots from the walk's start to the first knot where the pose is the start pose's
    mirror image (the trunk back upright, the other leg forward), as ``gait.load_step_knots``
    reads them. The hardware gait of the simulator repeats this step, mirrored every other time."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    from .gait import mirrored

    points: dict[int, np.ndarray] = {}
    with open(recording, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _, _, _, msg in reader.iter_decoded_messages(topics=[TOPIC_PLAN], log_time_order=True):
            if list(msg.joint_names) != list(JOINT_NAMES):
                raise ValueError(f"{recording}: the plan's joints are not the model's, in its order")
            stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
            for p in msg.points:
                t = stamp + p.time_from_start.sec * 1_000_000_000 + p.time_from_start.nanosec
                points[int(round(t / 1e6))] = np.asarray(p.positions, dtype=float)
    ms = np.array(sorted(k for k in points if k >= 0))
    if len(ms) < 3 or ms[0] != 0:
        raise ValueError(f"{recording}: no plan point at the walk's start")
    q = np.array([points[k] for k in ms])
    home = mirrored(q[0])
    ends = [i for i in range(1, len(ms)) if np.abs(q[i] - home).max() < np.deg2rad(0.05)
            and np.abs(q[:i] - q[0]).max() > np.deg2rad(10)]
    if not ends:
        raise ValueError(f"{recording}: the plan never reaches the start pose's mirror image")
    end = ends[0]
    return {"source": f"{SOURCE_REPOSITORY} {SCRATCHBUF_PATH} (commit {SOURCE_COMMIT}), {SOURCE_LICENCE}; "
                      "the commanded path's knots from the walk's start to the start pose's mirror image",
            "joint_names": list(JOINT_NAMES),
            "time_s": [round(float(x) / 1e3, 3) for x in ms[:end + 1]],
            "angles_rad": [[round(float(v), 6) for v in row] for row in q[:end + 1]]}


def tracking_errors(position_rad: np.ndarray, target_rad: np.ndarray) -> dict[str, dict[str, float]]:
    """|position - target| (deg) per joint group: mean and 95th percentile over samples and joints."""
    err = np.rad2deg(np.abs(position_rad - target_rad))
    out = {}
    for group, names in GROUPS.items():
        e = err[:, [JOINT_NAMES.index(n) for n in names]]
        out[group] = {"mean_deg": round(float(e.mean()), 2), "p95_deg": round(float(np.percentile(e, 95)), 2)}
    return out


def simulate_commanded(walk: RealWalk) -> dict:
    """Run WALK's commanded path in the simulator (bare floor, gain as sim.robot): joint angles
    at the walk's sample times (model order, rad) and the lowest head height."""
    import pybullet as pb

    from .episode import SETTLE_STEPS, World, standing_head_height_m
    from .robot import FALL_FRACTION, PHYSICS_HZ, Robot

    t_knots, q_knots = walk.knots()
    times = sample_ns(walk)
    world = World()
    try:
        world.add_floor()
        robot = Robot(world.client)
        robot.place(q_knots[0], (0.0, 0.0), 0.0)
        for _ in range(SETTLE_STEPS):
            robot.command(q_knots[0])
            pb.stepSimulation(physicsClientId=world.client)
        angles = np.empty((len(times), len(JOINT_NAMES)))
        i, step, low = 0, 0, robot.head_height_m()
        while i < len(times):
            # The state at physics step STEP is at STEP / 240 s; a sample takes the first state at or after it.
            while i < len(times) and times[i] <= step * 1e9 / PHYSICS_HZ:
                angles[i] = robot.joint_angles()
                i += 1
            step += 1
            t = step * 1e9 / PHYSICS_HZ
            robot.command(np.array([np.interp(t, t_knots, q_knots[:, j]) for j in range(q_knots.shape[1])]))
            pb.stepSimulation(physicsClientId=world.client)
            low = min(low, robot.head_height_m())
    finally:
        world.close()
    return {"angles": angles, "lowest_head_m": low,
            "fell": low < FALL_FRACTION * standing_head_height_m()}


def tracking_report(walk: RealWalk) -> dict:
    """The real robot's tracking and the simulator's on the same commanded path, per joint group:
    |position - target| over every sample and over each step's last sample (where the goal
    should be reached), and |position - commanded path| (the servo's lag behind the ramp),
    also over the steps shorter than FAST_STEP_S alone (the real walk's kick)."""
    target = model_rad(walk.registers["target"], walk.motor_names)
    real = model_rad(walk.registers["position"], walk.motor_names)
    t_knots, q_knots = walk.knots()
    times = sample_ns(walk)
    path = np.column_stack([np.interp(times, t_knots, q_knots[:, j]) for j in range(q_knots.shape[1])])
    sim = simulate_commanded(walk)
    ends = np.r_[np.diff(walk.step_of_sample) != 0, True]
    fast = (walk.step_end_s - walk.step_start_s)[walk.step_of_sample] < FAST_STEP_S

    def figures(angles: np.ndarray) -> dict:
        out = {"all_samples": tracking_errors(angles, target),
               "step_ends": tracking_errors(angles[ends], target[ends]),
               "from_path": tracking_errors(angles, path)}
        if fast.any():
            out["from_path_fast_steps"] = tracking_errors(angles[fast], path[fast])
        return out

    return {
        "samples": int(len(real)), "steps": int(ends.sum()),
        "fast_steps": int(np.sum(walk.step_end_s - walk.step_start_s < FAST_STEP_S)),
        "real": figures(real),
        "sim": {**figures(sim["angles"]),
                "lowest_head_m": round(sim["lowest_head_m"], 4), "fell": bool(sim["fell"])},
    }


__all__ = ["convert", "step_knots", "load_scratchbuf", "walk_from_runs", "model_rad", "model_order", "plan_points",
           "write_recording", "metadata", "tracking_report", "RealWalk"]
