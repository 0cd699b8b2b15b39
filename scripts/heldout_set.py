#!/usr/bin/env python3
"""A held-out data set: every episode of SET, whatever its split, as a test split.

    heldout_set.py SET OUT     writes OUT/ (symbolic links to SET's recordings and a manifest.json
                               whose test split holds all of them; train and validation empty)

SET is a data set generated with a seed no other set of the retrain uses, so that its plans are
its own (`sim generate`: a different seed gives plans no other seed's set uses): none of its
episodes, nor any plan they walk, was seen by a training, a calibration or a choice. `fall-guard
eval --data OUT --split test` then scores the networks on it, a second test set several times the
size of the training set's test split, where an ECE of 0.03 can be told from the noise floor.
Run with sim/.venv/bin/python.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from subset_by_cause import write_subset  # noqa: E402


def main() -> int:
    if len(sys.argv) != 3:
        print(__doc__, file=sys.stderr)
        return 2
    src, out = Path(sys.argv[1]).resolve(), Path(sys.argv[2])
    manifest = json.loads((src / "manifest.json").read_text())
    names = sorted(n for split in ("train", "validation", "test") for n in manifest.get(split, []))
    if not names:
        print(f"{src}: the manifest lists no episodes", file=sys.stderr)
        return 1
    write_subset(out, [(src / n, n) for n in names], {"test": names},
                 "every episode of a set of its own seed, held out", manifest.get("generator", {}))
    print(f"{out}: {len(names)} held-out episodes")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
