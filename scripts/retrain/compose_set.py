#!/usr/bin/env python3
"""A data set composed of the splits of others.

    compose_set.py OUT [--train SRC[:SPLIT,...]]... [--validation SRC[:SPLIT,...]]... [--test SRC[:SPLIT,...]]...

Each --train / --validation / --test names a data set directory SRC and, after a colon, which of
its splits go into that split of OUT (default: all three). OUT is a directory of symbolic links to
the recordings and a manifest.json (written as .partial, then renamed), so that `fall-guard-lab train`,
`calibrate`, `eval` and `warnings` read it like any data set. With one source the links keep the
recordings' names; with several, each is prefixed by its source's directory name (two generated
sets both hold episode_00000.mcap). An episode named twice, in one split or in two, is refused.

The retrain uses it for its held-out set (`--test heldout`: a set of its own seed and plans, a
second test set large enough to measure calibration). Run with sim/.venv/bin/python.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from subset_by_cause import write_subset  # noqa: E402

SPLITS = ("train", "validation", "test")


def source(arg: str) -> tuple[Path, tuple[str, ...]]:
    """SRC[:SPLIT,...] -> (the directory, the splits)."""
    path, _, splits = arg.partition(":")
    names = tuple(s for s in splits.split(",") if s) or SPLITS
    bad = [s for s in names if s not in SPLITS]
    if bad:
        raise argparse.ArgumentTypeError(f"{arg}: unknown split {bad[0]!r} (splits: {', '.join(SPLITS)})")
    return Path(path).resolve(), names


def compose(out: Path, wanted: dict[str, list[tuple[Path, tuple[str, ...]]]]) -> dict[str, int]:
    """Writes OUT from WANTED (split -> sources); returns the episodes per split."""
    dirs = sorted({src for sources in wanted.values() for src, _ in sources})
    manifests = {}
    for d in dirs:
        try:
            manifests[d] = json.loads((d / "manifest.json").read_text())
        except (OSError, ValueError) as e:
            raise SystemExit(f"{d}: no readable manifest.json ({e})")
    prefix = len(dirs) > 1
    entries, splits, seen, links = [], {s: [] for s in SPLITS}, {}, set()
    for split, sources in wanted.items():
        for src, src_splits in sources:
            for s in src_splits:
                for name in manifests[src].get(s, []):
                    key = (src, name)
                    if key in seen:
                        raise SystemExit(f"{src / name}: named twice (in {seen[key]} and {split})")
                    seen[key] = split
                    link = f"{src.name}_{name}" if prefix else name
                    if link in links:
                        raise SystemExit(f"{src / name}: its link {link} is another source's (rename a source directory)")
                    links.add(link)
                    entries.append((src / name, link))
                    splits[split].append(link)
    if not entries:
        raise SystemExit("the sources list no episodes")
    first = manifests[dirs[0]].get("generator", {})
    what = "; ".join(f"{split}: " + ", ".join(f"{src.name} ({'+'.join(ss)})" for src, ss in sources)
                     for split, sources in wanted.items() if sources)
    write_subset(out, entries, {k: sorted(v) for k, v in splits.items()}, what,
                 {**first, "sources": [{"dir": str(d), "seed": manifests[d].get("generator", {}).get("seed")}
                                       for d in dirs]})
    return {k: len(v) for k, v in splits.items()}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path)
    for split in SPLITS:
        ap.add_argument(f"--{split}", type=source, action="append", default=[], metavar="SRC[:SPLIT,...]")
    a = ap.parse_args()
    counts = compose(a.out, {s: getattr(a, s) for s in SPLITS})
    print(f"{a.out}: " + ", ".join(f"{n} {s}" for s, n in counts.items()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
