#!/usr/bin/env bash
# The soak: the daemon replaying at maximum speed for a long
# time (bench-daemon), with its memory sampled from outside once a minute
# (VmRSS, and its anonymous and file-backed parts, from /proc/PID/status)
# beside the load average, so that growth can be told from warm-up and from
# the page cache. A benchmark, not a test: run it on an otherwise idle
# machine. Figures: docs/performance.md, "The 1-hour soak".
#   scripts/measure/soak.sh [SECONDS] [OUT_PREFIX] [bench-daemon options, e.g. --config C]
# Writes OUT_PREFIX.json (bench-daemon's report) and OUT_PREFIX-rss-per-minute.txt.
set -euo pipefail
cd "$(dirname "$0")/../.."
duration="${1:-3600}"
prefix="${2:-out/soak-${duration}s}"
shift $(($# < 2 ? $# : 2))
bin="${FALL_GUARD_BIN:-${CARGO_TARGET_DIR:-target}/release/fall-guard}"
mkdir -p "$(dirname "$prefix")"
log="$prefix-rss-per-minute.txt"
"$bin" bench-daemon --duration-s "$duration" --json "$prefix.json" "$@" &
pid=$!
echo "pid $pid start $(date +%H:%M:%S) binary $bin" >"$log"
# One read of /proc/PID/status per sample, so the three figures agree.
field() { sed -n "s/^$1:[[:space:]]*\([0-9]*\) kB/\1/p" <<<"$status"; }
while kill -0 "$pid" 2>/dev/null; do
  status=$(cat "/proc/$pid/status" 2>/dev/null || true)
  rss=$(field VmRSS) anon=$(field RssAnon) file=$(field RssFile)
  [ -n "$rss" ] && echo "$(date +%H:%M:%S) VmRSS $rss kB anon $anon kB file $file kB load $(cut -d' ' -f1-3 /proc/loadavg)" >>"$log"
  for _ in $(seq 60); do kill -0 "$pid" 2>/dev/null || break; sleep 1; done
done
wait "$pid"
echo "end $(date +%H:%M:%S)" >>"$log"
