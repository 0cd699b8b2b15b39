#!/usr/bin/env bash
# Everything fall-guard needs on a fresh Debian/Ubuntu machine (idempotent):
#   - system packages for the build: libudev-dev (serialport), libclang-dev
#     (nokhwa's V4L2 bindings), nasm (burn's image codecs), pkg-config,
#     libssl-dev and openssl (the `security` feature's OpenSSL, and the
#     test keystore of scripts/security/sros2-keystore.sh);
#   - the two Python environments (scripts/setup-python.sh): sim/.venv for
#     the simulator, .venv with rclpy (PyPI wheels) for the ROS 2 tests.
# Needs root or sudo for the packages; skips them when they are installed.
set -euo pipefail
cd "$(dirname "$0")/.."

packages=(libudev-dev libclang-dev nasm pkg-config libssl-dev openssl python3-venv)
missing=()
for p in "${packages[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if [ ${#missing[@]} -gt 0 ]; then
  echo "== installing system packages: ${missing[*]}"
  sudo=""
  [ "$(id -u)" -eq 0 ] || sudo="sudo"
  export DEBIAN_FRONTEND=noninteractive
  $sudo apt-get update -qq
  $sudo apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
fi

if ! command -v cargo >/dev/null; then
  echo "cargo not found: install Rust (https://rustup.rs) first" >&2
  exit 1
fi

echo "== python environments"
bash scripts/setup-python.sh
