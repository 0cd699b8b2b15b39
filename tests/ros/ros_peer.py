#!/usr/bin/env python3
"""A real rclpy peer for fall-guard's ROS 2 interop tests.

Two modes, both speaking JSON lines on stdout so that the Rust tests can read
them without parsing ROS text output:

  listen   subscribe to topics and print every message received:
             {"event": "ready"}                       once subscriptions exist
             {"event": "msg", "topic": T, "t": S, "msg": {...}}  per message
             {"event": "done", "counts": {T: N}}      when all --count are met
           exits 0 when done, 3 on --timeout.

  publish  publish a scenario of sensor inputs (see PUBLISH_SCENARIO below):
             {"event": "published", "topic": T, "n": N}  after each publish
           then keeps publishing the streaming topics until killed or --timeout.

  walk     act as a robot's driver and planner for --joints (comma list):
           JointStates at 30 Hz stamped with the current time, and every
           second a new JointTrajectory (transient local) that starts now and
           runs 4 s ahead, the joints swaying slowly; prints
             {"event": "published", "topic": T, "n": N}  now and then.

Each subscription is given as TOPIC:TYPE:QOS, with TYPE like
std_msgs/msg/Bool and QOS one of the profile names of fall-guard's
docs/ros.md: sensor_data, forecast, latched, diagnostics.

Keep DDS on the loopback interface: the tests set
ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST and a ROS_DOMAIN_ID per test.
"""

import argparse
import importlib
import json
import math
import sys
import time

import rclpy
from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
)

QOS = {
    "sensor_data": QoSProfile(
        reliability=ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.VOLATILE,
        history=HistoryPolicy.KEEP_LAST,
        depth=5,
    ),
    "forecast": QoSProfile(
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.VOLATILE,
        history=HistoryPolicy.KEEP_LAST,
        depth=1,
    ),
    # A subscriber that logs every forecast: compatible with the forecast
    # publisher (reliable, volatile) but buffering on its side, so a test
    # process that is descheduled for a moment loses nothing.
    "forecast_log": QoSProfile(
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.VOLATILE,
        history=HistoryPolicy.KEEP_LAST,
        depth=300,
    ),
    "latched": QoSProfile(
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL,
        history=HistoryPolicy.KEEP_LAST,
        depth=1,
    ),
    "diagnostics": QoSProfile(
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.VOLATILE,
        history=HistoryPolicy.KEEP_LAST,
        depth=10,
    ),
}


def emit(obj):
    sys.stdout.write(json.dumps(obj) + "\n")
    sys.stdout.flush()


def message_class(type_name):
    parts = type_name.split("/")
    if len(parts) == 3 and parts[1] == "msg":
        pkg, ty = parts[0], parts[2]
    elif len(parts) == 2:
        pkg, ty = parts
    else:
        raise SystemExit(f"bad message type {type_name!r}: expected pkg/msg/Type")
    return getattr(importlib.import_module(f"{pkg}.msg"), ty)


def to_plain(value):
    """A ROS message (or field) as JSON-able Python values."""
    if hasattr(value, "get_fields_and_field_types"):
        return {f: to_plain(getattr(value, f)) for f in value.get_fields_and_field_types()}
    if isinstance(value, (bytes, bytearray)):
        return list(value)
    if isinstance(value, (list, tuple)):
        return [to_plain(v) for v in value]
    if hasattr(value, "tolist"):  # numpy / array.array
        return [to_plain(v) for v in value.tolist()]
    if isinstance(value, float) and math.isnan(value):
        return "NaN"  # JSON has no NaN
    return value


def listen(args):
    node = rclpy.create_node("fall_guard_test_listener")
    want = {}
    counts = {}
    finite = {}
    subs = []
    for spec in args.sub:
        try:
            topic, type_name, qos = spec.split(":")
        except ValueError:
            raise SystemExit(f"bad --sub {spec!r}: expected TOPIC:TYPE:QOS")
        cls = message_class(type_name)
        counts[topic] = 0
        finite[topic] = 0

        def callback(msg, topic=topic):
            counts[topic] += 1
            data = getattr(msg, "data", None)
            if data is not None and not isinstance(data, (bool, str)):
                try:
                    if all(math.isfinite(v) for v in data):
                        finite[topic] += 1
                except TypeError:
                    pass
            emit({"event": "msg", "topic": topic, "t": time.monotonic(), "wall": time.time(), "msg": to_plain(msg)})

        subs.append(node.create_subscription(cls, topic, callback, QOS[qos]))
    for spec in args.count:
        topic, n = spec.rsplit("=", 1)
        want[topic] = int(n)
    want_finite = {}
    for spec in args.count_finite:
        topic, n = spec.rsplit("=", 1)
        want_finite[topic] = int(n)
    emit({"event": "ready", "t": time.monotonic()})
    deadline = time.monotonic() + args.timeout
    while time.monotonic() < deadline:
        rclpy.spin_once(node, timeout_sec=0.05)
        if (want or want_finite) and all(counts.get(t, 0) >= n for t, n in want.items()) and all(
            finite.get(t, 0) >= n for t, n in want_finite.items()
        ):
            emit({"event": "done", "counts": counts, "finite": finite})
            return 0
    emit({"event": "timeout", "counts": counts, "finite": finite})
    return 3


