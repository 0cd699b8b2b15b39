#!/usr/bin/env python3
"""The validation set the latch thresholds are chosen on: falls, and walking.

    choice_set.py SET WALK OUT

Writes OUT/ (symbolic links and a manifest.json whose validation split holds
them; train and test empty): every falling episode of SET's validation split,
the non-falling validation episodes of SET at sigma <= 0.01 (walking), and
the validation split of the walking set WALK (`sim generate --sigmas
0.005,0.01 --ball-probability 0`). `fall-guard-lab warnings --split validation
--choose` on it bounds false alarms per minute of walking, as the daemon's
figure is defined, not of the high-sigma episodes that come close to a
fall and do not quite (an alarm there is no false alarm). The test figure
is taken on SET's test split and WALK's train and test splits, never on
these. Run with sim/.venv/bin/python.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from sim.stats import read_episode_metadata  # noqa: E402
from subset_by_cause import write_subset  # noqa: E402  (this script's folder is on sys.path)


def main() -> int:
    if len(sys.argv) != 4:
        print(__doc__, file=sys.stderr)
        return 2
    src, walk, out = Path(sys.argv[1]).resolve(), Path(sys.argv[2]).resolve(), Path(sys.argv[3])
    chosen: list[tuple[Path, str]] = []
    falls = walks = 0
    for name in json.loads((src / "manifest.json").read_text())["validation"]:
        meta = read_episode_metadata(src / name)
        falling = meta.get("fall_onset_ns") is not None
        if falling or float(meta["sigma"]) <= 0.01:
            chosen.append((src / name, name))
            falls += falling
            walks += not falling
    walk_names = json.loads((walk / "manifest.json").read_text())["validation"]
    chosen += [(walk / n, f"walk_{n}") for n in walk_names]
    write_subset(out, chosen, {"validation": sorted(n for _, n in chosen)},
                 "validation falls, validation walks at sigma <= 0.01, and the walking set's validation split")
    print(f"{out}: {falls} falls, {walks} walks of {src.name}, {len(walk_names)} walks of {walk.name}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
