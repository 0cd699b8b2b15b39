"""Write one episode as an MCAP recording, as ``ros2 bag record -s mcap`` would.

Data enters as numpy arrays of one simulated episode (``episode.Episode``) and
leaves as a ``.mcap`` file: profile ``ros2``, schema encoding ``ros2msg`` (the
``.msg`` text with dependencies appended after ``====`` lines, as rosbag2
writes it), message encoding ``cdr``, zstd chunks; plus the metadata record
``fall_guard.episode``. Topics, rates and stamps follow docs/contracts.md
"Recording conventions".
"""

from __future__ import annotations

import os
from pathlib import Path

from mcap_ros2.writer import Writer

from .episode import stamp_ns
from .robot import JOINT_NAMES, ROBOT_NAME

SEPARATOR = "=" * 80

_TIME = "int32 sec\nuint32 nanosec\n"
_HEADER = "builtin_interfaces/Time stamp\nstring frame_id\n"


def _schema(top: str, deps: list[tuple[str, str]]) -> str:
    text = top
    for name, body in deps:
        text += f"{SEPARATOR}\nMSG: {name}\n{body}"
    return text


SCHEMAS: dict[str, str] = {
    "sensor_msgs/msg/JointState": _schema(
        "std_msgs/Header header\nstring[] name\nfloat64[] position\nfloat64[] velocity\nfloat64[] effort\n",
        [("std_msgs/Header", _HEADER), ("builtin_interfaces/Time", _TIME)]),
    "trajectory_msgs/msg/JointTrajectory": _schema(
        "std_msgs/Header header\nstring[] joint_names\nJointTrajectoryPoint[] points\n",
        [("std_msgs/Header", _HEADER), ("builtin_interfaces/Time", _TIME),
         ("trajectory_msgs/JointTrajectoryPoint",
          "float64[] positions\nfloat64[] velocities\nfloat64[] accelerations\nfloat64[] effort\n"
          "builtin_interfaces/Duration time_from_start\n"),
         ("builtin_interfaces/Duration", _TIME)]),
    "sensor_msgs/msg/CompressedImage": _schema(
        "std_msgs/Header header\nstring format\nuint8[] data\n",
        [("std_msgs/Header", _HEADER), ("builtin_interfaces/Time", _TIME)]),
    "std_msgs/msg/Bool": "bool data\n",
}

TOPIC_JOINTS = "/joint_states"
TOPIC_PLAN = "/planned_trajectory"
TOPIC_CAMERA = "/head_camera/image_raw/compressed"
TOPIC_FALLEN = "/ground_truth/fallen"
TOPIC_TYPES = {
    TOPIC_JOINTS: "sensor_msgs/msg/JointState",
    TOPIC_PLAN: "trajectory_msgs/msg/JointTrajectory",
    TOPIC_CAMERA: "sensor_msgs/msg/CompressedImage",
    TOPIC_FALLEN: "std_msgs/msg/Bool",
}
METADATA_NAME = "fall_guard.episode"


def ros_time(ns: int) -> dict[str, int]:
    """builtin_interfaces/Time (or Duration) of a signed ns count: sec floors, nanosec in [0, 1e9)."""
    sec, nanosec = divmod(int(ns), 1_000_000_000)
    return {"sec": sec, "nanosec": nanosec}


def header(ns: int, frame_id: str = "") -> dict:
    return {"stamp": ros_time(ns), "frame_id": frame_id}


def write_episode(path: Path, episode) -> None:
    """Write EPISODE (an ``episode.Episode``) to PATH atomically (temp file + rename)."""
    tmp = path.with_name(path.name + ".partial")
    names = list(JOINT_NAMES)
    with open(tmp, "wb") as f:
        writer = Writer(f)
        schemas = {t: writer.register_msgdef(t, SCHEMAS[t]) for t in SCHEMAS}
        seq = {topic: 0 for topic in TOPIC_TYPES}

        def put(topic: str, msg: dict, log_ns: int) -> None:
            writer.write_message(topic, schemas[TOPIC_TYPES[topic]], msg,
                                 log_time=log_ns, publish_time=log_ns, sequence=seq[topic])
            seq[topic] += 1

        plan_every = episode.plan_period_ticks
        # The joints at the buses' cycle (what the daemon reads), merged in time order with
        # the ticks' messages; or one message a tick.
        reads = getattr(episode, "joint_messages", None)
        sent = getattr(episode, "camera_sent", None)
        r = 0

        def put_joints(ns: int, positions) -> None:
            put(TOPIC_JOINTS, {
                "header": header(ns, "base"),
                "name": names,
                "position": [float(a) for a in positions],
                "velocity": [], "effort": [],
            }, ns)

        for k in range(episode.n_ticks):
            now_ns = stamp_ns(k)
            while reads is not None and r < len(reads) and reads[r][0] <= now_ns:
                put_joints(*reads[r])
                r += 1
            if k % plan_every == 0:
                first, points = episode.plan_message_points(k)
                put(TOPIC_PLAN, {
                    "header": header(stamp_ns(first), "base"),
                    "joint_names": names,
                    "points": [{
                        "positions": [float(a) for a in row],
                        "velocities": [], "accelerations": [], "effort": [],
                        "time_from_start": ros_time(stamp_ns(first + i) - stamp_ns(first)),
                    } for i, row in enumerate(points)],
                }, now_ns)
            if reads is None:
                put_joints(now_ns, episode.joints_rad[k])
            frame = k if sent is None else sent[k]
            if frame >= 0:
                put(TOPIC_CAMERA, {
                    "header": header(now_ns, "head_camera"),
                    "format": "jpeg",
                    "data": episode.jpeg_frames[frame],
                }, now_ns)
            put(TOPIC_FALLEN, {"data": bool(episode.fallen[k])}, now_ns)
        # mcap_ros2's Writer has no metadata call; its inner mcap Writer does.
        writer._writer.add_metadata(METADATA_NAME, episode.metadata())
        writer.finish()
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


__all__ = ["write_episode", "TOPIC_TYPES", "SCHEMAS", "METADATA_NAME", "ROBOT_NAME"]
