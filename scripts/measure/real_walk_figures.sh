#!/usr/bin/env bash
# The shipped networks on the real Poppy walk (tests/fixtures/real/, docs/real-recordings.md):
# for each models/*.bpk, the share of valid ticks with fall_imminent asserted and the highest
# probability at the latch's horizon ([model].horizon_ms of the fixture's config). The walk
# did not fall, so every assertion on a valid tick is a false alarm. Prints a Markdown table
# (models/README.md, "On a real Poppy walk").
#
# - every network: `fall-guard-lab eval --recording --per-tick-out` (the daemon's windows, offline,
#   the input projection in int8 as the daemon holds it), with the config's latch (each network's trigger,
#   release, release hold) applied here; EMP and EP need the camera, which the walk has not: reported as such;
# - the daemon as deployed: `fall-guard replay --config tests/fixtures/real/replay.toml`
#   (no camera: it runs MP), its own printed latch counted.
#
# Usage: cargo build --release --workspace && bash scripts/measure/real_walk_figures.sh
#        FALL_GUARD=path/to/fall-guard FALL_GUARD_LAB=path/to/fall-guard-lab bash scripts/measure/real_walk_figures.sh
set -euo pipefail
cd "$(dirname "$0")/../.."
BIN=${FALL_GUARD:-target/release/fall-guard}
LAB=${FALL_GUARD_LAB:-target/release/fall-guard-lab}
REC=tests/fixtures/real/poppy_muffin_walk.mcap
CONFIG=tests/fixtures/real/replay.toml
for b in "$BIN" "$LAB"; do
  [ -x "$b" ] || { echo "no $b: run cargo build --release --workspace first (or set FALL_GUARD, FALL_GUARD_LAB)" >&2; exit 1; }
done
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT

for model in models/*.bpk; do
  name=$(basename "$model" .bpk)
  if ! "$LAB" eval --model "$model" --recording "$REC" --per-tick-out "$tmp/$name.jsonl" \
      --projection int8 > "$tmp/$name.log" 2>&1; then
    grep -m1 -o 'no messages on topic [^ ]*, which is needed' "$tmp/$name.log" > "$tmp/$name.why" \
      || tail -n 1 "$tmp/$name.log" > "$tmp/$name.why"
  fi
done
"$BIN" replay --config "$CONFIG" --max-speed > "$tmp/replay.txt" 2> "$tmp/replay.log"

python3 - "$tmp" "$CONFIG" models/*.bpk <<'EOF'
import json, math, re, sys, tomllib
from pathlib import Path

sys.path.insert(0, "scripts/retrain")
from model_meta import read_meta

tmp, config_path, models = Path(sys.argv[1]), sys.argv[2], sys.argv[3:]
model_cfg = tomllib.loads(Path(config_path).read_text())["model"]
horizon_ms = model_cfg["horizon_ms"]
per_network = model_cfg.get("thresholds", {})


def pair(ablation):
    """The network's own (trigger, release) from [model.thresholds], else [model]'s."""
    own = per_network.get(ablation.lower())
    return tuple(own) if own else (model_cfg["trigger"], model_cfg["release"])


def hold_ticks(rate_hz):
    """[model].release_hold_ms in ticks at `rate_hz`, rounded up (outputs::latch::release_hold_ticks)."""
    return max(1, math.ceil(model_cfg.get("release_hold_ms", 0) * rate_hz / 1000 - 1e-9))


def latch(probabilities, trigger, release, hold):
    """The daemon's latch over valid ticks: asserted until valid forecasts have been below release
    for `hold` ticks in a row."""
    on, asserted, triggers, below = True, 0, 0, 0
    for p in probabilities:
        below = below + 1 if on and p < release else 0
        if not on and p >= trigger:
            on, triggers = True, triggers + 1
        elif on and below >= hold:
            on, below = False, 0
        asserted += on
    return asserted, triggers


def row(label, ablation, rate_hz, probabilities, note=""):
    trigger, release = pair(ablation)
    asserted, triggers = latch(probabilities, trigger, release, hold_ticks(rate_hz))
    n = len(probabilities)
    return (f"| {label} | {ablation} | {n} | {asserted} ({100 * asserted / n:.1f}%) | {triggers} | "
            f"{max(probabilities):.3f} | {100 * sum(p >= trigger for p in probabilities) / n:.1f}% | "
            f"{trigger} / {release} |{note}")


print(f"Real walk `tests/fixtures/real/poppy_muffin_walk.mcap` (35.6 s, no fall); latch at {horizon_ms} ms with "
      f"each network's thresholds ({config_path}); valid ticks only (the first 2 s fill the window).\n")
print(f"| network | ablation | valid ticks | fall_imminent asserted | latch triggers | highest p at {horizon_ms} ms "
      f"| ticks with p >= trigger | trigger / release |")
print("| --- | --- | --- | --- | --- | --- | --- | --- |")
for model in models:
    name = Path(model).stem
    meta = read_meta(model)
    ms = [round(1000 * t / meta["rate_hz"]) for t in meta["horizons_ticks"]]
    if horizon_ms not in ms:
        print(f"| `{model}` | {meta['ablation']} | - | - | - | - | - | - | no {horizon_ms} ms horizon ({ms})")
        continue
    k = ms.index(horizon_ms)
    out = tmp / f"{name}.jsonl"
    if not out.exists():
        why = (tmp / f"{name}.why").read_text().strip()
        print(f"| `{model}` | {meta['ablation']} | could not run: {why} | | | | | |")
        continue
    ps = [json.loads(line)["probabilities"][k] for line in out.read_text().splitlines()]
    print(row(f"`{model}` (eval)", meta["ablation"], meta["rate_hz"], ps))

lines = [l for l in (tmp / "replay.txt").read_text().splitlines() if l.startswith("tick ")]
valid = [l for l in lines if " valid p=[" in l]
active = sorted({l.split()[3] for l in valid})
mp_meta = read_meta("models/mp.bpk")
k = [round(1000 * t / mp_meta["rate_hz"]) for t in mp_meta["horizons_ticks"]].index(horizon_ms)
ps = [float(re.search(r"p=\[([^\]]*)\]", l).group(1).split()[k]) for l in valid]
asserted = sum(l.endswith("imminent=true") for l in valid)
triggers = sum(1 for a, b in zip(valid, valid[1:]) if b.endswith("true") and a.endswith("false"))
trigger, release = pair("MP")
print(f"| daemon (`fall-guard replay --config {config_path}`) | {'/'.join(active)} | {len(valid)} | "
      f"{asserted} ({100 * asserted / len(valid):.1f}%) | {triggers} | {max(ps):.3f} | "
      f"{100 * sum(p >= trigger for p in ps) / len(ps):.1f}% | {trigger} / {release} |")
print(f"\nAll ticks of the replay: {len(lines)}, fall_imminent asserted on "
      f"{sum(l.endswith('imminent=true') for l in lines)} (the window filling included).")
EOF
