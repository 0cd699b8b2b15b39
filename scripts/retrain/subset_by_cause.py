#!/usr/bin/env python3
"""Data sets of one fall cause, and of the high sigmas, from SET's test split.

    subset_by_cause.py SET OUT     writes OUT/CAUSE/ for every cause of a test fall, OUT/high-sigma/,
                                   OUT/validation-collision/ and OUT/causes.json

The causes are the recordings' own (`fall_cause` metadata, sim/README.md):
generator 6 writes `perturbation`, `collision` (the ball or furniture),
`push` and `obstacle`, generator 5 the first two; a fall that names no cause
is `unknown`. OUT/CAUSE/ holds the test falls of that cause with every
non-falling test episode; high-sigma/ holds every test episode at a
perturbation sigma >= 0.035 (falling or not), so that a network's figures
there say what it sees within one level of perturbation, where the joints'
swell does not already tell the sigma.

Each is a directory of symbolic links to SET's recordings with a manifest.json
whose test split holds those episodes (train and validation empty), so that
`fall-guard-lab eval` and `warnings` score one cause at a time.
validation-collision/ is the same for the validation split's collision falls
and non-falling episodes: the camera's case where choices about the vision
encoder may be made (the test split's never are).

causes.json describes the test split's falls by cause (most falls first):
per cause its falls, share of the test falls, the time from the cause to the
onset (`cause_ns`: a push, the first touch of the ball, furniture or the
obstacle) and, for perturbation falls, from the event's first knot
(`event_ns`) to the onset, each as min / p10 / median / p90 / max / mean in
s, and how many of the timed falls had their cause at least 0.5 s before the
onset (the lead a warning needs: a fall caused later can only be warned that
early by a latch already asserted before its cause). `reports.py causes OUT`
lists the causes. Run with sim/.venv/bin/python.
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from sim.stats import _spread as spread  # noqa: E402  (the spread `sim stats` writes)
from sim.stats import read_episode_metadata  # noqa: E402


def write_subset(out: Path, entries: list[tuple[Path, str]], splits: dict[str, list[str]], subset: str,
                 generator: dict | None = None) -> None:
    """OUT/: a symbolic link NAME -> TARGET per entry and a manifest.json with SPLITS
    (written as .partial, then renamed; left as it is when it says the same, so that what was
    made from it stays newer); `generator.subset` says what the set is."""
    out.mkdir(parents=True, exist_ok=True)
    for target, name in entries:
        link = out / name
        if not link.exists():
            os.symlink(target, link)
    manifest = {"train": [], "validation": [], "test": [], **splits,
                "generator": {**(generator or {}), "subset": subset}}
    text = json.dumps(manifest, indent=2) + "\n"
    if (out / "manifest.json").is_file() and (out / "manifest.json").read_text() == text:
        return
    tmp = out / "manifest.json.partial"
    tmp.write_text(text)
    os.replace(tmp, out / "manifest.json")


#: The lead a warning needs for a safety node to brace in time, s (`fall-guard-lab warnings`).
EARLY_LEAD_S = 0.5
#: What a fall whose recording names no cause is filed under.
UNKNOWN = "unknown"
#: The other subsets OUT holds, which no cause may be named as.
OTHER_SUBSETS = ("high-sigma", "validation-collision")


def episode_row(src: Path, name: str) -> dict:
    """What the subsets need of one recording: its fall cause (None: no fall), the onset, the
    cause's and the event's times (ns; None where the recording has none) and its sigma."""
    meta = read_episode_metadata(src / name)

    def ns(key: str) -> int | None:
        return int(meta[key]) if meta.get(key) else None

    onset = ns("fall_onset_ns")
    cause = (meta.get("fall_cause") or UNKNOWN) if onset is not None else None
    if cause is not None and (cause in OTHER_SUBSETS or not cause.replace("-", "").replace("_", "").isalnum()):
        raise SystemExit(f"{src / name}: fall cause {cause!r} cannot name a subset directory")
    return {"name": name, "cause": cause, "onset_ns": onset, "cause_ns": ns("cause_ns"),
            "event_ns": ns("event_ns"), "sigma": float(meta["sigma"])}


def by_cause(rows: list[dict]) -> tuple[dict[str, list[str]], list[str], list[str]]:
    """ROWS (`episode_row`) split by fall cause (every cause they name, by name), the walks
    (no fall) and those at sigma >= 0.035."""
    causes: dict[str, list[str]] = {}
    walks, high = [], []
    for r in rows:
        (walks if r["cause"] is None else causes.setdefault(r["cause"], [])).append(r["name"])
        if r["sigma"] >= 0.035:
            high.append(r["name"])
    return dict(sorted(causes.items())), walks, high


def cause_stats(rows: list[dict], split: str) -> dict:
    """The falls of ROWS by cause, most falls first (the module's docstring: causes.json)."""
    falls = [r for r in rows if r["cause"] is not None]
    counts: dict[str, int] = {}
    for r in falls:
        counts[r["cause"]] = counts.get(r["cause"], 0) + 1
    causes = {}
    for cause in sorted(counts, key=lambda c: (-counts[c], c)):
        mine = [r for r in falls if r["cause"] == cause]
        from_cause = [(r["onset_ns"] - r["cause_ns"]) / 1e9 for r in mine if r["cause_ns"] is not None]
        # A perturbation fall has no outside cause: its event's first knot (event episodes only)
        # is when the plan began to throw the robot over, when the fall followed it.
        from_event = [(r["onset_ns"] - r["event_ns"]) / 1e9 for r in mine
                      if cause == "perturbation" and r["event_ns"] is not None and r["onset_ns"] >= r["event_ns"]]
        timed = from_cause or from_event
        causes[cause] = {
            "falls": len(mine), "share_of_falls": round(len(mine) / len(falls), 3),
            "cause_to_onset_s": spread(from_cause, 2), "event_to_onset_s": spread(from_event, 2),
            "timed_falls": len(timed), "caused_0_5s_before_onset": sum(t >= EARLY_LEAD_S for t in timed),
        }
    return {"split": split, "episodes": len(rows), "falls": len(falls), "walks": len(rows) - len(falls),
            "early_lead_s": EARLY_LEAD_S, "causes": causes}


def main() -> int:
    if len(sys.argv) != 3:
        print(__doc__, file=sys.stderr)
        return 2
    src, out = Path(sys.argv[1]).resolve(), Path(sys.argv[2])
    manifest = json.loads((src / "manifest.json").read_text())
    generator = manifest.get("generator", {})

    def subset(d: Path, names: list[str], what: str) -> None:
        write_subset(d, [(src / n, n) for n in names], {"test": sorted(names)}, what, generator)

    rows = [episode_row(src, n) for n in manifest["test"]]
    causes, walks, high = by_cause(rows)
    for cause, falls in causes.items():
        subset(out / cause, falls + walks, f"test falls caused by {cause} + test walks")
        print(f"{out / cause}: {len(falls)} {cause} falls, {len(walks)} walks")
    subset(out / "high-sigma", high, "test episodes at sigma >= 0.035")
    print(f"{out / 'high-sigma'}: {len(high)} episodes at sigma >= 0.035")
    tmp = out / "causes.json.partial"
    tmp.write_text(json.dumps(cause_stats(rows, "test"), indent=2) + "\n")
    os.replace(tmp, out / "causes.json")
    print(f"{out / 'causes.json'}: test falls by cause ({', '.join(causes) or 'no falls'})")
    causes, walks, _ = by_cause([episode_row(src, n) for n in manifest["validation"]])
    falls = causes.get("collision", [])
    subset(out / "validation-collision", falls + walks, "validation falls caused by collision + validation walks")
    print(f"{out / 'validation-collision'}: {len(falls)} collision falls, {len(walks)} walks (validation)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
