#!/usr/bin/env python3
"""Compares per-tick forecasts of two builds (`fall-guard-lab eval --recording
R --per-tick-out F`): DIR/<model>-aarch64.jsonl against DIR/<model>-native.jsonl.

Fails when the files differ in ticks or stamps, when a probability is NaN
in one and not the other, or when |p_aarch64 - p_native| exceeds the
tolerance. Prints the largest difference per model."""

import argparse
import json
import math
import sys
from pathlib import Path


def read(path: Path) -> list[dict]:
    with path.open() as f:
        return [json.loads(line) for line in f if line.strip()]


def compare(a: list[dict], b: list[dict]) -> tuple[float, int, list[str]]:
    errors = []
    if len(a) != len(b):
        errors.append(f"{len(a)} forecasts against {len(b)}")
    worst, worst_tick = 0.0, -1
    for ra, rb in zip(a, b):
        if (ra["tick"], ra["stamp_ns"]) != (rb["tick"], rb["stamp_ns"]):
            errors.append(f"tick {ra['tick']} at {ra['stamp_ns']} against tick {rb['tick']} at {rb['stamp_ns']}")
            break
        pa, pb = ra["probabilities"], rb["probabilities"]
        if len(pa) != len(pb):
            errors.append(f"tick {ra['tick']}: {len(pa)} horizons against {len(pb)}")
            break
        for x, y in zip(pa, pb):
            # serde_json writes a NaN as null.
            if x is None or y is None:
                if (x is None) != (y is None):
                    errors.append(f"tick {ra['tick']}: {x} against {y}")
                continue
            d = abs(x - y)
            if math.isnan(d) or d > worst:
                worst, worst_tick = d, ra["tick"]
    return worst, worst_tick, errors


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--tolerance", type=float, required=True)
    ap.add_argument("dir", type=Path)
    ap.add_argument("models", nargs="+")
    args = ap.parse_args()
    failed = False
    for m in args.models:
        a = read(args.dir / f"{m}-aarch64.jsonl")
        b = read(args.dir / f"{m}-native.jsonl")
        worst, tick, errors = compare(a, b)
        ok = not errors and worst <= args.tolerance and len(a) > 0
        failed |= not ok
        print(
            f"{m:>3}: {len(a)} ticks x {len(a[0]['probabilities']) if a else 0} horizons, "
            f"max |aarch64 - native| = {worst:.3g} (tick {tick}), "
            f"tolerance {args.tolerance:g}: {'ok' if ok else 'FAILED'}"
        )
        for e in errors[:5]:
            print(f"     {e}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
