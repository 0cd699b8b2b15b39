"""A data set of simulated episodes: a directory of ``.mcap`` files + ``manifest.json``.

Data enters as (out dir, number of episodes, base seed, jobs) and leaves as files:
``episode_NNNNN.mcap`` (episode index N, episode seed ``base_seed * 100000 + N``)
and ``manifest.json`` with the train / validation / test split (0.8 / 0.1 / 0.1
by episode, a seeded shuffle) and the generator parameters. A second run with the
same arguments only makes the files that are missing (each file is written to a
``.partial`` name and renamed when complete), and the same arguments always
give the same episodes.
"""

from __future__ import annotations

import json
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

import numpy as np
from tqdm import tqdm

from .episode import (DURATION_S, GENERATOR_VERSION, HAZARD_PROBABILITY, KNOT_TICKS, PERTURBATION_SCALE,
                      PHYSICS_HZ, RATE_HZ, SIGMAS, VALIDATION_DRAWS, VALIDATION_SIGMA, simulate_episode)
from .recording import write_episode
from .robot import FALL_FRACTION, JOINT_NAMES, ROBOT_NAME

SEED_STRIDE = 100_000
SPLITS = (("train", 0.8), ("validation", 0.1), ("test", 0.1))


class DatasetError(Exception):
    """A bad argument or an unusable output directory, with what to do about it."""


def episode_seed(base_seed: int, index: int) -> int:
    return base_seed * SEED_STRIDE + index


def episode_name(index: int) -> str:
    return f"episode_{index:05d}.mcap"


def split_names(n: int, base_seed: int) -> dict[str, list[str]]:
    """Split episode indices 0..n-1 into train/validation/test, by a seeded shuffle."""
    order = np.random.default_rng([base_seed, 7]).permutation(n)
    n_val = int(round(n * SPLITS[1][1]))
    n_test = int(round(n * SPLITS[2][1]))
    n_train = n - n_val - n_test
    parts = {"train": order[:n_train], "validation": order[n_train:n_train + n_val],
             "test": order[n_train + n_val:]}
    return {k: [episode_name(int(i)) for i in sorted(v)] for k, v in parts.items()}


def check_args(out: Path, episodes: int, seed: int, jobs: int, duration_s: float) -> None:
    if episodes < 1:
        raise DatasetError(f"--episodes must be at least 1 (got {episodes})")
    if episodes >= SEED_STRIDE:
        raise DatasetError(f"--episodes must be below {SEED_STRIDE} (got {episodes})")
    if seed < 0:
        raise DatasetError(f"--seed must be >= 0 (got {seed})")
    if jobs < 1:
        raise DatasetError(f"--jobs must be at least 1 (got {jobs})")
    if not 1.0 <= duration_s <= 120.0:
        raise DatasetError(f"--duration must be within 1..120 s (got {duration_s})")
    if out.exists() and not out.is_dir():
        raise DatasetError(f"--out {out}: exists and is not a directory")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise DatasetError(f"--out {out}: cannot create the directory ({e.strerror}); choose a writable path") from e
    probe = out / f".write_probe_{os.getpid()}"
    try:
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as e:
        raise DatasetError(f"--out {out}: directory is not writable ({e.strerror}); choose a writable path") from e


def _write_manifest(path: Path, manifest: dict) -> None:
    tmp = path.with_suffix(".json.partial")
    tmp.write_text(json.dumps(manifest, indent=2) + "\n")
    os.replace(tmp, path)


def _make_one(out: str, index: int, seed: int, duration_s: float) -> dict:
    t0 = time.perf_counter()
    ep = simulate_episode(seed, duration_s=duration_s)
    write_episode(Path(out) / episode_name(index), ep)
    return {"index": index, "sigma": ep.sigma, "fall_onset_tick": ep.fall_onset_tick, "fall_cause": ep.fall_cause,
            "seconds": time.perf_counter() - t0, "plan_attempts": ep.plan_attempts}


def generate(out: Path, episodes: int, seed: int, jobs: int = 1, duration_s: float = DURATION_S,
             progress: bool = True) -> list[dict]:
    """Make the missing episodes of the data set and (re)write its manifest; returns per-episode stats."""
    check_args(out, episodes, seed, jobs, duration_s)
    manifest_path = out / "manifest.json"
    generator = {
        "name": "fall_guard.sim", "version": GENERATOR_VERSION, "robot": ROBOT_NAME, "rate_hz": RATE_HZ,
        "physics_hz": PHYSICS_HZ,
        "seed": seed, "seed_range": [episode_seed(seed, 0), episode_seed(seed, episodes - 1)],
        "episodes": episodes, "duration_s": duration_s, "sigmas": list(SIGMAS),
        "fall_fraction": FALL_FRACTION, "joint_names": list(JOINT_NAMES),
        "knot_ticks": KNOT_TICKS, "perturbation_scale_rad": PERTURBATION_SCALE,
        "validation": {"draws": VALIDATION_DRAWS, "sigma": VALIDATION_SIGMA},
        "hazard_probability": HAZARD_PROBABILITY,
    }
    if manifest_path.exists():
        try:
            old = json.loads(manifest_path.read_text()).get("generator", {})
        except (OSError, json.JSONDecodeError) as e:
            raise DatasetError(f"{manifest_path}: unreadable manifest ({e}); remove it or use another --out") from e
        old.setdefault("version", 1)  # generator 1 wrote no version
        for key in ("version", "seed", "duration_s"):
            if old.get(key, generator[key]) != generator[key]:
                raise DatasetError(f"{manifest_path}: made with {key}={old[key]}, asked {key}={generator[key]}; "
                                   "use another --out or the same arguments")
    manifest = split_names(episodes, seed)
    manifest["generator"] = generator
    # Written first too, so an interrupted run is recognised (seed, duration) when resumed.
    _write_manifest(manifest_path, manifest)
    todo = [i for i in range(episodes) if not (out / episode_name(i)).is_file()]
    for stale in out.glob("*.partial"):
        stale.unlink()
    stats: list[dict] = []
    bar = tqdm(total=episodes, initial=episodes - len(todo), unit="ep", disable=not progress,
               desc=f"generating {out}", file=sys.stderr)
    if jobs == 1:
        for i in todo:
            stats.append(_make_one(str(out), i, episode_seed(seed, i), duration_s))
            bar.update(1)
    else:
        with ProcessPoolExecutor(max_workers=jobs) as pool:
            futures = [pool.submit(_make_one, str(out), i, episode_seed(seed, i), duration_s) for i in todo]
            for fut in as_completed(futures):
                stats.append(fut.result())
                bar.update(1)
    bar.close()
    _write_manifest(manifest_path, manifest)
    return sorted(stats, key=lambda s: s["index"])
