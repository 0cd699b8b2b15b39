#!/usr/bin/env bash
# Instructions per streaming tick of the aarch64 binary, counted under
# qemu-user with a TCG plugin (tb_count.c): `fall-guard bench` run with 10
# and with 50 ticks, the difference over 40 ticks, in total and by function
# (per_function.py). Instruction counts, not time: emulation says nothing of
# a core's speed, but the count is what the binary's kernels ask of one, and
# it does not depend on this machine's load. Needs scripts/cross/setup-cross.sh
# (qemu-user, the cross gcc and binutils) and an aarch64 build of the robot's
# binary. Figures: docs/performance.md, "aarch64: instructions per tick".
#
#   scripts/measure/aarch64/instructions.sh BINARY NET [bench options...]
#
# e.g. BINARY=target/aarch64-unknown-linux-gnu/release/fall-guard, NET=emp,
# options such as --convolutions f32. Outputs in $OUT_DIR (default out/aarch64).
set -euo pipefail
[ $# -ge 2 ] || { echo "usage: $0 BINARY NET [bench options...]" >&2; exit 2; }
binary="$1" net="$2"
shift 2
here="$(cd "$(dirname "$0")" && pwd)"
cd "$here/../../.."
out="${OUT_DIR:-out/aarch64}"
mkdir -p "$out"
plugin="$out/libtb_count.so"
[ "$plugin" -nt "$here/tb_count.c" ] || gcc -O2 -shared -fPIC -o "$plugin" "$here/tb_count.c"
tag="$(basename "$binary")-$net${*:+-$(echo "$*" | tr -c 'a-zA-Z0-9\n' '_')}"
for ticks in 10 50; do
  counts="$out/$tag-$ticks.tb"
  # -L /: Debian's libc6:arm64 loader and libc (.cargo/config.toml).
  qemu-aarch64 -L / -plugin "$plugin,out=$counts.partial" "$binary" bench \
    --model "models/$net.bpk" --ablation "${net^^}" --ticks "$ticks" "$@" > "$out/$tag-$ticks.log" 2>&1
  mv "$counts.partial" "$counts"
done
python3 "$here/per_function.py" "$binary" "$out/$tag-10.tb" "$out/$tag-50.tb" 40 "${TOP:-15}"
