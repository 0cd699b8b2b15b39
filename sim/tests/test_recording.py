"""A generated episode read back by rosbags: topics, types, counts, stamps, labels, metadata."""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np
from PIL import Image
from rosbags.typesys import get_types_from_msg

from sim.episode import GENERATOR_VERSION, RATE_HZ, stamp_ns
from sim.robot import JOINT_NAMES
from sim.tests.readback import TYPESTORE, read_metadata, read_recording

EXPECTED_TYPES = {
    "/joint_states": "sensor_msgs/msg/JointState",
    "/planned_trajectory": "trajectory_msgs/msg/JointTrajectory",
    "/head_camera/image_raw/compressed": "sensor_msgs/msg/CompressedImage",
    "/ground_truth/fallen": "std_msgs/msg/Bool",
}


def ns_of(t) -> int:
    return t.sec * 1_000_000_000 + t.nanosec


def test_topics_types_counts_and_stamps(small_dataset):
    out, stats = small_dataset
    for s in stats:
        path = out / f"episode_{s['index']:05d}.mcap"
        schemas, topics = read_recording(path)
        n_ticks = 4 * RATE_HZ
        assert {t: msgs[0][1] for t, msgs in topics.items()} == EXPECTED_TYPES
        assert len(topics["/ground_truth/fallen"]) == n_ticks
        assert len(topics["/planned_trajectory"]) == 4  # every 1 s
        assert [log for log, _, _ in topics["/ground_truth/fallen"]] == [stamp_ns(k) for k in range(n_ticks)]
        # The joints come at the servo buses' 50 Hz cycle, stamped with the cycle's newest read
        # (up to 2 ms late, the upper bus 5-9 ms and a retry 2-6 ms after the lower bus).
        joints = [log for log, _, _ in topics["/joint_states"]]
        assert len(joints) == 4 * 50 - 1  # cycles from 0 to the last tick's time
        assert all(0 < b - a < 40_000_000 for a, b in zip(joints, joints[1:]))
        assert all(5_000_000 <= log - 20_000_000 * c <= 17_000_000 for c, log in enumerate(joints))
        for log, _, msg in topics["/joint_states"]:
            assert ns_of(msg.header.stamp) == log
            assert list(msg.name) == list(JOINT_NAMES)
            assert len(msg.position) == 25 and np.all(np.isfinite(msg.position))
        # Camera frames at the ticks, some dropped (frozen ones repeat the bytes of an earlier one).
        frames = [log for log, _, _ in topics["/head_camera/image_raw/compressed"]]
        assert set(frames) <= {stamp_ns(k) for k in range(n_ticks)} and len(frames) >= 0.9 * n_ticks
        for log, _, msg in topics["/head_camera/image_raw/compressed"]:
            assert ns_of(msg.header.stamp) == log and msg.format == "jpeg"
        img = Image.open(io.BytesIO(bytes(topics["/head_camera/image_raw/compressed"][0][2].data)))
        assert img.format == "JPEG" and img.size == (64, 64) and img.mode == "RGB"
        # The camera sees a scene (furniture, walls, floor), not one flat colour.
        assert np.asarray(img, dtype=float).std(axis=(0, 1)).max() > 10
        for i, (log, _, msg) in enumerate(topics["/planned_trajectory"]):
            assert log == stamp_ns(i * RATE_HZ)
            # point 0 applies 2.5 s before now; points every tick to now + 3 s.
            assert ns_of(msg.header.stamp) == stamp_ns(i * RATE_HZ - 75)
            assert list(msg.joint_names) == list(JOINT_NAMES)
            assert len(msg.points) == 166
            first = i * RATE_HZ - 75
            for j, p in enumerate(msg.points):
                assert ns_of(p.time_from_start) == stamp_ns(first + j) - stamp_ns(first)
                assert len(p.positions) == 25
        # Before the episode starts, the plan holds the first pose.
        pts = topics["/planned_trajectory"][0][2].points
        assert all(np.array_equal(pts[j].positions, pts[75].positions) for j in range(75))
        # Successive plans agree where they overlap (one plan per episode, published in pieces).
        a, b = topics["/planned_trajectory"][0][2].points, topics["/planned_trajectory"][1][2].points
        for j in range(75 + 30, 166):
            assert np.array_equal(a[j].positions, b[j - 30].positions)
        # The schemas are ros2msg texts that rosbags parses into the standard definitions.
        for name, (encoding, text) in schemas.items():
            assert encoding == "ros2msg"
            parsed = get_types_from_msg(text.split("=" * 80)[0], name)
            std_fields = [f[0] for f in TYPESTORE.fielddefs[name][1]]
            assert [f[0] for f in parsed[name][1]] == std_fields, name


