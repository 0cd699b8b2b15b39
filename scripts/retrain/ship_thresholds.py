#!/usr/bin/env python3
"""Write each shipped network's latch thresholds into a daemon config.

    ship_thresholds.py --reports DIR [--horizon-ms MS] CONFIG.toml [CONFIG.toml ...]

Reads DIR/selected.txt and DIR/ABL-thresholds.json (`fall-guard-lab warnings
--choose` on the validation split, from scripts/retrain/retrain.sh) and rewrites, in
each config, `[model].trigger` / `release` (EMP's pair: the default) and the
`[model.thresholds]` table (one `[trigger, release]` per network), and with
`--horizon-ms` the horizon the latch watches (`[model].horizon_ms`, the one
the pairs were chosen at), with `--release-hold-ms` its release hold
(`[model].release_hold_ms`). A network
for which no pair on the grid kept false alarms within the budget gets the
grid's highest trigger, as the evaluation used, and the config says so. A
network not among the selected keeps the line the config has for it.
Each file is written as FILE.partial and renamed. Standard library only.
"""

from __future__ import annotations

import argparse
import json
import os
import re
from pathlib import Path

BEGIN = "# -- per-network thresholds (scripts/retrain/ship_thresholds.py) --"
END = "# -- end of per-network thresholds --"


def chosen_pairs(reports: Path) -> dict[str, tuple[float, float, str]]:
    pairs = {}
    for line in (reports / "selected.txt").read_text().splitlines():
        if not line.strip():
            continue
        abl = line.split()[0]
        r = json.loads((reports / f"{abl}-thresholds.json").read_text())
        held = r.get("max_held_share")
        budget = f"<= {r['max_false_alarms_per_min']} false alarms / min" + (
            f" and <= {held:.0%} of walking held" if held is not None else "")
        c, note = r["chosen"], f"{budget} on validation"
        if c is None:
            c = max(r["grid"], key=lambda s: s["trigger"])
            note = f"no pair kept {note}: the grid's highest trigger"
        # Three places: the grid's top steps (0.995) are not 2-place numbers.
        pairs[abl] = (round(c["trigger"], 3), round(c["release"], 3), note)
    return pairs


def rewrite(text: str, pairs: dict[str, tuple[float, float, str]], horizon_ms: int | None = None,
            hold_ms: int | None = None) -> str:
    if horizon_ms is not None:
        text = re.sub(r"(?m)^horizon_ms = [0-9]+", f"horizon_ms = {horizon_ms}", text, count=1)
    if hold_ms is not None:
        text = re.sub(r"(?m)^release_hold_ms = [0-9]+", f"release_hold_ms = {hold_ms}", text, count=1)
    if "emp" in pairs:
        t, r, _ = pairs["emp"]
        text = re.sub(r"(?m)^trigger = [0-9.]+", f"trigger = {t}", text, count=1)
        text = re.sub(r"(?m)^release = [0-9.]+", f"release = {r}", text, count=1)
    # A network not shipped this time keeps the line it has (its file is unchanged).
    kept = {}
    if BEGIN in text:
        old = text[text.index(BEGIN):text.index(END)] if END in text else ""
        kept = {m.group(1): m.group(0) for m in re.finditer(r"(?m)^(emp|mp|ep|p) = \[.*$", old)}
    block = [BEGIN, "[model.thresholds]   # [trigger, release] of each network, chosen for it on validation"]
    for abl in ("emp", "mp", "ep", "p"):
        if abl in pairs:
            t, r, note = pairs[abl]
            block.append(f"{abl} = [{t}, {r}]".ljust(21) + f"# {note}")
        elif abl in kept:
            block.append(kept[abl])
    block.append(END)
    if BEGIN in text:
        text = re.sub(re.escape(BEGIN) + r".*?" + re.escape(END), "\n".join(block), text, flags=re.S)
    else:
        text = text.rstrip("\n") + "\n\n" + "\n".join(block) + "\n"
    return text


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reports", type=Path, required=True)
    ap.add_argument("--horizon-ms", type=int, help="the horizon the pairs were chosen at")
    ap.add_argument("--release-hold-ms", type=int, help="the release hold they were chosen with")
    ap.add_argument("configs", type=Path, nargs="+")
    a = ap.parse_args()
    pairs = chosen_pairs(a.reports)
    for path in a.configs:
        tmp = path.with_name(path.name + ".partial")
        tmp.write_text(rewrite(path.read_text(), pairs, a.horizon_ms, a.release_hold_ms))
        os.replace(tmp, path)
        print(f"{path}: " + ", ".join(f"{k} {v[0]}/{v[1]}" for k, v in pairs.items()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
