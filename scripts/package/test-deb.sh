#!/usr/bin/env bash
# The Debian packages as CI builds and checks them: amd64 from the native
# binary the tests built, and arm64 from the aarch64 binary
# scripts/cross/cross-test.sh built when there is one (a release build of each
# would add two more full builds to CI; `scripts/package/deb.sh` alone builds
# release binaries). The aarch64 binary is the dev-profile one
# (target-aarch64/aarch64-unknown-linux-gnu/debug/fall-guard), or with
# CROSS_CI=1 the one of the lean cross build (`CROSS_CI=1
# scripts/cross/cross-test.sh`: profile cross-ci, no V4L2 camera, so that arm64
# package checks the packaging; it is not one to ship). Each package goes
# through scripts/package/check-deb.sh; with FALL_GUARD_DEB_INSTALL=1 (CI) the
# amd64 one is also installed, checked and purged, which changes this
# system.
set -euo pipefail
cd "$(dirname "$0")/../.."

native="${CARGO_TARGET_DIR:-target}/debug/fall-guard"
aarch64_profile=debug
[ "${CROSS_CI:-0}" = 1 ] && aarch64_profile=cross-ci
aarch64="${AARCH64_TARGET_DIR:-target-aarch64}/aarch64-unknown-linux-gnu/$aarch64_profile/fall-guard"
[ -x "$native" ] || { echo "no $native: run scripts/test.sh first" >&2; exit 1; }
out="${OUT_DIR:-out/deb}"

host=$(dpkg --print-architecture)
[ "$host" = amd64 ] || { echo "expects an amd64 build machine, not $host" >&2; exit 1; }
amd64_deb=$(bash scripts/package/deb.sh --arch amd64 --binary "$native" --out "$out")
debs=("$amd64_deb")
if [ -x "$aarch64" ]; then
  arm64_deb=$(bash scripts/package/deb.sh --arch arm64 --binary "$aarch64" --out "$out")
  bash scripts/package/check-deb.sh "$arm64_deb"
  debs+=("$arm64_deb")
else
  echo "(no $aarch64: arm64 package not built; scripts/cross/cross-test.sh builds it)"
fi
if [ "${FALL_GUARD_DEB_INSTALL:-0}" = 1 ]; then
  bash scripts/package/check-deb.sh --install "$amd64_deb"
else
  bash scripts/package/check-deb.sh "$amd64_deb"
  echo "(not installed: FALL_GUARD_DEB_INSTALL=1 installs, checks and purges it)"
fi
ls -l "${debs[@]}"
