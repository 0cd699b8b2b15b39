#!/usr/bin/env bash
# Builds the Debian package of fall-guard for the robot (amd64 or arm64):
#   dist/fall-guard_<version>-1_<arch>.deb
# with dpkg-deb (no packaging tool to install; dpkg-shlibdeps computes the
# library dependencies). Contents:
#   /usr/bin/fall-guard                        the binary (stripped)
#   /usr/share/fall-guard/models/              the networks in models/ + model card
#   /usr/share/fall-guard/launch/              the ROS 2 launch file
#   /etc/fall-guard/poppy_humanoid.toml        the config (conffile)
#   /etc/default/fall-guard                    the service's environment (conffile)
#   /usr/lib/systemd/system/fall-guard.service the unit (ExecStart=/usr/bin/fall-guard)
#   /usr/lib/udev/rules.d/70-fall-guard-usb2ax.rules  /dev/usb2ax-lower, -upper
#   /usr/lib/sysusers.d/fall-guard.conf        the fall-guard user (dialout, video),
#                                              created by the postinst
#   /usr/share/doc/fall-guard/                 README, daemon and ROS docs, copyright
#
# Usage: scripts/package/deb.sh [--arch amd64|arm64] [--binary PATH] [--out DIR]
#   --arch    Debian architecture (default: this machine's);
#   --binary  package this fall-guard binary instead of building one. Without
#             it: `cargo build --release --bin fall-guard`, the robot's binary
#             only (the lab's `fall-guard-lab` is never packaged; arm64: the cross build of
#             scripts/cross/setup-cross.sh, RUSTC=/usr/bin/rustc, target dir
#             $AARCH64_TARGET_DIR or target-aarch64);
#   --out     output directory (default: dist).
# Maintainer field: $DEBFULLNAME <$DEBEMAIL> when set.
set -euo pipefail
cd "$(dirname "$0")/../.."

host_arch=$(dpkg --print-architecture)
arch=$host_arch
binary=""
out=dist
while [ $# -gt 0 ]; do
  case "$1" in
    --arch) arch=$2; shift 2 ;;
    --binary) binary=$2; shift 2 ;;
    --out) out=$2; shift 2 ;;
    *) echo "usage: $0 [--arch amd64|arm64] [--binary PATH] [--out DIR]" >&2; exit 2 ;;
  esac
done

case "$arch" in
  amd64) triple=x86_64-linux-gnu; rust_target=x86_64-unknown-linux-gnu; machine="X86-64" ;;
  arm64) triple=aarch64-linux-gnu; rust_target=aarch64-unknown-linux-gnu; machine="AArch64" ;;
  *) echo "unsupported architecture: $arch (amd64 or arm64)" >&2; exit 2 ;;
esac

if [ -z "$binary" ]; then
  if [ "$arch" = "$host_arch" ]; then
    cargo build --release --bin fall-guard
    binary="${CARGO_TARGET_DIR:-target}/release/fall-guard"
  else
    [ "$arch" = arm64 ] || { echo "cross build only for arm64" >&2; exit 2; }
    target_dir="${AARCH64_TARGET_DIR:-$PWD/target-aarch64}"
    RUSTC=/usr/bin/rustc CARGO_TARGET_DIR="$target_dir" \
      cargo build --release --target "$rust_target" --bin fall-guard
    binary="$target_dir/$rust_target/release/fall-guard"
  fi
fi
[ -x "$binary" ] || { echo "no binary at $binary" >&2; exit 1; }
# The binary must be for the package's architecture.
readelf -h "$binary" | grep -q "Machine:.*$machine" || {
  echo "$binary is not an $arch ($machine) executable" >&2
  exit 1
}

version=$(sed -n 's/^version = "\(.*\)"$/\1/p' Cargo.toml | head -1)
deb_version="$version-1"
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
root="$work/debian/fall-guard"

install -d "$root/DEBIAN"
strip_tool=strip
[ "$arch" = "$host_arch" ] || strip_tool="$triple-strip"
install -D -m 0755 "$binary" "$root/usr/bin/fall-guard"
"$strip_tool" --strip-unneeded "$root/usr/bin/fall-guard"
install -D -m 0644 -t "$root/usr/share/fall-guard/models" \
  models/*.bpk models/README.md
install -D -m 0644 launch/fall_guard.launch.py "$root/usr/share/fall-guard/launch/fall_guard.launch.py"
install -D -m 0644 config/poppy_humanoid.toml "$root/etc/fall-guard/poppy_humanoid.toml"
install -D -m 0644 packaging/default "$root/etc/default/fall-guard"
install -D -m 0644 systemd/fall-guard.service "$root/usr/lib/systemd/system/fall-guard.service"
install -D -m 0644 packaging/70-fall-guard-usb2ax.rules \
  "$root/usr/lib/udev/rules.d/70-fall-guard-usb2ax.rules"
install -D -m 0644 packaging/fall-guard.sysusers "$root/usr/lib/sysusers.d/fall-guard.conf"
install -D -m 0644 -t "$root/usr/share/doc/fall-guard" \
  README.md docs/daemon.md docs/ros.md packaging/copyright

# Library dependencies of the binary, for the package's architecture.
mkdir -p "$work/debian"
printf 'Source: fall-guard\n\nPackage: fall-guard\nArchitecture: any\n' > "$work/debian/control"
shlibs=$(cd "$work" && DEB_HOST_ARCH="$arch" dpkg-shlibdeps -O -e debian/fall-guard/usr/bin/fall-guard 2>&1 |
  sed -n 's/^shlibs:Depends=//p')
[ -n "$shlibs" ] || { echo "dpkg-shlibdeps found no dependencies" >&2; exit 1; }

maintainer="${DEBFULLNAME:-fall-guard developers} <${DEBEMAIL:-fall-guard@localhost}>"
installed_size=$(du -sk --exclude=DEBIAN "$root" | cut -f1)
cat > "$root/DEBIAN/control" <<EOF
Package: fall-guard
Version: $deb_version
Architecture: $arch
Maintainer: $maintainer
Installed-Size: $installed_size
Depends: $shlibs, systemd
Recommends: udev
Section: misc
Priority: optional
Description: onboard fall forecasting for the Poppy Humanoid robot
 Reads the servos (two USB2AX Dynamixel buses), the head camera and the
 motion plan, runs the EMP network every tick and publishes fall
 probabilities 0.5-2 s ahead and a fall_imminent safety signal on ROS 2.
 The shipped networks are trained on simulated data only (model card:
 /usr/share/fall-guard/models/README.md).
 .
 After installing: systemctl enable --now fall-guard
EOF
printf '%s\n' /etc/fall-guard/poppy_humanoid.toml /etc/default/fall-guard > "$root/DEBIAN/conffiles"
install -m 0755 packaging/postinst packaging/prerm packaging/postrm "$root/DEBIAN/"
(cd "$root" && find . -path ./DEBIAN -prune -o -path ./etc -prune -o -type f -printf '%P\0' |
  LC_ALL=C sort -z | xargs -0 md5sum > DEBIAN/md5sums)

mkdir -p "$out"
deb="$out/fall-guard_${deb_version}_${arch}.deb"
dpkg-deb --root-owner-group -Zgzip --build "$root" "$deb" >/dev/null
echo "$deb"
