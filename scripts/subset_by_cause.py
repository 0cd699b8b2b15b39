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
`fall-guard eval` and `warnings` score one cause at a time.
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

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
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


def main() -> int:
    if len(sys.argv) != 3:
        print(__doc__, file=sys.stderr)
        return 2
    src, out = Path(sys.argv[1]).resolve(), Path(sys.argv[2])
    manifest = json.loads((src / "manifest.json").read_text())
    causes: dict[str, list[str]] = {"collision": [], "perturbation": []}
    walks, high = [], []
    for name in manifest["test"]:
        meta = read_episode_metadata(src / name)
        cause = meta.get("fall_cause")
        (causes[cause] if cause in causes else walks).append(name)
        if float(meta["sigma"]) >= 0.035:
            high.append(name)
    for cause, falls in causes.items():
        d = out / cause
        write_subset(d, [(src / n, n) for n in falls + walks], {"test": sorted(falls + walks)},
                     f"test falls caused by {cause} + test walks", manifest.get("generator", {}))
        print(f"{d}: {len(falls)} {cause} falls, {len(walks)} walks")
    d = out / "high-sigma"
    write_subset(d, [(src / n, n) for n in high], {"test": sorted(high)},
                 "test episodes at sigma >= 0.035", manifest.get("generator", {}))
    print(f"{d}: {len(high)} episodes at sigma >= 0.035")
    falls, walks = [], []
    for name in manifest["validation"]:
        cause = read_episode_metadata(src / name).get("fall_cause")
        if cause == "collision":
            falls.append(name)
        elif cause is None:
            walks.append(name)
    d = out / "validation-collision"
    write_subset(d, [(src / n, n) for n in falls + walks], {"test": sorted(falls + walks)},
                 "validation falls caused by collision + validation walks", manifest.get("generator", {}))
    print(f"{d}: {len(falls)} collision falls, {len(walks)} walks (validation)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
