"""The committed test fixtures: a small data set in ``tests/fixtures/``.

Eight episodes of 10 s from the generator the shipped networks learnt, four
that fall and four that do not, each made to a recipe (``RECIPES``: the
split, the gait family, sigma, which outside causes it meets, and the
outcome asked of it): the first candidate seed of its slot whose episode
has that outcome is kept, so regeneration gives the same files. Train: a
dynamic walk, a fall by the plan's event, a walk of the hardware gait (the
real walk's step), a fall by a push. Validation: a walk and a fall by the
plan's event. Test: a walk and the README's demo, a fall by a ball the
camera sees coming. ``manifest.json`` lists the splits. Regenerate with
``python -m sim fixtures``.
"""

from __future__ import annotations

import json
import os
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .dataset import SEED_STRIDE, check_args, episode_name
from .episode import DURATION_S, PHYSICS_HZ, RATE_HZ, search_plan, simulate_episode
from .recording import write_episode
from .robot import FALL_FRACTION, JOINT_NAMES, ROBOT_NAME

FIXTURE_BASE_SEED = 7
#: Candidate seeds per slot: slot S tries FIXTURE_BASE_SEED * SEED_STRIDE + S * CANDIDATES + j.
CANDIDATES = 40
#: A fixture's fall comes this late or later, so that a replay shows the network's window full
#: and released for seconds of walking before it (the window holds 2 s).
MIN_ONSET_S = 5.0


@dataclass(frozen=True)
class Recipe:
    split: str
    sigma: float
    cause: str | None        # the fall cause asked for; None: the episode must not fall
    gait: str = "dynamic"
    ball: bool = False
    push: bool = False


RECIPES: tuple[Recipe, ...] = (
    Recipe("train", 0.005, None),
    Recipe("train", 0.04, "perturbation"),
    Recipe("train", 0.01, None, gait="hardware"),
    Recipe("train", 0.01, "push", push=True),
    Recipe("validation", 0.005, None),
    Recipe("validation", 0.04, "perturbation"),
    Recipe("test", 0.01, None),
    Recipe("test", 0.035, "collision", ball=True),
)


def _candidate(slot: int, seed: int):
    r = RECIPES[slot]
    plan = None
    if r.gait != "dynamic":
        plan = search_plan(np.random.default_rng([seed, 31]), DURATION_S, f"fixture:{slot}", family=r.gait)
    ep = simulate_episode(seed, sigma=r.sigma, duration_s=DURATION_S, plan=plan, hazard=r.ball, push=r.push,
                          obstacle=False)
    wanted = (ep.fall_cause == r.cause and (not r.ball or ep.contact_with == "ball")
              and (ep.fall_onset_tick is None or ep.fall_onset_tick >= MIN_ONSET_S * RATE_HZ))
    return ep if wanted else None


def _slot(slot: int, out: str) -> dict:
    for j in range(CANDIDATES):
        seed = FIXTURE_BASE_SEED * SEED_STRIDE + slot * CANDIDATES + j
        ep = _candidate(slot, seed)
        if ep is not None:
            write_episode(Path(out) / episode_name(slot), ep)
            return {"file": episode_name(slot), "seed": seed, "sigma": ep.sigma,
                    "fall_onset_tick": ep.fall_onset_tick, "fall_cause": ep.fall_cause,
                    "gait": RECIPES[slot].gait}
    raise RuntimeError(f"fixtures: slot {slot} ({RECIPES[slot]}) had no such episode in {CANDIDATES} seeds")


def make_fixtures(out: Path, jobs: int = 2) -> list[dict]:
    check_args(out, 1, FIXTURE_BASE_SEED, jobs, DURATION_S)
    for old in out.glob("episode_*.mcap"):
        old.unlink()
    with ProcessPoolExecutor(max_workers=jobs) as pool:
        rows = list(pool.map(_slot, range(len(RECIPES)), [str(out)] * len(RECIPES)))
    manifest = {
        split: [r["file"] for r, recipe in zip(rows, RECIPES) if recipe.split == split]
        for split in ("train", "validation", "test")
    }
    manifest["generator"] = {
        "name": "fall_guard.sim fixtures", "robot": ROBOT_NAME, "rate_hz": RATE_HZ,
        "physics_hz": PHYSICS_HZ, "seed": FIXTURE_BASE_SEED, "seeds": [r["seed"] for r in rows],
        "duration_s": DURATION_S, "fall_fraction": FALL_FRACTION, "joint_names": list(JOINT_NAMES),
        "recipes": [recipe.__dict__ for recipe in RECIPES], "command": "python -m sim fixtures",
    }
    tmp = out / "manifest.json.partial"
    tmp.write_text(json.dumps(manifest, indent=2) + "\n")
    os.replace(tmp, out / "manifest.json")
    return rows