def stamp(msg_time, stamp_ns):
    msg_time.sec = stamp_ns // 1_000_000_000
    msg_time.nanosec = stamp_ns % 1_000_000_000


# The scenario the input test checks value by value (tests/ros_inputs.rs
# holds the same numbers).
JOINTS = ["abs_y", "abs_x", "abs_z"]
PLAN_STAMP_NS = 1_700_000_000_250_000_000
PLAN_STEP_NS = 33_333_333
PLAN_POINTS = 4
JPEG_BYTES = bytes([0xFF, 0xD8, 0xFF, 0xE0, 0x00, 0x10, 0x4A, 0x46, 0xFF, 0xD9])


def joint_positions(i):
    return [0.01 * i, -0.5 + 0.001 * i, 1.25]


def publish(args):
    from sensor_msgs.msg import CompressedImage, JointState
    from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

    node = rclpy.create_node("fall_guard_test_publisher")
    joints = node.create_publisher(JointState, args.joint_states, QOS["sensor_data"])
    plans = node.create_publisher(JointTrajectory, args.planned_trajectory, QOS["latched"])
    images = node.create_publisher(CompressedImage, args.camera, QOS["sensor_data"])

    # The plan is published once, before anybody listens: only a
    # transient-local subscription can get it.
    plan = JointTrajectory()
    stamp(plan.header.stamp, PLAN_STAMP_NS)
    plan.header.frame_id = "base_link"
    plan.joint_names = JOINTS
    for p in range(PLAN_POINTS):
        point = JointTrajectoryPoint()
        point.positions = [0.1 * p, 0.2 * p, -0.3 * p]
        point.time_from_start.sec = (p * PLAN_STEP_NS) // 1_000_000_000
        point.time_from_start.nanosec = (p * PLAN_STEP_NS) % 1_000_000_000
        plan.points.append(point)
    plans.publish(plan)
    emit({"event": "published", "topic": args.planned_trajectory, "n": 1})

    deadline = time.monotonic() + args.timeout
    i = 0
    while time.monotonic() < deadline:
        i += 1
        js = JointState()
        stamp(js.header.stamp, 1_000_000_000 + i * 33_000_000)
        js.name = JOINTS
        js.position = joint_positions(i)
        js.velocity = [0.5, 0.0, -0.5]
        joints.publish(js)
        img = CompressedImage()
        stamp(img.header.stamp, 1_000_000_000 + i * 33_000_000)
        img.header.frame_id = "head_camera"
        img.format = "jpeg"
        img.data = JPEG_BYTES + bytes([i % 256])
        images.publish(img)
        if i == 1 or i % 30 == 0:
            emit({"event": "published", "topic": args.joint_states, "n": i})
        rclpy.spin_once(node, timeout_sec=args.period)
    return 0


def sway(names, t):
    """A slow, small sway of every joint (radians) at time t (s)."""
    return [0.05 * math.sin(0.8 * t + 0.3 * j) for j in range(len(names))]


def current_fault(path):
    """The fault named in the file at `path` (empty: none, or no file)."""
    if not path:
        return ""
    try:
        with open(path) as f:
            return f.read().strip()
    except FileNotFoundError:
        return ""


