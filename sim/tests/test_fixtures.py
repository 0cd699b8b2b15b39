"""The committed fixtures in tests/fixtures/: complete, readable, both outcomes in every split, as their recipes ask."""

from __future__ import annotations

import json
from pathlib import Path

from sim.episode import GENERATOR_VERSION
from sim.fixtures import MIN_ONSET_S, RECIPES
from sim.tests.readback import read_metadata, read_recording

FIXTURES = Path(__file__).resolve().parents[2] / "tests" / "fixtures"


def test_fixture_manifest_and_files():
    manifest = json.loads((FIXTURES / "manifest.json").read_text())
    listed = manifest["train"] + manifest["validation"] + manifest["test"]
    assert len(listed) == len(set(listed)) == 8
    assert sorted(listed) == sorted(p.name for p in FIXTURES.glob("*.mcap"))
    total = sum((FIXTURES / n).stat().st_size for n in listed)
    assert total < 8_000_000
    for split in ("train", "validation", "test"):
        outcomes = {"fall_onset_ns" in read_metadata(FIXTURES / n) for n in manifest[split]}
        assert outcomes == {True, False}, split


def test_fixtures_follow_their_recipes():
    manifest = json.loads((FIXTURES / "manifest.json").read_text())
    for i, recipe in enumerate(RECIPES):
        name = f"episode_{i:05d}.mcap"
        meta = read_metadata(FIXTURES / name)
        assert name in manifest[recipe.split], name
        assert meta["generator"] == str(GENERATOR_VERSION), name
        assert meta.get("fall_cause") == recipe.cause, name
        assert float(meta["sigma"]) == recipe.sigma, name
        assert json.loads(meta["gait"]).get("family", "dynamic") == recipe.gait, name
        if recipe.cause is not None:
            assert int(meta["fall_onset_ns"]) >= MIN_ONSET_S * 1e9, name
        if recipe.ball:
            assert meta["contact_with"] == "ball", name


def test_fixtures_read_back_with_rosbags():
    for path in sorted(FIXTURES.glob("*.mcap")):
        _, topics = read_recording(path)
        # As the daemon reads them: the joints at the buses' 50 Hz cycle, a frame dropped now and then.
        assert 450 <= len(topics["/joint_states"]) <= 500, path
        assert 270 <= len(topics["/head_camera/image_raw/compressed"]) <= 300, path
        assert len(topics["/ground_truth/fallen"]) == 300, path
        assert len(topics["/planned_trajectory"]) == 10, path
        meta = read_metadata(path)
        fallen = [m.data for _, _, m in topics["/ground_truth/fallen"]]
        assert ("fall_onset_ns" in meta) == any(fallen), path
