"""Reading recordings back with rosbags (an independent reader) for the tests."""

from __future__ import annotations

from pathlib import Path

from rosbags.interfaces import Connection, ConnectionExtRosbag2
from rosbags.rosbag2.storage_mcap import MCAPFile, McapReader
from rosbags.typesys import Stores, get_typestore

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)


def read_recording(path: Path):
    """(schemas {name: (encoding, text)}, {topic: [(log_ns, msgtype, msg)]}, profile ok)."""
    f = MCAPFile(path)
    f.open()  # checks magic and the ros2 profile
    f.meta_scan()
    schemas = {s.name: (s.encoding, s.data) for s in f.schemas.values()}
    connections = [
        Connection(id=cid, topic=ch.topic, msgtype=ch.schema, msgdef=None, digest="", msgcount=0,
                   ext=ConnectionExtRosbag2(serialization_format=ch.message_encoding, offered_qos_profiles=[]),
                   owner=None)
        for cid, ch in f.channels.items()
    ]
    f.close()
    reader = McapReader([path], connections)
    reader.open()
    # rosbags' indexed path skips chunks whose message_start_time is 0, and the
    # episode clock starts at 0 ns (docs/contracts.md): read by a full scan.
    for r in reader.readers:
        r.chunks = []
    topics: dict[str, list] = {c.topic: [] for c in connections}
    for conn, log_ns, raw in reader.messages():
        assert conn.ext.serialization_format == "cdr"
        topics[conn.topic].append((log_ns, conn.msgtype, TYPESTORE.deserialize_cdr(raw, conn.msgtype)))
    reader.close()
    return schemas, topics


def read_metadata(path: Path) -> dict[str, str]:
    from mcap.reader import make_reader

    with open(path, "rb") as fh:
        for m in make_reader(fh).iter_metadata():
            if m.name == "fall_guard.episode":
                return dict(m.metadata)
    raise AssertionError(f"{path}: no fall_guard.episode metadata")
