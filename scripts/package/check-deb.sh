#!/usr/bin/env bash
# Checks a fall-guard Debian package (scripts/package/deb.sh):
#   - control fields, conffiles, maintainer scripts; every expected path with
#     its mode; the binary is an executable for the package's architecture,
#     the robot's only (no lab binary, no training crate linked in);
#   - the pieces agree: the unit's ExecStart and --config are packaged files,
#     the package holds every network in models/ and every network the
#     config names, the config's serial ports are the names the udev rule
#     creates;
#   - `systemd-analyze verify` of the unit (its ExecStart pointed at the
#     unpacked binary, since the package is not installed); verify exits 0
#     on unknown keys and bad values (it only warns), so any output fails.
# With --install (the package must be for this machine's architecture):
# `apt-get install ./PKG` as the README says, then the fall-guard user and its
# groups, `systemd-analyze verify` of the installed unit, `udevadm test` of
# the rule on a tty that is not a USB2AX (no USB device here to test the
# names on), the installed binary
# replaying a bundled recording as the fall-guard user with the installed
# config and networks, and last `apt-get purge` (the config goes with it).
# Changes the system with --install: use it in CI or on a scratch machine.
#
# Usage: scripts/package/check-deb.sh [--install] dist/fall-guard_*.deb
set -euo pipefail
cd "$(dirname "$0")/../.."

install=0
if [ "${1:-}" = "--install" ]; then
  install=1
  shift
fi
[ $# -eq 1 ] || { echo "usage: $0 [--install] PACKAGE.deb" >&2; exit 2; }
deb=$(realpath "$1")
fail() { echo "check-deb: $deb: $*" >&2; exit 1; }

tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
field() { dpkg-deb -f "$deb" "$1"; }

echo "== $deb"
dpkg-deb -I "$deb" | sed -n '1,/^ Package:/p' | head -n -1
[ "$(field Package)" = fall-guard ] || fail "Package is not fall-guard"
arch=$(field Architecture)
case "$arch" in
  amd64) machine="X86-64" ;;
  arm64) machine="AArch64" ;;
  *) fail "unexpected Architecture $arch" ;;
esac
[[ "$(basename "$deb")" == fall-guard_"$(field Version)"_"$arch".deb ]] || fail "file name does not match Version/Architecture"
depends=$(field Depends)
for d in libc6 systemd; do
  [[ ",$depends" == *", $d"* || "$depends" == "$d"* ]] || fail "Depends lacks $d: $depends"
done
echo "Version $(field Version), Architecture $arch, Depends: $depends"

