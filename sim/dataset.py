"""A data set of simulated episodes: a directory of ``.mcap`` files + ``manifest.json``.

Data enters as (out dir, number of episodes, base seed, jobs) and leaves as files:
``episode_NNNNN.mcap`` (episode index N, episode seed ``base_seed * 100000 + N``),
``plans/plan_GGGGG.json`` (the kept walking plans) and ``manifest.json`` with
the train / validation / test split and the generator parameters.

**Plans are shared, never across splits or seeds.** The episodes are cut into
``plan_groups`` contiguous groups of about ``EPISODES_PER_PLAN``; the plan of
group G is searched once (``episode.search_plan``, from the random stream
``[base_seed, PLAN_STREAM, G]``, so another base seed searches other plans) and
followed by every episode of the group, each with its own room, start pose,
ball and perturbation draw from its own episode seed. The split (0.8 / 0.1 /
0.1, a seeded shuffle) is made over the groups, so no plan is in two splits.

A second run with the same arguments only makes the files that are missing
(each file is written to a ``.partial`` name and renamed when complete), and
the same arguments always give the same bytes.
"""

from __future__ import annotations

import json
import math
import os
import resource
import sys
import time
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from pathlib import Path

import numpy as np
from tqdm import tqdm

from .balance import KH, KHD, KR, KRD, LIMIT_RAD
from .episode import (BACKGROUND_SIGMA_MAX, BACKGROUND_SIGMAS, DURATION_S, EVENT_GAIN, EVENT_KNOTS, EVENT_START_S,
                      GENERATOR_VERSION, HAZARD_PROBABILITY, KNOT_TICKS, MIN_PROGRESS_M, OBSTACLE_DIST_M,
                      OBSTACLE_KINDS, PERTURBATION_SCALE, PHYSICS_HZ, PLAN_STREAM, PUSH_DURATION_S, PUSH_IMPULSE_NS,
                      PUSH_START_S, RATE_HZ, SIGMAS, VALIDATION_BACKGROUND_SIGMA, VALIDATION_DRAWS, VALIDATION_SIGMA,
                      KeptPlan, outside_cause_probabilities, search_plan, simulate_episode)
from .gait import GAIT_FAMILIES
from .recording import write_episode
from .robot import FALL_FRACTION, JOINT_NAMES, ROBOT_NAME

SEED_STRIDE = 100_000
SPLITS = (("train", 0.8), ("validation", 0.1), ("test", 0.1))
#: Episodes that follow one kept plan (a 2,000-episode set has 200 plans).
EPISODES_PER_PLAN = 10
#: Small sets get this many plans at least (one per episode below it), so that
#: every split of a set of 10 or more episodes has episodes.
MIN_PLAN_GROUPS = 10


class DatasetError(Exception):
    """A bad argument or an unusable output directory, with what to do about it."""


def episode_seed(base_seed: int, index: int) -> int:
    return base_seed * SEED_STRIDE + index


def episode_name(index: int) -> str:
    return f"episode_{index:05d}.mcap"


def plan_name(group: int) -> str:
    return f"plan_{group:05d}.json"


def plan_groups(episodes: int) -> int:
    """How many plans a set of EPISODES episodes has."""
    return max(math.ceil(episodes / EPISODES_PER_PLAN), min(episodes, MIN_PLAN_GROUPS))


def plan_group(index: int, episodes: int) -> int:
    """The plan group of episode INDEX: contiguous groups of (nearly) equal size."""
    return index * plan_groups(episodes) // episodes


def plan_id(base_seed: int, group: int) -> str:
    return f"{base_seed}:{group}"


def plan_rng(base_seed: int, group: int) -> np.random.Generator:
    """The plan search's random stream of GROUP in the set of BASE_SEED (no other seed or group shares it)."""
    return np.random.default_rng([base_seed, PLAN_STREAM, group])


def split_names(n: int, base_seed: int) -> dict[str, list[str]]:
    """Split episode indices 0..n-1 into train/validation/test by plan group (a seeded shuffle of the groups)."""
    groups = plan_groups(n)
    order = np.random.default_rng([base_seed, 7]).permutation(groups)
    n_val = int(round(groups * SPLITS[1][1]))
    n_test = int(round(groups * SPLITS[2][1]))
    n_train = groups - n_val - n_test
    parts = {"train": order[:n_train], "validation": order[n_train:n_train + n_val],
             "test": order[n_train + n_val:]}
    of_split = {int(g): k for k, gs in parts.items() for g in gs}
    out: dict[str, list[str]] = {k: [] for k in parts}
    for i in range(n):
        out[of_split[plan_group(i, n)]].append(episode_name(i))
    return out


