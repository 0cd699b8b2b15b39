#!/usr/bin/env bash
# What building for the robot needs on a Debian 12 machine (idempotent; run
# after scripts/setup.sh):
#   - the aarch64 cross toolchain, all from Debian: rustc-web (rustc 1.96,
#     /usr/bin/rustc; rustup has no aarch64 standard library installed here)
#     with libstd-rust-web-dev:arm64, gcc-aarch64-linux-gnu (linker and C
#     compiler for the -sys crates) with libc6-dev-arm64-cross (also the arm64
#     kernel headers nokhwa's V4L2 bindings are generated from), and
#     libudev-dev:arm64 (serialport's libudev);
#   - qemu-user: runs the aarch64 tests and binaries on this machine;
#   - dpkg-dev (dpkg-shlibdeps), systemd (systemd-analyze, systemd-sysusers)
#     and udev (udevadm) for scripts/package/deb.sh and scripts/package/check-deb.sh.
# Needs root or sudo.
set -euo pipefail

sudo=""
[ "$(id -u)" -eq 0 ] || sudo="sudo"
export DEBIAN_FRONTEND=noninteractive

updated=0
if ! dpkg --print-foreign-architectures | grep -qx arm64; then
  echo "== adding the arm64 architecture to dpkg"
  $sudo dpkg --add-architecture arm64
  $sudo apt-get update -qq
  updated=1
fi

packages=(rustc-web libstd-rust-web-dev:arm64 gcc-aarch64-linux-gnu libc6-dev-arm64-cross
  libudev-dev:arm64 qemu-user dpkg-dev systemd udev)
missing=()
for p in "${packages[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if [ ${#missing[@]} -gt 0 ]; then
  echo "== installing: ${missing[*]}"
  [ "$updated" = 1 ] || $sudo apt-get update -qq
  $sudo apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
fi

# bookworm-security carries rustc-web 1.96; bookworm itself has 1.85, older
# than the crate's rust-version.
cd "$(dirname "$0")/../.."
need=$(sed -n 's/^rust-version = "\(.*\)"$/\1/p' Cargo.toml)
have=$(/usr/bin/rustc -V | cut -d' ' -f2)
if [ "$(printf '%s\n%s\n' "$need" "$have" | sort -V | head -1)" != "$need" ]; then
  echo "/usr/bin/rustc is $have, fall-guard needs $need: enable bookworm-security in apt's sources" >&2
  exit 1
fi
/usr/bin/rustc --print target-libdir --target aarch64-unknown-linux-gnu >/dev/null
echo "cross toolchain: $(/usr/bin/rustc -V) for aarch64-unknown-linux-gnu, $(qemu-aarch64 --version | head -1)"
