#!/usr/bin/env python3
"""Instructions per tick by function, from two tb_count.c outputs of the
same aarch64 binary: `fall-guard bench` with FEW and with MANY ticks (all
else the same), so that their difference over MANY - FEW is one tick's
work (the streaming push and forecast, and the bench's own noise input).

    per_function.py BINARY FEW.tb MANY.tb TICKS [TOP]

A block is charged to the function whose symbol (`aarch64-linux-gnu-nm`)
starts at or below its address; the binary is position-independent and
qemu-user loads it at 0x5500000000 (QEMU_BASE overrides)."""
import bisect
import os
import subprocess
import sys
from collections import Counter


def symbols(binary):
    out = subprocess.run(["aarch64-linux-gnu-nm", "-C", "--defined-only", "-n", binary],
                         capture_output=True, text=True, check=True).stdout
    syms = []
    for line in out.splitlines():
        parts = line.split(" ", 2)
        if len(parts) == 3 and parts[1] in "tTwW":
            syms.append((int(parts[0], 16), parts[2]))
    return syms


def per_symbol(path, syms, base):
    starts = [a for a, _ in syms]
    end = starts[-1] + (1 << 20)
    total = Counter()
    with open(path) as f:
        for line in f:
            vaddr, n = line.split()
            at = int(vaddr, 16) - base
            i = bisect.bisect_right(starts, at) - 1
            name = syms[i][1] if 0 <= at < end and i >= 0 else "(outside the binary: libc, loader)"
            total[name] += int(n)
    return total


def main():
    if len(sys.argv) < 5:
        sys.exit(__doc__)
    binary, few, many, ticks = sys.argv[1], sys.argv[2], sys.argv[3], int(sys.argv[4])
    top = int(sys.argv[5]) if len(sys.argv) > 5 else 15
    base = int(os.environ.get("QEMU_BASE", "5500000000"), 16)
    syms = symbols(binary)
    a, b = per_symbol(few, syms, base), per_symbol(many, syms, base)
    diff = {k: (b[k] - a[k]) / ticks for k in set(a) | set(b)}
    total = sum(diff.values())
    print(f"per tick: {total / 1e6:.2f} M instructions")
    for name, n in sorted(diff.items(), key=lambda kv: -abs(kv[1]))[:top]:
        print(f"{n / 1e6:8.3f} M {100 * n / total:5.1f}%  {name[:140]}")


if __name__ == "__main__":
    main()