def walk(args):
    """Joint states (30 Hz) and a plan (1 Hz) of a slow sway, stamped now;
    with --camera and --jpeg, also that JPEG as the head camera; --streams
    names the ones to publish (default all three). With --fault-file,
    while that file names a fault, the input goes bad: `future` stamps
    joint states and images 5 s ahead, `past` 60 s behind, `nan` makes a
    joint NaN, `empty_plan` publishes trajectories with no points,
    `plan_nan` plans with a NaN angle, `plan_limits` plans 3 rad beyond
    every joint's angle, `bad_jpeg` sends image bytes that are not a JPEG,
    `huge_image` a 10 MB image twice a second instead of the frames,
    `freeze` publishes no image."""
    from sensor_msgs.msg import CompressedImage, JointState
    from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

    names = args.joints.split(",")
    streams = set(args.streams.split(","))
    unknown = streams - {"joints", "plan", "camera"}
    if unknown:
        raise SystemExit(f"bad --streams {args.streams!r}: unknown {sorted(unknown)}")
    node = rclpy.create_node("fall_guard_test_walker")
    joints = node.create_publisher(JointState, args.joint_states, QOS["sensor_data"])
    plans = node.create_publisher(JointTrajectory, args.planned_trajectory, QOS["latched"])
    images = None
    jpeg = b""
    huge = b"\xff" * 10_000_000
    next_huge = 0.0
    shift_ns = {"future": 5_000_000_000, "past": -60_000_000_000}
    if args.camera and args.jpeg and "camera" in streams:
        images = node.create_publisher(CompressedImage, args.camera, QOS["sensor_data"])
        with open(args.jpeg, "rb") as f:
            jpeg = f.read()
    start = time.time()
    deadline = time.monotonic() + args.timeout
    i = 0
    next_plan = 0.0
    last_fault = ""
    while time.monotonic() < deadline:
        now = time.time()
        now_ns = time.time_ns()
        fault = current_fault(args.fault_file)
        if fault != last_fault:
            emit({"event": "fault", "fault": fault, "t": time.monotonic()})
            last_fault = fault
        if "plan" in streams and now >= next_plan and fault == "empty_plan":
            plan = JointTrajectory()
            stamp(plan.header.stamp, now_ns)
            plan.joint_names = names
            plans.publish(plan)
            next_plan = now + 1.0
        if "plan" in streams and now >= next_plan:
            plan = JointTrajectory()
            stamp(plan.header.stamp, now_ns)
            plan.joint_names = names
            for p in range(121):
                dt_ns = p * 33_333_333
                point = JointTrajectoryPoint()
                point.positions = sway(names, now - start + dt_ns / 1e9)
                if fault == "plan_nan":
                    point.positions[0] = float("nan")
                elif fault == "plan_limits":
                    point.positions = [v + 3.0 for v in point.positions]
                point.time_from_start.sec = dt_ns // 1_000_000_000
                point.time_from_start.nanosec = dt_ns % 1_000_000_000
                plan.points.append(point)
            plans.publish(plan)
            emit({"event": "published", "topic": args.planned_trajectory, "n": int(now - start) + 1})
            next_plan = now + 1.0
        i += 1
        if "joints" in streams:
            js = JointState()
            stamp(js.header.stamp, now_ns + shift_ns.get(fault, 0))
            js.name = names
            js.position = sway(names, now - start)
            if fault == "nan":
                js.position[0] = float("nan")
            joints.publish(js)
        if images is not None and fault != "freeze" and (fault != "huge_image" or now >= next_huge):
            img = CompressedImage()
            stamp(img.header.stamp, now_ns + shift_ns.get(fault, 0))
            img.header.frame_id = "head_camera"
            img.format = "jpeg"
            img.data = b"not a JPEG at all" if fault == "bad_jpeg" else huge if fault == "huge_image" else jpeg
            if fault == "huge_image":
                next_huge = now + 0.5
            images.publish(img)
        if i == 1 or i % 30 == 0:
            emit({"event": "published", "topic": args.joint_states, "n": i})
        rclpy.spin_once(node, timeout_sec=args.period)
    return 0


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="mode", required=True)
    lp = sub.add_parser("listen")
    lp.add_argument("--sub", action="append", default=[], help="TOPIC:TYPE:QOS")
    lp.add_argument("--count", action="append", default=[], help="TOPIC=N to wait for")
    lp.add_argument(
        "--count-finite",
        action="append",
        default=[],
        help="TOPIC=N: wait for N messages whose array `data` is all finite numbers",
    )
    lp.add_argument("--timeout", type=float, default=30.0)
    pp = sub.add_parser("publish")
    pp.add_argument("--joint-states", default="/joint_states")
    pp.add_argument("--planned-trajectory", default="/planned_trajectory")
    pp.add_argument("--camera", default="/head_camera/image_raw/compressed")
    pp.add_argument("--period", type=float, default=0.033)
    pp.add_argument("--timeout", type=float, default=30.0)
    wp = sub.add_parser("walk")
    wp.add_argument("--joints", required=True, help="joint names, comma-separated")
    wp.add_argument("--joint-states", default="/joint_states")
    wp.add_argument("--planned-trajectory", default="/planned_trajectory")
    wp.add_argument("--period", type=float, default=0.033)
    wp.add_argument("--timeout", type=float, default=60.0)
    wp.add_argument("--camera", default="/head_camera/image_raw/compressed", help="topic of the --jpeg frames")
    wp.add_argument(
        "--jpeg", "--camera-jpeg", dest="jpeg", default="", help="publish this JPEG file's bytes as camera frames"
    )
    wp.add_argument("--fault-file", default="", help="a file naming the fault to inject (see walk)")
    wp.add_argument("--streams", default="joints,plan,camera", help="the streams to publish, comma-separated")
    args = parser.parse_args()
    rclpy.init()
    try:
        modes = {"listen": listen, "publish": publish, "walk": walk}
        return modes[args.mode](args)
    finally:
        rclpy.try_shutdown()


if __name__ == "__main__":
    sys.exit(main())
