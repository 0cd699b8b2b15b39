#!/usr/bin/env bash
# A slow core, emulated: runs a command on one CPU under a CFS bandwidth
# quota (cgroup v2 `cpu.max` or v1 `cpu.cfs_quota_us`), so that it gets
# PERCENT of that core in every period: 1 ms of every 4 ms at 25%, of every
# 10 ms at 10% (the kernel's smallest quota is 1 ms). A core PERCENT as
# fast, to the nearest period: the command's instructions are the same,
# each millisecond of work takes 100/PERCENT as long in wall time, and a
# burst of work waits at most one period for its share. Not a real slow core (its caches and
# memory are this machine's); what it shows is how the daemon behaves when
# each tick costs that many times more. A benchmark, not a test: it needs
# root (to make the cgroup) and an otherwise idle machine. Figures:
# docs/performance.md, "On an emulated slow core".
#
#   scripts/measure/slow-core.sh PERCENT [--then SECONDS PERCENT2] -- COMMAND...
#
# `--then S P2` changes the quota to P2 percent S seconds after the start
# (the load lifted or added while the daemon runs). CPU: SLOW_CORE_CPU
# (default the last one). The cgroup is removed when the command ends.
set -euo pipefail
usage() { echo "usage: $0 PERCENT [--then SECONDS PERCENT2] -- COMMAND..." >&2; exit 2; }
[ $# -ge 3 ] || usage
percent="$1"
shift
then_s="" then_pct=""
if [ "$1" = "--then" ]; then
  [ $# -ge 4 ] || usage
  then_s="$2" then_pct="$3"
  shift 3
fi
[ "$1" = "--" ] || usage
shift
# The shortest period whose quota is at least the kernel's 1 ms, for the
# lower of the two percentages.
low="$percent"
[ -n "$then_pct" ] && [ "$then_pct" -lt "$low" ] && low="$then_pct"
[ "$low" -ge 1 ] && [ "$low" -le 100 ] || { echo "PERCENT must be 1..100" >&2; exit 2; }
period_us=$(( (100000 + low - 1) / low ))
[ "$period_us" -lt 2000 ] && period_us=2000
cpu="${SLOW_CORE_CPU:-$(($(nproc) - 1))}"
name="fall-guard-slow-core-$$"

if [ -f /sys/fs/cgroup/cgroup.controllers ] && grep -qw cpu /sys/fs/cgroup/cgroup.controllers; then
  dir="/sys/fs/cgroup/$name"
  set_quota() { echo "$(($1 * period_us / 100)) $period_us" >"$dir/cpu.max"; }
  procs="$dir/cgroup.procs"
elif [ -d /sys/fs/cgroup/cpu ]; then
  dir="/sys/fs/cgroup/cpu/$name"
  set_quota() { echo "$(($1 * period_us / 100))" >"$dir/cpu.cfs_quota_us"; }
  procs="$dir/cgroup.procs"
else
  echo "no cgroup cpu controller found (v2 cpu.max or v1 cpu)" >&2
  exit 1
fi
mkdir "$dir" || { echo "cannot make $dir (root needed)" >&2; exit 1; }
cleanup() {
  [ -n "${timer:-}" ] && kill "$timer" 2>/dev/null || true
  # Processes left in the group go back to the root group before rmdir.
  if [ -f "$procs" ]; then
    while read -r p; do echo "$p" >"$(dirname "$dir")/cgroup.procs" 2>/dev/null || true; done <"$procs"
  fi
  rmdir "$dir" 2>/dev/null || true
}
trap cleanup EXIT
[ -f "$dir/cpu.cfs_period_us" ] && echo "$period_us" >"$dir/cpu.cfs_period_us"
set_quota "$percent"
echo "slow core: CPU $cpu at ${percent}% (${period_us} us period)${then_s:+, ${then_pct}% after ${then_s} s}" >&2
if [ -n "$then_s" ]; then
  (sleep "$then_s" && set_quota "$then_pct" && echo "slow core: now ${then_pct}% ($(date +%T))" >&2) &
  timer=$!
fi
# The command runs in the group from its first instruction: a child shell
# joins it, then execs the command pinned to the one CPU.
sh -c 'echo $$ >"$1"; shift; exec taskset -c "$@"' sh "$procs" "$cpu" "$@"
