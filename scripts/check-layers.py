#!/usr/bin/env python3
"""The library's layers import only downwards: a check of `src/`.

Every `crate::` path in a module's code (comments and `#[cfg(test)] mod
tests` blocks left out) is an import of the unit it names. Units are the
top-level modules, except `pipeline`, whose files are units of their own
(the window sits below the model, the tick loop above it). Each unit
belongs to one layer of LAYERS; a unit may import its own layer's units
and those below, never one above, and the units may not form a cycle.

Usage: python3 scripts/check-layers.py [--graph] [--src DIR]   (exit 1 on a violation)
"""

import os
import re
import sys

SRC = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "src")

# Lowest first. A unit is named by its module path; the longest match wins.
LAYERS = [
    ("base", ["clock", "robot", "msgs", "frame", "shutdown"]),
    ("streams", ["streams"]),
    ("ros", ["ros"]),
    ("recording", ["recording"]),
    ("window", ["pipeline::window"]),
    ("model", ["model"]),
    ("sources", ["sources"]),
    ("config", ["config"]),
    ("outputs", ["outputs"]),
    ("pipeline", ["pipeline"]),
    ("train", ["train"]),
    ("daemon", ["daemon"]),
]
# The crate root and the binary are above every layer.
TOP = {"crate", "main", "cli"}

PATH = re.compile(r"\bcrate::((?:[a-z_][a-z0-9_]*)(?:::[a-z_][a-z0-9_]*)*)")
GROUP = re.compile(r"\bcrate::\{([^}]*)\}")


def module_of(path):
    rel = os.path.relpath(path, SRC)[:-3].split(os.sep)
    if rel[-1] in ("mod", "lib"):
        rel = rel[:-1]
    return "::".join(rel) or "crate"


def unit_of(module):
    best = None
    for layer, (name, prefixes) in enumerate(LAYERS):
        for p in prefixes:
            if module == p or module.startswith(p + "::"):
                if best is None or len(p) > len(best[1]):
                    best = (layer, p)
    return best


def code_of(text):
    """The file without comments and without its `mod tests` blocks."""
    text = re.sub(r"//[^\n]*", "", text)
    out, i = [], 0
    for m in re.finditer(r"#\[cfg\(test\)\]\s*mod\s+\w+\s*\{", text):
        if m.start() < i:
            continue
        out.append(text[i : m.start()])
        depth, j = 1, m.end()
        while depth and j < len(text):
            depth += {"{": 1, "}": -1}.get(text[j], 0)
            j += 1
        i = j
    out.append(text[i:])
    return "".join(out)


def imports(text):
    code = code_of(text)
    names = set(PATH.findall(code))
    for group in GROUP.findall(code):
        for item in group.split(","):
            item = item.strip()
            if item:
                names.add(item.split("::{")[0].split(" as ")[0].strip())
    return names


def main():
    global SRC
    if "--src" in sys.argv:
        SRC = sys.argv[sys.argv.index("--src") + 1]
    edges = {}
    problems = []
    for root, _, files in os.walk(SRC):
        for f in files:
            if not f.endswith(".rs"):
                continue
            path = os.path.join(root, f)
            module = module_of(path)
            if module in TOP:
                continue
            if f == "tests.rs":
                continue
            src = unit_of(module)
            if src is None:
                problems.append(f"{module}: in no layer (add it to LAYERS)")
                continue
            with open(path, encoding="utf-8") as fh:
                names = imports(fh.read())
            for name in sorted(names):
                dst = unit_of(name)
                if dst is None or dst[1] == src[1]:
                    continue
                edges.setdefault(src[1], {}).setdefault(dst[1], set()).add(module)
                if dst[0] > src[0]:
                    problems.append(
                        f"{module} ({LAYERS[src[0]][0]}) imports {name} "
                        f"({LAYERS[dst[0]][0]}): a layer above"
                    )
    # Cycles among units (Tarjan's strongly connected components).
    index, low, stack, on, comps = {}, {}, [], set(), []

    def strong(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in edges.get(v, {}):
            if w not in index:
                strong(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                comps.append(sorted(comp))

    for v in sorted(set(edges) | {w for d in edges.values() for w in d}):
        if v not in index:
            strong(v)
    for comp in comps:
        problems.append("import cycle: " + " <-> ".join(comp))
    if "--graph" in sys.argv:
        for a in sorted(edges):
            print(f"{a} -> {', '.join(sorted(edges[a]))}")
    for p in problems:
        print(p)
    if problems:
        print(f"{len(problems)} layer violation(s)", file=sys.stderr)
        return 1
    print(f"layers ok: {len(edges)} units import only downwards, no cycle")
    return 0


if __name__ == "__main__":
    sys.exit(main())
