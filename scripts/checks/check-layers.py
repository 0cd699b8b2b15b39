#!/usr/bin/env python3
"""Inside each library crate, the modules import one another without a
cycle: a check of `crates/runtime/src` and `crates/lab/src`.

Which crate may use which is Cargo's to guarantee (the robot's binary does
not depend on the lab; `scripts/checks/check-crates.sh`). Inside a crate, Cargo
allows any module to import any other; this check keeps the top-level
modules of each crate a directed graph without a cycle, which is what
makes them layers: a module imports only the ones below it, and the order
is the graph itself (printed by `--graph`, drawn in
`docs/architecture.md`), not a list declared here.

Every `crate::` path (and `super::` path of a top-level file) in a module's
code, comments and `#[cfg(test)] mod tests` blocks left out, is an import
of the top-level module it names.

Usage: python3 scripts/checks/check-layers.py [--graph] [--src DIR ...]   (exit 1 on a cycle)
"""

import os
import re
import sys

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..")
CRATES = [os.path.join(ROOT, "crates", c, "src") for c in ("runtime", "lab")]
# A binary's files: above every module of the library beside them.
BINARY = {"main", "cli"}

PATH = re.compile(r"\b(crate|super)::((?:[a-z_][a-z0-9_]*)(?:::[a-z_][a-z0-9_]*)*)")
GROUP = re.compile(r"\b(crate|super)::\{([^}]*)\}")


def module_of(src, path):
    rel = os.path.relpath(path, src)[:-3].split(os.sep)
    if rel[-1] in ("mod", "lib"):
        rel = rel[:-1]
    return rel


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


def imports(text, module, is_mod_file):
    """The top-level modules `text` (the file of `module`) names."""
    code = code_of(text)
    paths = [(k, p) for k, p in PATH.findall(code)]
    for k, group in GROUP.findall(code):
        for item in group.split(","):
            item = item.strip()
            if item:
                paths.append((k, item.split("::{")[0].split(" as ")[0].strip()))
    # `super` of a file `a/b.rs` is `a`; of `a/b/mod.rs`, `a` too.
    parent = module[:-1] if not is_mod_file else module[:-1]
    names = set()
    for kind, p in paths:
        parts = p.split("::")
        full = parts if kind == "crate" else parent + parts
        if full:
            names.add(full[0])
    return names


def check(src, graph):
    edges = {}
    for root, _, files in os.walk(src):
        for f in files:
            if not f.endswith(".rs") or f == "tests.rs":
                continue
            path = os.path.join(root, f)
            module = module_of(src, path)
            if not module or module[0] in BINARY:
                continue
            with open(path, encoding="utf-8") as fh:
                names = imports(fh.read(), module, f == "mod.rs")
            for name in names:
                if name != module[0] and name not in ("self", "super", "crate"):
                    edges.setdefault(module[0], {}).setdefault(name, set()).add(
                        "::".join(module)
                    )
    # Cycles among top-level modules (Tarjan's strongly connected components).
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

    nodes = sorted(set(edges) | {w for d in edges.values() for w in d})
    for v in nodes:
        if v not in index:
            strong(v)
    problems = []
    for comp in comps:
        inner = [
            f"{a} -> {b} ({', '.join(sorted(edges[a][b]))})"
            for a in comp
            for b in sorted(edges.get(a, {}))
            if b in comp
        ]
        problems.append("import cycle: " + " <-> ".join(comp) + ": " + "; ".join(inner))
    name = os.path.relpath(src, ROOT)
    if graph:
        # Each module's height: 0 for a module that imports none, else one
        # more than the highest it imports (a cycle leaves it unranked).
        height = {}

        def rank(v, seen=()):
            if v in height:
                return height[v]
            if v in seen:
                return 0
            h = 1 + max((rank(w, seen + (v,)) for w in edges.get(v, {})), default=-1)
            height[v] = h
            return h

        print(f"{name}:")
        for v in sorted(nodes, key=lambda v: (rank(v), v)):
            deps = ", ".join(sorted(edges.get(v, {})))
            print(f"  [{rank(v)}] {v} -> {deps}" if deps else f"  [{rank(v)}] {v}")
    return name, len(nodes), problems


def main():
    srcs = CRATES
    if "--src" in sys.argv:
        srcs = sys.argv[sys.argv.index("--src") + 1 :]
        srcs = [s for s in srcs if not s.startswith("--")]
    failed = False
    for src in srcs:
        name, n, problems = check(src, "--graph" in sys.argv)
        for p in problems:
            print(f"{name}: {p}")
        if problems:
            failed = True
        else:
            print(f"{name}: layers ok: {n} modules, no import cycle")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