def check_args(out: Path, episodes: int, seed: int, jobs: int, duration_s: float,
               sigmas: tuple[float, ...] = SIGMAS, hazard_probability: float = HAZARD_PROBABILITY,
               gait: str = "dynamic") -> None:
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
    if not sigmas or any(not 0.0 <= x <= 0.2 for x in sigmas):
        raise DatasetError(f"--sigmas must be one or more values within 0..0.2 (got {list(sigmas)})")
    if not 0.0 <= hazard_probability <= 1.0:
        raise DatasetError(f"--ball-probability must be within 0..1 (got {hazard_probability})")
    if gait not in GAIT_FAMILIES:
        raise DatasetError(f"--gait must be one of {', '.join(GAIT_FAMILIES)} (got {gait!r})")
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


def find_plan(out: str, base_seed: int, group: int, duration_s: float, gait: str = "dynamic") -> dict:
    """Search the plan of GROUP (from the GAIT family) and write it to plans/ (.partial, then renamed)."""
    t0 = time.perf_counter()
    plan = search_plan(plan_rng(base_seed, group), duration_s, plan_id(base_seed, group), gait)
    path = Path(out) / "plans" / plan_name(group)
    tmp = path.with_name(path.name + ".partial")
    tmp.write_text(json.dumps(plan.as_dict(), sort_keys=True) + "\n")
    os.replace(tmp, path)
    return {"group": group, "attempts": plan.attempts, "seconds": time.perf_counter() - t0}


def read_plan(out: Path, group: int) -> KeptPlan:
    path = out / "plans" / plan_name(group)
    try:
        return KeptPlan.from_dict(json.loads(path.read_text()))
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise DatasetError(f"{path}: unreadable plan ({e}); remove it and run again to search it anew") from e


def make_one(out: str, index: int, seed: int, duration_s: float, plan: dict,
              sigmas: tuple[float, ...], hazard_probability: float) -> dict:
    t0 = time.perf_counter()
    ep = simulate_episode(seed, duration_s=duration_s, plan=KeptPlan.from_dict(plan), sigmas=sigmas,
                          hazard_probability=hazard_probability)
    write_episode(Path(out) / episode_name(index), ep)
    return {"index": index, "sigma": ep.sigma, "fall_onset_tick": ep.fall_onset_tick, "fall_cause": ep.fall_cause,
            "seconds": time.perf_counter() - t0, "plan_attempts": ep.plan_attempts}


def _make_all(out: Path, seed: int, episodes: int, duration_s: float, todo: list[int], missing_plans: list[int],
              sigmas: tuple[float, ...], hazard_probability: float, jobs: int, bar,
              gait: str = "dynamic") -> list[dict]:
    """Search the missing plans and make the TODO episodes, all in one pool of JOBS workers.

    An episode is submitted as soon as its plan exists, so the workers are not
    idle while the slowest plan searches run (one search costs several
    episodes and their costs differ by 10x).
    """
    waiting: dict[int, list[int]] = {}
    for i in todo:
        waiting.setdefault(plan_group(i, episodes), []).append(i)

    def episode_tasks(group: int) -> list[tuple]:
        plan = read_plan(out, group).as_dict()
        return [(str(out), i, episode_seed(seed, i), duration_s, plan, sigmas, hazard_probability)
                for i in waiting.pop(group, [])]

    stats: list[dict] = []
    ready = [t for g in sorted(set(waiting) - set(missing_plans)) for t in episode_tasks(g)]
    if jobs == 1:
        for g in missing_plans:
            find_plan(str(out), seed, g, duration_s, gait)
            ready += episode_tasks(g)
        for t in ready:
            stats.append(make_one(*t))
            bar.update(1)
        return stats
    with ProcessPoolExecutor(max_workers=jobs) as pool:
        pending = {pool.submit(find_plan, str(out), seed, g, duration_s, gait) for g in missing_plans}
        pending |= {pool.submit(make_one, *t) for t in ready}
        while pending:
            done, pending = wait(pending, return_when=FIRST_COMPLETED)
            for fut in done:
                row = fut.result()
                if "group" in row:
                    pending |= {pool.submit(make_one, *t) for t in episode_tasks(row["group"])}
                else:
                    stats.append(row)
                    bar.update(1)
    return stats


def cpu_seconds() -> float:
    """CPU time (user + system) of this process and its finished children."""
    me, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return me.ru_utime + me.ru_stime + kids.ru_utime + kids.ru_stime


