#!/usr/bin/env bash
# fall-guard on the robot's architecture, checked on this machine (after
# scripts/cross/setup-cross.sh):
#   1. cross-builds the robot's binary, the lab's and the runtime's test
#      harnesses for aarch64-unknown-linux-gnu with all default features
#      (Flex backend, V4L2 camera, Jazzy), in one profile (dev: dependencies
#      at opt-level 3);
#   2. runs the runtime's model, frame and window tests under qemu-user;
#   3. runs a short `fall-guard bench` and `fall-guard-lab bench` under
#      qemu-user (their timings under emulation mean nothing: it shows the
#      benchmarks run);
#   4. forecasts a bundled recording tick by tick with each shipped network
#      (`fall-guard-lab eval --recording`, the runtime's streaming
#      forecaster), on aarch64 under qemu and natively, and fails when a
#      probability differs by more than $TOLERANCE.
#
# CROSS_CI=1 is the lean variant sized for CI (a cold build on 2 cores; run
# by .ci/run; docs/performance.md, "aarch64 under qemu-user", has its time): the same
# steps, but
#   - profile `cross-ci` (Cargo.toml: dependencies at opt-level 1 except
#     burn's Flex backend, gemm and pulp at 3; no debug info, no incremental);
#   - without the V4L2 camera (`--no-default-features --features
#     flex,jazzy`: no nokhwa, bindgen or libclang); the
#     full-feature cross build stays here, without CROSS_CI;
#   - the per-tick comparison for EMP and P only (all four streams, and
#     proprioception alone), same recording and tolerance;
#   - the native side is the lab binary scripts/test.sh built
#     ($CARGO_TARGET_DIR/debug/fall-guard-lab), not a second native build.
# $NETWORKS overrides the networks compared, $NATIVE_BIN the native lab binary.
#
# The aarch64 build goes to $AARCH64_TARGET_DIR (default target-aarch64),
# outputs to $OUT_DIR (default out/cross). The binary is
# $AARCH64_TARGET_DIR/aarch64-unknown-linux-gnu/<debug|cross-ci>/fall-guard,
# where scripts/package/test-deb.sh (with the same CROSS_CI) packages it.
set -euo pipefail
cd "$(dirname "$0")/../.."

target=aarch64-unknown-linux-gnu
aarch64_dir="${AARCH64_TARGET_DIR:-$PWD/target-aarch64}"
native_dir="${CARGO_TARGET_DIR:-$PWD/target}"
out="${OUT_DIR:-out/cross}"
# Largest |p_aarch64 - p_native| accepted: the two builds sum the GEMMs in
# different orders (NEON vs AVX2/FMA kernels); docs/performance.md
# ("aarch64 under qemu-user") has the differences measured.
tolerance="${TOLERANCE:-1e-4}"
recording=tests/fixtures/episode_00005.mcap
mkdir -p "$out"

if [ "${CROSS_CI:-0}" = 1 ]; then
  build=(--profile cross-ci --no-default-features --features flex,jazzy)
  profile_dir=cross-ci
  networks=(${NETWORKS:-emp p})
  bench_networks=(--ablation EMP --ablation P)
  native_bin="${NATIVE_BIN:-$native_dir/debug/fall-guard-lab}"
else
  build=()
  profile_dir=debug
  networks=(${NETWORKS:-emp mp ep p})
  bench_networks=()
  native_bin="${NATIVE_BIN:-}"
fi

# Debian's rustc-web has the aarch64 standard library; the linker and the
# qemu runner are in .cargo/config.toml.
xcargo() { RUSTC=/usr/bin/rustc CARGO_TARGET_DIR="$aarch64_dir" cargo "$@"; }

echo "== aarch64 build: the runtime's test harnesses, the robot's and the lab's binaries"
xcargo test --target "$target" "${build[@]}" --no-run -p fall-guard-runtime --lib --test data_window
# Both binaries in one build: their dependencies' features unified, burn
# compiled once for the two.
xcargo build --target "$target" "${build[@]}" -p fall-guard -p fall-guard-lab

echo "== aarch64 tests under qemu-user"
timed() { local t0=$SECONDS; "$@"; echo "($((SECONDS - t0)) s: $*)"; }
timed xcargo test --target "$target" "${build[@]}" -p fall-guard-runtime --lib -- model:: frame::
timed xcargo test --target "$target" "${build[@]}" -p fall-guard-runtime --test data_window

arm_bin="$aarch64_dir/$target/$profile_dir/fall-guard"
arm_lab="$aarch64_dir/$target/$profile_dir/fall-guard-lab"
# -L /: Debian's libc6:arm64 loader and libc, one glibc build (.cargo/config.toml).
run_arm() { qemu-aarch64 -L / "$arm_bin" "$@"; }
run_arm_lab() { qemu-aarch64 -L / "$arm_lab" "$@"; }
file_machine() { readelf -h "$1" | sed -n 's/^ *Machine: *//p'; }
echo "fall-guard binary: $(file_machine "$arm_bin")"

echo "== fall-guard bench under qemu-user (timings under emulation mean nothing)"
timed run_arm bench "${bench_networks[@]}" --ticks 5 --json "$out/bench-aarch64.json"
timed run_arm_lab bench --train-steps 1 --json "$out/bench-train-aarch64.json"

echo "== per-tick forecasts of $recording (${networks[*]}): aarch64 (qemu) vs native"
if [ -z "$native_bin" ] || [ ! -x "$native_bin" ]; then
  cargo build -p fall-guard-lab --bin fall-guard-lab
  native_bin="$native_dir/debug/fall-guard-lab"
fi
for m in "${networks[@]}"; do
  timed run_arm_lab eval --model "models/$m.bpk" --recording "$recording" \
    --per-tick-out "$out/$m-aarch64.jsonl"
  "$native_bin" eval --model "models/$m.bpk" --recording "$recording" \
    --per-tick-out "$out/$m-native.jsonl"
done
# The daemon's default projection (int8, `[model].projection`): the
# aarch64 kernel (generic, vectorised for NEON) against AVX2.
timed run_arm_lab eval --model models/emp.bpk --recording "$recording" --projection int8 \
  --per-tick-out "$out/emp-int8-aarch64.jsonl"
"$native_bin" eval --model models/emp.bpk --recording "$recording" --projection int8 \
  --per-tick-out "$out/emp-int8-native.jsonl"
python3 scripts/cross/compare_forecasts.py --tolerance "$tolerance" "$out" "${networks[@]}" emp-int8
echo "cross-test: done in $SECONDS s ($(uptime | sed 's/.*load/load/'))"
