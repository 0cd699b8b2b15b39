#!/usr/bin/env bash
# The Debian packages as CI builds and checks them: amd64 from the native
# binary the tests built, arm64 from the aarch64 binary scripts/cross-test.sh
# built (both dev profile, dependencies at opt-level 3: a release build of
# each would add two more full builds to CI; `scripts/deb.sh` alone builds
# release binaries). Each package goes through scripts/check-deb.sh; with
# FALL_GUARD_DEB_INSTALL=1 (CI) the amd64 one is also installed, checked
# and purged, which changes this system.
set -euo pipefail
cd "$(dirname "$0")/.."

native="${CARGO_TARGET_DIR:-target}/debug/fall-guard"
aarch64="${AARCH64_TARGET_DIR:-target-aarch64}/aarch64-unknown-linux-gnu/debug/fall-guard"
for b in "$native" "$aarch64"; do
  [ -x "$b" ] || { echo "no $b: run scripts/test.sh and scripts/cross-test.sh first" >&2; exit 1; }
done
out="${OUT_DIR:-out/deb}"

host=$(dpkg --print-architecture)
[ "$host" = amd64 ] || { echo "expects an amd64 build machine, not $host" >&2; exit 1; }
amd64_deb=$(bash scripts/deb.sh --arch amd64 --binary "$native" --out "$out")
arm64_deb=$(bash scripts/deb.sh --arch arm64 --binary "$aarch64" --out "$out")
bash scripts/check-deb.sh "$arm64_deb"
if [ "${FALL_GUARD_DEB_INSTALL:-0}" = 1 ]; then
  bash scripts/check-deb.sh --install "$amd64_deb"
else
  bash scripts/check-deb.sh "$amd64_deb"
  echo "(not installed: FALL_GUARD_DEB_INSTALL=1 installs, checks and purges it)"
fi
ls -l "$amd64_deb" "$arm64_deb"
