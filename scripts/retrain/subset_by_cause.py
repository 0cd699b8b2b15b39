#!/usr/bin/env python3
"""Data sets of one fall cause, and of the high sigmas, from SET's test split.

    subset_by_cause.py SET OUT     writes OUT/collision/, OUT/perturbation/, OUT/high-sigma/
                                   and OUT/validation-collision/

collision/ and perturbation/ hold the test falls of that cause with every
non-falling test episode; high-sigma/ holds every test episode at a
perturbation sigma >= 0.035 (falling or not), so that a network's figures
there say what it sees within one level of perturbation, where the joints'
swell does not already tell the sigma.

Each is a directory of symbolic links to SET's recordings with a manifest.json
whose test split holds those episodes (train and validation empty), so that
`fall-guard-lab eval` and `warnings` score one cause at a time.
validation-collision/ is the same for the validation split's collision falls
and non-falling episodes: the camera's case where choices about the vision
encoder may be made (the test split's never are). The cause is the
recording's `fall_cause` metadata (sim/README.md). Run with sim/.venv/bin/python.
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from sim.stats import read_episode_metadata  # noqa: E402


def write_subset(out: Path, entries: list[tuple[Path, str]], splits: dict[str, list[str]], subset: str,
                 generator: dict | None = None) -> None:
    """OUT/: a symbolic link NAME -> TARGET per entry and a manifest.json with SPLITS
    (written as .partial, then renamed); `generator.subset` says what the set is."""
    out.mkdir(parents=True, exist_ok=True)
    for target, name in entries:
        link = out / name
        if not link.exists():
            os.symlink(target, link)
    manifest = {"train": [], "validation": [], "test": [], **splits,
                "generator": {**(generator or {}), "subset": subset}}
    tmp = out / "manifest.json.partial"
    tmp.write_text(json.dumps(manifest, indent=2) + "\n")
    os.replace(tmp, out / "manifest.json")


def by_cause(src: Path, names: list[str]) -> tuple[dict[str, list[str]], list[str], list[str]]:
    """NAMES split by fall cause (collision, perturbation), the walks (no fall) and
    those at sigma >= 0.035, from each recording's metadata."""
    causes: dict[str, list[str]] = {"collision": [], "perturbation": []}
    walks, high = [], []
    for name in names:
        meta = read_episode_metadata(src / name)
        cause = meta.get("fall_cause")
        (causes[cause] if cause in causes else walks).append(name)
        if float(meta["sigma"]) >= 0.035:
            high.append(name)
    return causes, walks, high


def main() -> int:
    if len(sys.argv) != 3:
        print(__doc__, file=sys.stderr)
        return 2
    src, out = Path(sys.argv[1]).resolve(), Path(sys.argv[2])
    manifest = json.loads((src / "manifest.json").read_text())
    generator = manifest.get("generator", {})

    def subset(d: Path, names: list[str], what: str) -> None:
        write_subset(d, [(src / n, n) for n in names], {"test": sorted(names)}, what, generator)

    causes, walks, high = by_cause(src, manifest["test"])
    for cause, falls in causes.items():
        subset(out / cause, falls + walks, f"test falls caused by {cause} + test walks")
        print(f"{out / cause}: {len(falls)} {cause} falls, {len(walks)} walks")
    subset(out / "high-sigma", high, "test episodes at sigma >= 0.035")
    print(f"{out / 'high-sigma'}: {len(high)} episodes at sigma >= 0.035")
    causes, walks, _ = by_cause(src, manifest["validation"])
    falls = causes["collision"]
    subset(out / "validation-collision", falls + walks, "validation falls caused by collision + validation walks")
    print(f"{out / 'validation-collision'}: {len(falls)} collision falls, {len(walks)} walks (validation)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