# Paths and modes (dpkg-deb -c: mode owner/group size date time path).
dpkg-deb -c "$deb" | awk '{print $1, $2, $6}' > "$tmp/contents"
expect() {
  grep -qxF -e "$1 root/root ./$2" "$tmp/contents" || fail "missing or wrong mode: $1 /$2"
}
expect -rwxr-xr-x usr/bin/fall-guard
# Every network the repository ships (models/*.bpk) is in the package.
for m in models/*.bpk; do expect -rw-r--r-- "usr/share/fall-guard/$m"; done
expect -rw-r--r-- usr/share/fall-guard/models/README.md
expect -rw-r--r-- usr/share/fall-guard/launch/fall_guard.launch.py
expect -rw-r--r-- etc/fall-guard/poppy_humanoid.toml
expect -rw-r--r-- etc/default/fall-guard
expect -rw-r--r-- usr/lib/systemd/system/fall-guard.service
expect -rw-r--r-- usr/lib/udev/rules.d/70-fall-guard-usb2ax.rules
expect -rw-r--r-- usr/lib/sysusers.d/fall-guard.conf
expect -rw-r--r-- usr/share/doc/fall-guard/copyright
expect -rw-r--r-- usr/share/doc/fall-guard/README.md
echo "$(grep -vc '/$' "$tmp/contents") files, the expected paths and modes present"

mkdir "$tmp/control" && dpkg-deb -e "$deb" "$tmp/control"
printf '%s\n' /etc/default/fall-guard /etc/fall-guard/poppy_humanoid.toml > "$tmp/want-conffiles"
sort "$tmp/control/conffiles" | diff -u "$tmp/want-conffiles" - || fail "conffiles differ"
for s in postinst prerm postrm; do
  [ -x "$tmp/control/$s" ] || fail "no executable $s"
  sh -n "$tmp/control/$s" || fail "$s: shell syntax"
done
(cd "$tmp/control" && [ -f md5sums ]) || fail "no md5sums"

root="$tmp/root"
dpkg-deb -x "$deb" "$root"
(cd "$root" && md5sum --quiet -c "$tmp/control/md5sums") || fail "md5sums do not match"
readelf -h "$root/usr/bin/fall-guard" | grep -q "Machine:.*$machine" || fail "usr/bin/fall-guard is not $machine"
readelf -h "$root/usr/bin/fall-guard" | grep -q "Type:.*\(EXEC\|DYN\)" || fail "usr/bin/fall-guard is not an executable"
# The robot's binary only: no lab binary, and none of the training crates
# linked in (their source paths would be in the binary's panic messages).
[ ! -e "$root/usr/bin/fall-guard-lab" ] || fail "the package ships the lab binary"
for crate in fall-guard-lab plotters linfa indicatif; do
  if grep -aq "/$crate-[0-9]\|crates/lab/src" "$root/usr/bin/fall-guard"; then
    fail "usr/bin/fall-guard links $crate (training code on the robot)"
  fi
done

# The pieces agree with each other.
python3 - "$root" <<'EOF'
import re
import sys
import tomllib
from pathlib import Path

root = Path(sys.argv[1])
def fail(msg):
    sys.exit(f"check-deb: {msg}")

unit = (root / "usr/lib/systemd/system/fall-guard.service").read_text()
m = re.search(r"^ExecStart=(\S+) run --config (\S+)$", unit, re.M)
if not m:
    fail("no `ExecStart=BIN run --config FILE` in the unit")
binary, config_path = m.groups()
for p in (binary, config_path):
    if not (root / p.lstrip("/")).is_file():
        fail(f"the unit names {p}, which the package does not install")
for key in ("User=fall-guard", "SupplementaryGroups=dialout video"):
    if key not in unit:
        fail(f"the unit lacks {key}")
sysusers = (root / "usr/lib/sysusers.d/fall-guard.conf").read_text().split("\n")
for line in ("m fall-guard dialout", "m fall-guard video"):
    if line not in sysusers:
        fail(f"sysusers.d lacks `{line}`")

config = tomllib.loads((root / config_path.lstrip("/")).read_text())
model_dir = root / config["model"]["dir"].lstrip("/")
for k in ("emp", "mp", "ep", "p"):
    if k not in config["model"]:
        continue
    f = model_dir / config["model"][k]
    if not f.is_file():
        fail(f"[model].{k} = {f.relative_to(root)} is not in the package")

rules = (root / "usr/lib/udev/rules.d/70-fall-guard-usb2ax.rules").read_text()
names = {"/dev/" + n for n in re.findall(r'SYMLINK\+="([^"]+)"', rules)}
ports = {b: v["port"] for b, v in config["dynamixel"]["buses"].items()}
for bus, port in ports.items():
    if port not in names:
        fail(f"[dynamixel.buses.{bus}].port = {port}: the udev rule creates {sorted(names)}")
if 'ATTRS{idVendor}=="16d0", ATTRS{idProduct}=="06a7"' not in rules:
    fail("the udev rule does not select the USB2AX (16d0:06a7)")
print(f"unit runs {binary} --config {config_path}; models in {config['model']['dir']}; "
      f"buses {ports} are the udev rule's names")
EOF

verify() {
  local said
  said=$(systemd-analyze verify --man=no "$1" 2>&1) && [ -z "$said" ] ||
    fail "systemd-analyze verify $1: ${said:-exit status not 0}"
  echo "systemd-analyze verify $1: no warnings"
}
echo "== systemd-analyze verify (unpacked unit)"
sed "s#^ExecStart=/usr/bin/fall-guard #ExecStart=$root/usr/bin/fall-guard #" \
  "$root/usr/lib/systemd/system/fall-guard.service" > "$tmp/fall-guard.service"
verify "$tmp/fall-guard.service"

[ "$install" = 1 ] || exit 0

[ "$arch" = "$(dpkg --print-architecture)" ] || fail "--install needs a package for this machine"
echo "== apt-get install $deb"
DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "$deb" >/dev/null
dpkg-query -W -f='${Status} ${Version}\n' fall-guard
groups=$(id -nG fall-guard) || fail "no fall-guard user after install"
for g in dialout video; do
  [[ " $groups " == *" $g "* ]] || fail "fall-guard is not in $g (groups: $groups)"
done
echo "user fall-guard: groups $groups, shell $(getent passwd fall-guard | cut -d: -f7)"
echo "== systemd-analyze verify (installed unit)"
verify /usr/lib/systemd/system/fall-guard.service
/usr/bin/fall-guard --version
echo "== udev reads the installed rule, without errors, and it leaves other ttys alone"
tty=$(ls /sys/class/tty | head -1)
udevadm test --action=add "/sys/class/tty/$tty" > "$tmp/udev.log" 2>&1 || true
grep -q "Reading rules file: /usr/lib/udev/rules.d/70-fall-guard-usb2ax.rules" "$tmp/udev.log" ||
  { cat "$tmp/udev.log" >&2; fail "udevadm test did not read the rule"; }
if grep "70-fall-guard-usb2ax.rules" "$tmp/udev.log" | grep -v "Reading rules file"; then
  fail "the udev rule has errors or acts on $tty, which is not a USB2AX"
fi
echo "udevadm test /sys/class/tty/$tty: rule read, nothing done"
echo "== the installed binary, config and networks replay a recording as user fall-guard"
cp tests/fixtures/episode_00005.mcap "$tmp/episode.mcap"
chmod 0755 "$tmp" && chmod 0644 "$tmp/episode.mcap"
ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST runuser -u fall-guard -- \
  /usr/bin/fall-guard replay --config /etc/fall-guard/poppy_humanoid.toml \
  --recording "$tmp/episode.mcap" --max-speed --quiet 2> "$tmp/replay.log" ||
  { cat "$tmp/replay.log" >&2; fail "replay with the installed config failed"; }
grep -o 'replay finished.*' "$tmp/replay.log"
echo "== apt-get purge fall-guard"
DEBIAN_FRONTEND=noninteractive apt-get purge -y -qq fall-guard >/dev/null
for p in /usr/bin/fall-guard /etc/fall-guard /usr/lib/systemd/system/fall-guard.service; do
  [ ! -e "$p" ] || fail "$p left after purge"
done
echo "ok: installed, checked, purged"
