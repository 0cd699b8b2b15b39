"""Shared fixtures: one small generated data set per pytest run (2 episodes of 4 s)."""

from __future__ import annotations

import pytest

from sim.dataset import generate


@pytest.fixture(scope="session")
def small_dataset(tmp_path_factory):
    out = tmp_path_factory.mktemp("dataset")
    stats = generate(out, episodes=2, seed=3, jobs=1, duration_s=4.0, progress=False)
    return out, stats


@pytest.fixture(scope="session")
def kept_plan():
    """One plan kept by the search (a data set's plan group; its search is among the cheapest)."""
    import numpy as np

    from sim.episode import search_plan
    return search_plan(np.random.default_rng([78, 31, 3]), 10.0, "78:3")
