"""The house in numbers, from the source alone (nothing is imported or run).

    python tools/house_stats.py            # a table for docs/architecture.md
    python tools/house_stats.py --json     # the same as JSON

rooms      packages and sub-packages (folders with an __init__.py) of the six top-level packages
arrows     distinct room → room import edges (an import anywhere in a module counts)
cycles     strongly connected groups of modules under *every* import, top-level or inside a
           function: an import written inside a function to break a cycle still closes it here
breakers   imports written inside a function whose two modules lie in one cycle (they exist only
           to keep the cycle from failing at import time)
private    uses of another module's ``_name`` (tools/private_names.py)
largest    the longest module (lines) and the longest function (lines, ast end − start + 1)
"""

from __future__ import annotations

import ast
import json
import sys
from collections import defaultdict
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
PACKAGES = ("plumbing", "brdfdata", "fitting", "acquisition", "calibration", "simulator", "gonio")


def modules() -> dict[str, Path]:
    """Dotted module name → file, for every module of our packages."""
    out = {}
    for pkg in PACKAGES:
        root = REPO / pkg
        if not root.is_dir():
            continue
        for path in sorted(root.rglob("*.py")):
            parts = list(path.relative_to(REPO).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join(parts)] = path
    return out


def _target(name: str, known: dict[str, Path]) -> str | None:
    """The longest known module that ``name`` is or lies in."""
    while name:
        if name in known:
            return name
        name = name.rpartition(".")[0]
    return None


def imports(known: dict[str, Path]) -> dict[str, set[tuple[str, bool]]]:
    """module → {(imported module, at top level?)}."""
    edges: dict[str, set[tuple[str, bool]]] = defaultdict(set)
    for mod, path in known.items():
        tree = ast.parse(path.read_text())
        is_pkg = path.name == "__init__.py"
        top = {id(n) for n in tree.body}
        for node in ast.walk(tree):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    pkg = mod if is_pkg else mod.rpartition(".")[0]
                    for _ in range(node.level - 1):
                        pkg = pkg.rpartition(".")[0]
                    base = f"{pkg}.{base}" if base else pkg
                names = [f"{base}.{a.name}" for a in node.names] or [base]
                names = [n if _target(n, known) != mod else base for n in names]
            for n in names:
                t = _target(n, known)
                if t and t != mod:
                    edges[mod].add((t, id(node) in top))
    return edges


def cycles(edges: dict[str, set[tuple[str, bool]]]) -> list[list[str]]:
    """Strongly connected groups (Tarjan) of more than one module."""
    graph = {m: {t for t, _ in ts} for m, ts in edges.items()}
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []
    counter = [0]
    sys.setrecursionlimit(10000)

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = []
            while True:
                w = stack.pop()
                on.discard(w)
                group.append(w)
                if w == v:
                    break
            if len(group) > 1:
                out.append(sorted(group))

    for v in list(graph):
        if v not in index:
            visit(v)
    return out


def _private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__")


def private_uses(module: str, source: str, known: set[str]) -> list[tuple[int, str]]:
    """(line, text) of every use in ``source`` (module ``module``) of a private name of another
    module in ``known``."""
    tree = ast.parse(source)
    bound: dict[str, str] = {}  # local name → our module it is bound to
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            for alias in node.names:
                full = f"{node.module}.{alias.name}"
                if full in known:
                    bound[alias.asname or alias.name] = full
                elif node.module in known and node.module != module and _private(alias.name):
                    found.append((node.lineno, f"from {node.module} import {alias.name}"))
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name in known:
                    local = alias.asname or alias.name.split(".")[0]
                    bound[local] = alias.name if alias.asname else local
    for node in ast.walk(tree):
        if (
            isinstance(node, ast.Attribute)
            and isinstance(node.value, ast.Name)
            and node.value.id in bound
            and _private(node.attr)
            and bound[node.value.id] != module
            and f"{bound[node.value.id]}.{node.attr}" not in known
        ):
            found.append((node.lineno, f"{node.value.id}.{node.attr}"))
    return sorted(found)


def room(mod: str, known: dict[str, Path]) -> str:
    """The package (folder) a module lives in."""
    return mod if known[mod].name == "__init__.py" else mod.rpartition(".")[0]


def stats() -> dict:
    known = modules()
    edges = imports(known)
    rooms = {room(m, known) for m in known}
    arrows = {
        (room(a, known), room(b, known))
        for a, ts in edges.items()
        for b, _ in ts
        if room(a, known) != room(b, known)
    }
    lines = {m: len(p.read_text().splitlines()) for m, p in known.items()}
    longest = ("", "", 0)
    for m, p in known.items():
        for node in ast.walk(ast.parse(p.read_text())):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                n = node.end_lineno - node.lineno + 1
                if n > longest[2]:
                    longest = (m, node.name, n)
    big = max(lines, key=lines.get)
    found = cycles(edges)
    group = {m: i for i, c in enumerate(found) for m in c}
    breakers = sorted(
        f"{a} -> {b}"
        for a, ts in edges.items()
        for b, top in ts
        if not top and a in group and group.get(b) == group[a]
    )
    private = sum(len(private_uses(m, p.read_text(), set(known))) for m, p in known.items())
    return {
        "modules": len(known),
        "lines": sum(lines.values()),
        "rooms": len(rooms),
        "arrows": len(arrows),
        "cycles": found,
        "breakers": breakers,
        "private_names": private,
        "largest_module": [big, lines[big]],
        "longest_function": [f"{longest[0]}:{longest[1]}", longest[2]],
    }


def main() -> None:
    s = stats()
    if "--json" in sys.argv:
        print(json.dumps(s, indent=2))
        return
    print(f"modules          {s['modules']} ({s['lines']} lines)")
    print(f"rooms            {s['rooms']}")
    print(f"arrows           {s['arrows']}")
    print(f"cycles           {len(s['cycles'])}")
    for c in s["cycles"]:
        print("  " + " ↔ ".join(c))
    print(f"breakers         {len(s['breakers'])}")
    for b in s["breakers"]:
        print("  " + b)
    print(f"private names    {s['private_names']} used outside their module")
    print(f"largest module   {s['largest_module'][0]} ({s['largest_module'][1]} lines)")
    print(f"longest function {s['longest_function'][0]} ({s['longest_function'][1]} lines)")


if __name__ == "__main__":
    main()
