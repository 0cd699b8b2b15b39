"""scripts/subset_by_cause.py on the repository's fixture data set and on a synthetic set of four causes."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from mcap.writer import Writer

REPO = Path(__file__).resolve().parents[3]
FIXTURES = REPO / "tests" / "fixtures"
SCRIPT = REPO / "scripts" / "retrain" / "subset_by_cause.py"
sys.path.insert(0, str(REPO))
from sim.recording import METADATA_NAME  # noqa: E402


def subsets(src: Path, out: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPT), str(src), str(out)], check=True, capture_output=True, text=True)


def split_of(out: Path, name: str, src: Path) -> list[str]:
    """The test split of OUT/NAME, checked to be a subset of SRC's recordings."""
    m = json.loads((out / name / "manifest.json").read_text())
    assert m["train"] == [] and m["validation"] == []
    assert m["generator"]["subset"]
    for episode in m["test"]:
        assert (out / name / episode).resolve() == (src / episode).resolve()
    return m["test"]


def test_the_subsets_hold_each_cause_with_the_walks(tmp_path):
    # The fixtures' test split: episode 6 walks (sigma 0.01), episode 7 falls
    # by collision (sigma 0.035); validation: 4 walks, 5 falls by perturbation.
    out = tmp_path / "bycause"
    subsets(FIXTURES, out)
    assert json.loads((out / "collision" / "manifest.json").read_text())["generator"]["seed"] == 7
    assert split_of(out, "collision", FIXTURES) == ["episode_00006.mcap", "episode_00007.mcap"]
    # No test fall by perturbation: no subset of it.
    assert not (out / "perturbation").exists()
    assert split_of(out, "high-sigma", FIXTURES) == ["episode_00007.mcap"]
    assert split_of(out, "validation-collision", FIXTURES) == ["episode_00004.mcap"]
    stats = json.loads((out / "causes.json").read_text())
    assert (stats["falls"], stats["walks"], list(stats["causes"])) == (1, 1, ["collision"])
    # Generator 6 times the fall from the ball's first touch (cause_ns): 0.9 s before the onset.
    assert stats["causes"]["collision"]["cause_to_onset_s"]["median"] == 0.9
    assert stats["causes"]["collision"]["timed_falls"] == 1


S = 1_000_000_000


def write_episode(path: Path, sigma: float, cause: str | None = None, onset_s: float | None = None,
                  cause_s: float | None = None, event_s: float | None = None) -> None:
    """A recording with only its episode metadata, as generator 6 writes it."""
    meta = {"source": "sim", "generator": "6", "sigma": f"{sigma:g}"}
    if onset_s is not None:
        meta.update(fall_onset_ns=str(round(onset_s * S)), fall_cause=cause)
    if cause_s is not None:
        meta["cause_ns"] = str(round(cause_s * S))
    if event_s is not None:
        meta["event_ns"] = str(round(event_s * S))
    with open(path, "wb") as f:
        w = Writer(f)
        w.start(profile="ros2")
        w.add_metadata(METADATA_NAME, meta)
        w.finish()


def four_causes(root: Path) -> Path:
    """A set of generator 6's four causes: test falls by perturbation (2), push (2), collision
    (1), obstacle (1) and two walks; validation: a collision fall, a push fall and a walk."""
    root.mkdir()
    test = {
        "t_pert_event.mcap": dict(sigma=0.04, cause="perturbation", onset_s=6.0, event_s=4.5),
        "t_pert_low.mcap": dict(sigma=0.005, cause="perturbation", onset_s=3.0),
        "t_push_far.mcap": dict(sigma=0.01, cause="push", onset_s=5.0, cause_s=4.1),
        "t_push_near.mcap": dict(sigma=0.005, cause="push", onset_s=7.0, cause_s=6.7),
        "t_ball.mcap": dict(sigma=0.035, cause="collision", onset_s=8.0, cause_s=7.6),
        "t_table.mcap": dict(sigma=0.01, cause="obstacle", onset_s=5.5, cause_s=3.1),
        "t_walk.mcap": dict(sigma=0.01),
        "t_walk_high.mcap": dict(sigma=0.035, event_s=5.0),
    }
    validation = {
        "v_ball.mcap": dict(sigma=0.005, cause="collision", onset_s=6.0, cause_s=5.2),
        "v_push.mcap": dict(sigma=0.005, cause="push", onset_s=4.0, cause_s=3.5),
        "v_walk.mcap": dict(sigma=0.005),
    }
    for name, kw in {**test, **validation}.items():
        write_episode(root / name, **kw)
    (root / "manifest.json").write_text(json.dumps({
        "train": [], "validation": sorted(validation), "test": sorted(test), "generator": {"seed": 6}}))
    return root