def generate(out: Path, episodes: int, seed: int, jobs: int = 1, duration_s: float = DURATION_S,
             progress: bool = True, sigmas: tuple[float, ...] = SIGMAS,
             hazard_probability: float = HAZARD_PROBABILITY, ray_address: str | None = None,
             use_ray: bool = False, gait: str = "dynamic") -> list[dict]:
    """Make the missing plans and episodes of the data set and (re)write its manifest; returns per-episode stats.

    With USE_RAY the plan groups run as tasks on the Ray cluster at RAY_ADDRESS
    (``sim/cluster.py``; JOBS is then the cluster's affair); the files are the same.
    GAIT is the family every plan of the set is searched from (``gait.GAIT_FAMILIES``).
    """
    sigmas = tuple(float(x) for x in sigmas)
    check_args(out, episodes, seed, jobs, duration_s, sigmas, hazard_probability, gait)
    manifest_path = out / "manifest.json"
    groups = plan_groups(episodes)
    generator = {
        "name": "fall_guard.sim", "version": GENERATOR_VERSION, "robot": ROBOT_NAME, "rate_hz": RATE_HZ,
        "physics_hz": PHYSICS_HZ,
        "seed": seed, "seed_range": [episode_seed(seed, 0), episode_seed(seed, episodes - 1)],
        "episodes": episodes, "duration_s": duration_s, "sigmas": list(sigmas),
        "fall_fraction": FALL_FRACTION, "joint_names": list(JOINT_NAMES),
        "knot_ticks": KNOT_TICKS, "perturbation_scale_rad": PERTURBATION_SCALE,
        "event": {"above_sigma": BACKGROUND_SIGMA_MAX, "background_sigmas": list(BACKGROUND_SIGMAS),
                  "knots": EVENT_KNOTS, "gain": EVENT_GAIN, "start_s": list(EVENT_START_S)},
        "validation": {"draws": VALIDATION_DRAWS, "sigma": VALIDATION_SIGMA,
                       "background_sigma": VALIDATION_BACKGROUND_SIGMA, "min_progress_m": MIN_PROGRESS_M},
        "hazard_probability": hazard_probability,
        # Pushes and obstacles come with the ball: none when hazard_probability is 0 (the walking set).
        **outside_cause_probabilities(hazard_probability),
        "push": {"start_s": list(PUSH_START_S), "impulse_ns": list(PUSH_IMPULSE_NS), "duration_s": PUSH_DURATION_S},
        "obstacle": {"kinds": list(OBSTACLE_KINDS), "distance_m": {k: list(v) for k, v in OBSTACLE_DIST_M.items()}},
        "balance": {"kh": KH, "khd": KHD, "kr": KR, "krd": KRD, "limit_rad": LIMIT_RAD},
        "plan_groups": groups, "episodes_per_plan": EPISODES_PER_PLAN, "gait": gait,
    }
    if manifest_path.exists():
        try:
            old = json.loads(manifest_path.read_text()).get("generator", {})
        except (OSError, json.JSONDecodeError) as e:
            raise DatasetError(f"{manifest_path}: unreadable manifest ({e}); remove it or use another --out") from e
        old.setdefault("version", 1)  # generator 1 wrote no version
        old.setdefault("gait", "dynamic")  # a set made before the hardware gait is a dynamic one
        for key in ("version", "seed", "duration_s", "episodes", "sigmas", "hazard_probability", "gait"):
            if old.get(key, generator[key]) != generator[key]:
                raise DatasetError(f"{manifest_path}: made with {key}={old[key]}, asked {key}={generator[key]}; "
                                   "use another --out or the same arguments")
    manifest = split_names(episodes, seed)
    manifest["plans"] = {episode_name(i): plan_id(seed, plan_group(i, episodes)) for i in range(episodes)}
    manifest["generator"] = generator
    # Written first too, so an interrupted run is recognised (seed, duration) when resumed.
    _write_manifest(manifest_path, manifest)
    (out / "plans").mkdir(exist_ok=True)
    for stale in [*out.glob("*.partial"), *(out / "plans").glob("*.partial")]:
        stale.unlink()
    todo = [i for i in range(episodes) if not (out / episode_name(i)).is_file()]
    needed = sorted({plan_group(i, episodes) for i in todo})
    missing_plans = [g for g in needed if not (out / "plans" / plan_name(g)).is_file()]
    bar = tqdm(total=episodes, initial=episodes - len(todo), unit="ep", disable=not progress,
               desc=f"generating {out} ({len(missing_plans)} plans to search)", file=sys.stderr)
    if use_ray:
        from .cluster import make_all as make_all_on_ray
        stats = make_all_on_ray(out, seed, episodes, duration_s, todo, missing_plans, sigmas, hazard_probability,
                                ray_address, bar, gait)
    else:
        stats = _make_all(out, seed, episodes, duration_s, todo, missing_plans, sigmas, hazard_probability, jobs,
                          bar, gait)
    bar.close()
    _write_manifest(manifest_path, manifest)
    return sorted(stats, key=lambda s: s["index"])

