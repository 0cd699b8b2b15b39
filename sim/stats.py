"""Summary of a data set directory: episodes, fall rate per sigma, onset times, progress.

Data enters as the ``fall_guard.episode`` metadata of each ``.mcap`` in a
directory; leaves as a JSON summary on stdout (``python -m sim stats DIR``).
"""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

from mcap.reader import make_reader

from .recording import METADATA_NAME


def read_episode_metadata(path: Path) -> dict[str, str]:
    with open(path, "rb") as f:
        for m in make_reader(f).iter_metadata():
            if m.name == METADATA_NAME:
                return dict(m.metadata)
    raise ValueError(f"{path}: no {METADATA_NAME} metadata record")


def _spread(values: list[float], digits: int) -> dict[str, float]:
    return {"min": min(values), "max": max(values), "mean": round(sum(values) / len(values), digits)}


def summarise(directory: Path) -> dict:
    files = sorted(directory.glob("*.mcap"))
    if not files:
        raise ValueError(f"{directory}: no .mcap recordings")
    per_sigma: dict[str, list[int]] = defaultdict(lambda: [0, 0])
    onsets_s, progress = [], []
    for path in files:
        meta = read_episode_metadata(path)
        row = per_sigma[meta["sigma"]]
        row[1] += 1
        if "fall_onset_ns" in meta:
            row[0] += 1
            onsets_s.append(int(meta["fall_onset_ns"]) / 1e9)
        progress.append(float(meta.get("progress_m", "nan")))
    falls = sum(r[0] for r in per_sigma.values())
    return {
        "episodes": len(files),
        "falling": falls,
        "fall_rate": round(falls / len(files), 3),
        "per_sigma": {s: {"falling": r[0], "episodes": r[1]}
                      for s, r in sorted(per_sigma.items(), key=lambda kv: float(kv[0]))},
        "onset_s": _spread(onsets_s, 2) if onsets_s else None,
        "plan_progress_m": _spread(progress, 3),
    }
