"""Shared plans: a plan serves several episodes of one split, never two splits or two seeds."""

from __future__ import annotations

import json

import numpy as np

from sim.dataset import (EPISODES_PER_PLAN, episode_name, generate, plan_group, plan_groups, plan_id, plan_rng,
                         split_names)
from sim.gait import PARAM_RANGES, PROPOSAL_RANGES, GaitParams


def test_no_plan_is_in_two_splits():
    for n in (1, 2, 7, 10, 25, 100, 2000, 2003):
        splits = split_names(n, base_seed=1)
        names = [x for part in splits.values() for x in part]
        assert sorted(names) == [episode_name(i) for i in range(n)], n
        group_split = {}
        for split, part in splits.items():
            for name in part:
                g = plan_group(int(name[8:13]), n)
                assert group_split.setdefault(g, split) == split, (n, g)
        if n >= 10:
            assert all(splits.values()), (n, {k: len(v) for k, v in splits.items()})
    assert plan_groups(2000) == 200
    sizes = np.bincount([plan_group(i, 2000) for i in range(2000)])
    assert sizes.min() == sizes.max() == EPISODES_PER_PLAN
    # 160 / 20 / 20 plans.
    assert [len(v) for v in split_names(2000, 1).values()] == [1600, 200, 200]


def test_another_seed_searches_other_plans():
    # The search's candidates come from the stream [seed, PLAN_STREAM, group]:
    # no two (seed, group) share a candidate, so no two seeds share a plan.
    seen = {}
    for seed in (1, 2, 3, 41):
        for g in range(200):
            rng = plan_rng(seed, g)
            for attempt in range(3):
                key = tuple(GaitParams.propose(rng).as_dict().values())
                assert key not in seen, (seed, g, attempt, seen.get(key))
                seen[key] = (seed, g, attempt)
    assert plan_id(1, 5) != plan_id(2, 5)


def test_the_proposal_lies_inside_the_gait_family():
    for k, (lo, hi) in PROPOSAL_RANGES.items():
        plo, phi = PARAM_RANGES[k]
        assert plo <= lo < hi <= phi, k


def test_generated_set_shares_plans_within_a_split(tmp_path):
    out = tmp_path / "d"
    generate(out, episodes=12, seed=9, jobs=2, duration_s=1.5, progress=False)
    manifest = json.loads((out / "manifest.json").read_text())
    plans = manifest["plans"]
    assert len(set(plans.values())) == plan_groups(12) == 10
    split_of = {n: s for s in ("train", "validation", "test") for n in manifest[s]}
    by_plan = {}
    for name, pid in plans.items():
        by_plan.setdefault(pid, set()).add(split_of[name])
    assert all(len(s) == 1 for s in by_plan.values())
    # Every episode of a plan follows the same gait, each with its own room and perturbation.
    from sim.stats import read_episode_metadata
    metas = {n: read_episode_metadata(out / n) for n in plans}
    shared = [n for n in plans if plans[n] == plans[episode_name(0)]]
    assert len(shared) == 2
    a, b = (metas[n] for n in shared)
    assert a["gait"] == b["gait"] and a["plan_id"] == b["plan_id"] == plan_id(9, 0)
    assert a["scene"] != b["scene"] and a["seed"] != b["seed"]
    assert len(list((out / "plans").glob("plan_*.json"))) == 10