def test_every_cause_of_generator_6_gets_its_subset_and_its_figures(tmp_path):
    src = four_causes(tmp_path / "set")
    out = tmp_path / "bycause"
    subsets(src, out)
    walks = ["t_walk.mcap", "t_walk_high.mcap"]
    # A push or an obstacle fall is a fall: in its own subset, never among the walks.
    assert split_of(out, "perturbation", src) == sorted(["t_pert_event.mcap", "t_pert_low.mcap", *walks])
    assert split_of(out, "push", src) == sorted(["t_push_far.mcap", "t_push_near.mcap", *walks])
    assert split_of(out, "collision", src) == sorted(["t_ball.mcap", *walks])
    assert split_of(out, "obstacle", src) == sorted(["t_table.mcap", *walks])
    assert split_of(out, "high-sigma", src) == ["t_ball.mcap", "t_pert_event.mcap", "t_walk_high.mcap"]
    assert split_of(out, "validation-collision", src) == ["v_ball.mcap", "v_walk.mcap"]

    stats = json.loads((out / "causes.json").read_text())
    assert (stats["split"], stats["episodes"], stats["falls"], stats["walks"]) == ("test", 8, 6, 2)
    # Most falls first, then by name.
    assert list(stats["causes"]) == ["perturbation", "push", "collision", "obstacle"]
    c = stats["causes"]
    assert [c[k]["falls"] for k in c] == [2, 2, 1, 1]
    assert [c[k]["share_of_falls"] for k in c] == [0.333, 0.333, 0.167, 0.167]
    # From cause_ns: the push 0.9 s and 0.3 s before its onset (median 0.6), only the first >= 0.5 s.
    assert c["push"]["cause_to_onset_s"]["median"] == 0.6
    assert (c["push"]["timed_falls"], c["push"]["caused_0_5s_before_onset"]) == (2, 1)
    assert c["collision"]["cause_to_onset_s"]["median"] == 0.4
    assert (c["collision"]["timed_falls"], c["collision"]["caused_0_5s_before_onset"]) == (1, 0)
    assert c["obstacle"]["cause_to_onset_s"]["median"] == 2.4
    # A perturbation fall has no outside cause: timed from its event, where it had one.
    assert c["perturbation"]["cause_to_onset_s"] is None
    assert c["perturbation"]["event_to_onset_s"]["median"] == 1.5
    assert (c["perturbation"]["timed_falls"], c["perturbation"]["caused_0_5s_before_onset"]) == (1, 1)

    # The retrain's list of causes, from the same file.
    r = subprocess.run([sys.executable, str(REPO / "scripts" / "retrain" / "reports.py"), "causes", str(out)],
                       check=True, capture_output=True, text=True)
    assert r.stdout.split() == ["perturbation", "push", "collision", "obstacle"]


def test_a_subset_made_again_keeps_its_manifest_unless_it_changed(tmp_path):
    src = four_causes(tmp_path / "set")
    out = tmp_path / "bycause"
    subsets(src, out)
    manifest = out / "push" / "manifest.json"
    before = manifest.stat().st_mtime_ns
    subsets(src, out)
    assert manifest.stat().st_mtime_ns == before
    # The push fall becomes an obstacle fall: both subsets change.
    write_episode(src / "t_push_near.mcap", sigma=0.005, cause="obstacle", onset_s=7.0, cause_s=6.7)
    subsets(src, out)
    assert "t_push_near.mcap" not in split_of(out, "push", src)
    assert "t_push_near.mcap" in split_of(out, "obstacle", src)
