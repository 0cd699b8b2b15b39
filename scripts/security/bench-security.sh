#!/usr/bin/env bash
# The CPU cost of DDS Security per tick: `fall-guard bench-daemon --speed 1`
# (the bundled recording at real time, 30 ticks a second, publishing on
# ROS 2) with one listener of its outputs (examples/sros2_listener.rs:
# forecast, fall_imminent, /diagnostics), open and then secured with a
# keystore from scripts/security/sros2-keystore.sh, back to back, PAIRS times. The
# daemon's CPU time (utime + stime, /proc/PID/stat) is read once a second;
# the first 5 s (start, discovery, the handshake) are left out.
#
# Reports per run: CPU ms per tick over the steady part (total / ticks),
# the median and p99 of the per-second windows (each window's CPU / 30),
# bench-daemon's sensor-to-publish latency p50 / p99, and what the listener
# received (both modes must deliver). All traffic on 127.0.0.1.
#
# Usage: scripts/security/bench-security.sh [--duration-s 60] [--pairs 2] [--out DIR]
# Builds: cargo build --release --features security --bin fall-guard
# --example sros2_listener (both modes run that one binary).
set -euo pipefail
cd "$(dirname "$0")/../.."

duration=60 pairs=2 out=""
while [ $# -gt 0 ]; do
  case "$1" in
    --duration-s) duration=$2; shift 2 ;;
    --pairs) pairs=$2; shift 2 ;;
    --out) out=$2; shift 2 ;;
    *) sed -n '/^# Usage:/p' "$0" >&2; exit 2 ;;
  esac
done
[ -n "$out" ] || out=$(mktemp -d)
mkdir -p "$out"

cargo build --release --features security --bin fall-guard --example sros2_listener
target="${CARGO_TARGET_DIR:-target}/release"
bin="$target/fall-guard" listener="$target/examples/sros2_listener"

keystore="$out/keystore"
rm -rf "$keystore"
bash scripts/security/sros2-keystore.sh fall-guard "$keystore" >/dev/null

clk=$(getconf CLK_TCK)
domain=$((100 + $$ % 100))
export ROS_DOMAIN_ID=$domain ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
unset ROS_LOCALHOST_ONLY ROS_SECURITY_ENCLAVE_OVERRIDE RUST_LOG

cpu_ticks() { awk '{print $14 + $15}' "/proc/$1/stat" 2>/dev/null || echo ""; }

run() { # $1 = open|secured, $2 = index
  local mode=$1 i=$2 tag="$1-$2"
  if [ "$mode" = secured ]; then
    export ROS_SECURITY_ENABLE=true ROS_SECURITY_STRATEGY=Enforce ROS_SECURITY_KEYSTORE="$keystore"
  else
    unset ROS_SECURITY_ENABLE ROS_SECURITY_STRATEGY ROS_SECURITY_KEYSTORE
  fi
  "$listener" $((duration + 20)) > "$out/$tag.listener.txt" 2>&1 &
  local lpid=$!
  sleep 2
  "$bin" bench-daemon --speed 1 --duration-s "$duration" --json "$out/$tag.json" \
    > "$out/$tag.stdout" 2> "$out/$tag.stderr" &
  local pid=$!
  : > "$out/$tag.cpu"
  while kill -0 "$pid" 2>/dev/null; do
    local c
    c=$(cpu_ticks "$pid")
    [ -n "$c" ] && echo "$(date +%s.%N) $c" >> "$out/$tag.cpu"
    sleep 1
  done
  wait "$pid" || { echo "bench-daemon ($mode) failed: $out/$tag.stderr" >&2; kill "$lpid" 2>/dev/null; exit 1; }
  kill "$lpid" 2>/dev/null || true
  wait "$lpid" 2>/dev/null || true
}

echo "== load before: $(cut -d' ' -f1-3 /proc/loadavg) (1, 5, 15 min), $(nproc) cores"
for i in $(seq 1 "$pairs"); do
  run open "$i"
  run secured "$i"
done
echo "== load after: $(cut -d' ' -f1-3 /proc/loadavg)"

python3 - "$out" "$clk" "$pairs" <<'EOF'
import json, sys, statistics
out, clk, pairs = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
rows = {}
for mode in ("open", "secured"):
    for i in range(1, pairs + 1):
        tag = f"{mode}-{i}"
        samples = [tuple(map(float, l.split())) for l in open(f"{out}/{tag}.cpu") if l.strip()]
        t0 = samples[0][0]
        steady = [s for s in samples if s[0] - t0 >= 5.0]
        windows = []
        for a, b in zip(steady, steady[1:]):
            dt = b[0] - a[0]
            windows.append((b[1] - a[1]) / clk * 1000.0 / (30.0 * dt))
        span = steady[-1][0] - steady[0][0]
        total = (steady[-1][1] - steady[0][1]) / clk * 1000.0 / (30.0 * span)
        windows.sort()
        p99 = windows[min(len(windows) - 1, int(0.99 * len(windows)))]
        rep = json.load(open(f"{out}/{tag}.json"))
        heard = [l for l in open(f"{out}/{tag}.listener.txt") if l.startswith("t=")]
        last = heard[-1].strip() if heard else "(listener printed nothing)"
        rows[tag] = (total, statistics.median(windows), p99, rep)
        print(f"{tag:10} cpu/tick {total:6.3f} ms (windows median {statistics.median(windows):6.3f}, p99 {p99:6.3f}) "
              f"publish p50 {rep['publish_latency_p50_ms']:.2f} p99 {rep['publish_latency_p99_ms']:.2f} ms, "
              f"overruns {rep['overruns']}, ticks {rep['ticks']} | listener: {last}")
mean = lambda mode: statistics.mean(rows[f"{mode}-{i}"][0] for i in range(1, pairs + 1))
o, s = mean("open"), mean("secured")
print(f"== mean cpu/tick: open {o:.3f} ms, secured {s:.3f} ms: +{s - o:.3f} ms ({(s / o - 1) * 100:+.1f}%)")
EOF
echo "== files: $out"