def test_metadata_and_labels_agree_with_head_height(small_dataset):
    out, stats = small_dataset
    for s in stats:
        path = out / f"episode_{s['index']:05d}.mcap"
        meta = read_metadata(path)
        for key in ("source", "robot", "rate_hz", "seed", "sigma", "standing_head_height_m",
                    "fall_threshold_m", "duration_s"):
            assert isinstance(meta[key], str) and meta[key], key
        assert meta["source"] == "sim" and meta["robot"] == "poppy_humanoid" and meta["rate_hz"] == "30"
        assert meta["duration_s"] == "4"
        assert abs(float(meta["fall_threshold_m"]) - 0.8 * float(meta["standing_head_height_m"])) < 1e-3
        assert float(meta["sigma"]) in (0.005, 0.01, 0.035, 0.04)
        _, topics = read_recording(path)
        fallen = [m.data for _, _, m in topics["/ground_truth/fallen"]]
        if any(fallen):
            onset = fallen.index(True)
            assert all(fallen[onset:]), "fallen must be sticky"
            assert meta["fall_onset_ns"] == str(stamp_ns(onset))
        else:
            assert "fall_onset_ns" not in meta


def test_labels_follow_head_height():
    """Fallen is exactly 'head below 0.8 x standing height', sticky from the first such tick."""
    from sim.episode import simulate_episode

    ep = simulate_episode(100_005, sigma=0.04, duration_s=6.0, render=False)
    below = ep.head_height_m < ep.fall_threshold_m
    assert np.array_equal(ep.fallen, np.maximum.accumulate(below))
    assert ep.fall_threshold_m == round(0.8 * ep.standing_head_height_m, 4)
    assert 0.70 < ep.standing_head_height_m < 0.74


def test_manifest(small_dataset):
    out, _ = small_dataset
    manifest = json.loads((out / "manifest.json").read_text())
    names = manifest["train"] + manifest["validation"] + manifest["test"]
    assert sorted(names) == ["episode_00000.mcap", "episode_00001.mcap"]
    assert manifest["generator"]["seed"] == 3 and manifest["generator"]["rate_hz"] == 30
    assert manifest["generator"]["version"] == GENERATOR_VERSION
    for name in names:
        meta = read_metadata(out / name)
        assert meta["generator"] == str(GENERATOR_VERSION)
        assert meta["plan_id"] == manifest["plans"][name]


def test_stats_report_causes_distance_and_refuse_nothing(small_dataset):
    from sim.stats import summarise

    out, stats = small_dataset
    s = summarise(out)
    assert s["episodes"] == 2 and s["generators"] == [str(GENERATOR_VERSION)] and s["distinct_plans"] == 2
    assert s["falling"] == sum(r["fall_onset_tick"] is not None for r in stats)
    for row in s["per_sigma"].values():
        assert row["distance_m"]["min"] >= 0.0
        assert row["collision_falls"] <= row["falling"]


def test_stats_time_the_ball_from_launch_to_the_collision_fall():
    """On the fixtures (one collision fall): the launch lead is that fall's
    onset less its ball's launch, from its own metadata."""
    from sim.stats import read_episode_metadata, summarise

    fixtures = Path(__file__).resolve().parents[2] / "tests" / "fixtures"
    leads = []
    for f in sorted(fixtures.glob("*.mcap")):
        meta = read_episode_metadata(f)
        if meta.get("fall_cause") == "collision":
            launch = json.loads(meta["hazard"])["launch_ns"]
            leads.append((int(meta["fall_onset_ns"]) - int(launch)) / 1e9)
    assert len(leads) == 1
    s = summarise(fixtures)
    assert s["collision_launch_to_onset_s"]["median"] == round(leads[0], 2)
    assert s["collision_launched_before_onset_share"]["0.5"] == float(leads[0] > 0.5)
    assert s["collision_launched_before_onset_share"]["2"] == float(leads[0] > 2.0)


def test_generator_1_directory_is_refused(tmp_path):
    from sim.dataset import DatasetError, generate

    (tmp_path / "manifest.json").write_text(json.dumps({"generator": {"seed": 3, "duration_s": 4.0}}))
    try:
        generate(tmp_path, episodes=1, seed=3, jobs=1, duration_s=4.0, progress=False)
    except DatasetError as e:
        assert "version=1" in str(e) and f"version={GENERATOR_VERSION}" in str(e)
    else:
        raise AssertionError("a generator 1 directory was extended with this generator's episodes")
