#!/usr/bin/env bash
# The crate graph (docs/architecture.md, "Crates"): the robot's binary
# (package fall-guard) links the runtime and never the lab, nor what only
# training uses (plotters, linfa, indicatif, ndarray, burn's autodiff and
# optimisers), checked on `cargo
# tree` of the normal dependencies, with the default features and with
# `--features security`; the runtime never reaches the lab, with every
# feature. The libraries' own code (crates/runtime/src, crates/lab/src but
# the lab binary's main.rs and cli.rs) uses no command-line parser (clap)
# and no anyhow: checked on the sources, since ros2-client and rustypot
# depend on clap themselves.
#
# Usage: scripts/checks/check-crates.sh [--tree FILE PACKAGE]
#   --tree checks the dependency list in FILE (one crate name a line, as
#   `cargo tree -e normal --prefix none` writes it) as PACKAGE's instead of
#   running cargo: what the test of this script feeds it.
set -euo pipefail
cd "$(dirname "$0")/../.."
CARGO=${CARGO:-cargo}

# PACKAGE: the crates it must never reach.
forbidden() {
  case $1 in
    fall-guard) echo "fall-guard-lab plotters linfa linfa-logistic indicatif ndarray burn-autodiff burn-optim" ;;
    fall-guard-runtime) echo "fall-guard-lab plotters linfa linfa-logistic indicatif burn-autodiff burn-optim" ;;
    fall-guard-lab) echo "" ;;
  esac
}

# check PACKAGE LABEL < tree: fails naming each forbidden crate found.
check() {
  local package=$1 label=$2 tree bad=0 name
  tree=$(awk '{print $1}' | sort -u)
  for name in $(forbidden "$package"); do
    if grep -qx "$name" <<<"$tree"; then
      echo "check-crates: $package ($label) depends on $name" >&2
      bad=1
    fi
  done
  if [ "$bad" = 0 ]; then
    echo "check-crates: $package ($label): $(wc -l <<<"$tree") crates, none of: $(forbidden "$package")"
  fi
  return $bad
}

if [ "${1:-}" = "--tree" ]; then
  check "$3" "$2" < "$2"
  exit
fi

tree() {
  "$CARGO" tree --locked -e normal --prefix none --format '{p}' "$@" | sed 's/ (\*)$//'
}
status=0
check fall-guard "default features" < <(tree -p fall-guard) || status=1
check fall-guard "--features security" < <(tree -p fall-guard --features security) || status=1
check fall-guard-runtime "every feature" < <(tree -p fall-guard-runtime --features security,ndarray) || status=1
if grep -rnE '\b(clap|anyhow)::|use (clap|anyhow)\b' crates/runtime/src crates/lab/src --include='*.rs' \
    | grep -v '^crates/lab/src/\(main\|cli\)\.rs:'; then
  echo "check-crates: a library uses clap or anyhow (the binaries' only)" >&2
  status=1
else
  echo "check-crates: the libraries' code uses neither clap nor anyhow"
fi
exit $status
