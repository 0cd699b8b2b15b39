"""The committed test fixtures: a small data set in ``tests/fixtures/``.

Eight episodes of 10 s, four that fall and four that do not, chosen from a fixed
list of candidate seeds (so regeneration gives the same files), with a
``manifest.json`` whose every split holds both outcomes: train 2 + 2,
validation 1 + 1, test 1 + 1. Regenerate with ``python -m sim fixtures``.
"""

from __future__ import annotations

import json
import os
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

from .dataset import SEED_STRIDE, check_args, episode_name
from .episode import DURATION_S, PHYSICS_HZ, RATE_HZ, simulate_episode
from .recording import write_episode
from .robot import FALL_FRACTION, JOINT_NAMES, ROBOT_NAME

FIXTURE_BASE_SEED = 7
N_EACH = 4
#: Candidate sigmas in turn: small ones give walking episodes, large ones falls.
SIGMA_CYCLE = (0.005, 0.04, 0.01, 0.035)
MAX_CANDIDATES = 40


def _simulate(seed: int, sigma: float):
    return simulate_episode(seed, sigma=sigma, duration_s=DURATION_S)


def make_fixtures(out: Path, jobs: int = 2) -> list[dict]:
    check_args(out, 1, FIXTURE_BASE_SEED, jobs, DURATION_S)
    for old in out.glob("episode_*.mcap"):
        old.unlink()
    falls, walks = [], []
    i = 0
    with ProcessPoolExecutor(max_workers=jobs) as pool:
        while (len(falls) < N_EACH or len(walks) < N_EACH) and i < MAX_CANDIDATES:
            batch = list(range(i, i + jobs))
            i += jobs
            eps = pool.map(_simulate, [FIXTURE_BASE_SEED * SEED_STRIDE + k for k in batch],
                           [SIGMA_CYCLE[k % len(SIGMA_CYCLE)] for k in batch])
            for k, ep in zip(batch, eps):
                bucket = falls if ep.fall_onset_tick is not None else walks
                if len(bucket) < N_EACH:
                    write_episode(out / episode_name(k), ep)
                    bucket.append((k, ep.sigma, ep.fall_onset_tick))
    if len(falls) < N_EACH or len(walks) < N_EACH:
        raise RuntimeError(f"fixtures: only {len(falls)} falling and {len(walks)} walking episodes "
                           f"in {MAX_CANDIDATES} candidates")
    name = lambda row: episode_name(row[0])  # noqa: E731
    manifest = {
        "train": sorted([name(r) for r in falls[:2] + walks[:2]]),
        "validation": sorted([name(falls[2]), name(walks[2])]),
        "test": sorted([name(falls[3]), name(walks[3])]),
        "generator": {
            "name": "fall_guard.sim fixtures", "robot": ROBOT_NAME, "rate_hz": RATE_HZ,
            "physics_hz": PHYSICS_HZ, "seed": FIXTURE_BASE_SEED,
            "seed_range": [FIXTURE_BASE_SEED * SEED_STRIDE, FIXTURE_BASE_SEED * SEED_STRIDE + i - 1],
            "duration_s": DURATION_S, "sigmas": list(SIGMA_CYCLE), "fall_fraction": FALL_FRACTION,
            "joint_names": list(JOINT_NAMES), "command": "python -m sim fixtures",
        },
    }
    tmp = out / "manifest.json.partial"
    tmp.write_text(json.dumps(manifest, indent=2) + "\n")
    os.replace(tmp, out / "manifest.json")
    return [{"file": episode_name(k), "sigma": s, "fall_onset_tick": o} for k, s, o in sorted(falls + walks)]
