"""The package's import graph, read from the source: levels, circles, imports that break the layer rule, file sizes.

    python scripts/import_graph.py [--src src/gtforge] [--json]

Every ``import gtforge...`` / ``from gtforge... import ...`` counts, at module level or inside a function (a
function-local import is an edge all the same; it only runs later). ``from gtforge.io import formats`` counts as an
edge to ``gtforge.io.formats``. The layer rule itself lives in ``tests/test_architecture.py``, which imports this
file's functions; docs/architecture.md explains it.
"""
from __future__ import annotations

import argparse
import ast
import json
import sys
from pathlib import Path

PACKAGE = "gtforge"


def module_files(src: Path) -> dict[str, Path]:
    """Every module of the package: dotted name -> file (``__init__.py`` names its package)."""
    out = {}
    for p in sorted(src.rglob("*.py")):
        rel = p.relative_to(src.parent).with_suffix("")
        parts = list(rel.parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = p
    return out


def _resolve(name: str, modules: dict[str, Path]) -> str | None:
    """The longest module name that ``name`` starts with (``gtforge.camera.Rig`` -> ``gtforge.camera``)."""
    parts = name.split(".")
    for k in range(len(parts), 0, -1):
        cand = ".".join(parts[:k])
        if cand in modules:
            return cand
    return None


def imports_of(path: Path, modname: str, modules: dict[str, Path]) -> list[tuple[str, int, bool]]:
    """(imported module, line, at module level) for every gtforge import in one file."""
    tree = ast.parse(path.read_text(), filename=str(path))
    top_level = {id(n) for n in tree.body}
    out = []
    pkg = modname if path.name == "__init__.py" else modname.rpartition(".")[0]
    for node in ast.walk(tree):
        names = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = pkg.split(".")
                anchor = anchor[:len(anchor) - (node.level - 1)]
                base = ".".join(anchor + ([base] if base else []))
            names = [f"{base}.{a.name}" for a in node.names] + [base]
        hits = set()
        for nm in names:
            if nm == PACKAGE or nm.startswith(PACKAGE + "."):
                r = _resolve(nm, modules)
                if r and r != modname and r != PACKAGE:
                    hits.add(r)
        # `from gtforge.io import formats` names gtforge.io and gtforge.io.formats: keep the deepest
        hits = {h for h in hits if not any(o != h and o.startswith(h + ".") for o in hits)}
        for h in sorted(hits):
            out.append((h, node.lineno, id(node) in top_level))
    return out


def graph(src: Path) -> tuple[dict[str, Path], dict[str, list[tuple[str, int, bool]]]]:
    modules = module_files(src)
    return modules, {m: imports_of(p, m, modules) for m, p in modules.items()}


def circles(edges: dict[str, list[tuple[str, int, bool]]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index, low, on, stack, out, counter = {}, {}, set(), [], [], [0]
    adj = {m: sorted({e[0] for e in es}) for m, es in edges.items()}
    sys.setrecursionlimit(10000)

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in adj.get(v, []):
            if w not in index:
                visit(w)
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
                out.append(sorted(comp))

    for v in sorted(adj):
        if v not in index:
            visit(v)
    return out


def levels(edges: dict[str, list[tuple[str, int, bool]]]) -> dict[str, int]:
    """Level 0 imports nothing of the package; otherwise one more than its highest import (a circle shares a level)."""
    comp_of = {}
    for i, c in enumerate(circles(edges)):
        for m in c:
            comp_of[m] = ("circle", i)
    key = {m: comp_of.get(m, m) for m in edges}
    members = {}
    for m, k in key.items():
        members.setdefault(k, []).append(m)
    memo: dict = {}

    def lev(k):
        if k in memo:
            return memo[k]
        memo[k] = 0
        deps = {key[e[0]] for m in members[k] for e in edges[m] if e[0] in key and key[e[0]] != k}
        memo[k] = 1 + max((lev(d) for d in deps), default=-1)
        return memo[k]

    return {m: lev(key[m]) for m in edges}


def layer_of(module: str, layers: list[tuple[str, tuple[str, ...]]]) -> int:
    """The rank of the first layer whose prefixes match the module (exact name or a package prefix)."""
    for rank, (_, prefixes) in enumerate(layers):
        for p in prefixes:
            if module == p or module.startswith(p + "."):
                return rank
    raise KeyError(f"{module}: in no layer of the import rule; add it to LAYERS in tests/test_architecture.py")


def upward(edges, layers) -> list[tuple[str, int, str]]:
    """Imports from a lower layer into a higher one: (importer, line, imported)."""
    out = []
    for m, es in edges.items():
        for tgt, line, _ in es:
            if layer_of(tgt, layers) > layer_of(m, layers):
                out.append((m, line, tgt))
    return sorted(out)


def summary(src: Path, layers=None) -> dict:
    modules, edges = graph(src)
    lv = levels(edges)
    sizes = {m: sum(1 for _ in p.open()) for m, p in modules.items()}
    out = {
        "modules": len(modules),
        "levels": max(lv.values()) + 1,
        "circles": circles(edges),
        "function_local_imports": sum(1 for es in edges.values() for e in es if not e[2]),
        "largest": sorted(sizes.items(), key=lambda kv: -kv[1])[:8],
        "over_500_lines": sorted(m for m, n in sizes.items() if n > 500),
    }
    if layers is not None:
        out["upward"] = upward(edges, layers)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--src", default=str(Path(__file__).resolve().parents[1] / "src" / PACKAGE))
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
    s = summary(Path(a.src))
    if a.json:
        print(json.dumps(s, indent=1))
        return 0
    print(f"{s['modules']} modules over {s['levels']} import levels; "
          f"{s['function_local_imports']} function-local gtforge imports")
    print(f"circles: {len(s['circles'])}")
    for c in s["circles"]:
        print("  " + " <-> ".join(c))
    print("largest files (lines): " + ", ".join(f"{m} {n}" for m, n in s["largest"]))
    print(f"over 500 lines: {', '.join(s['over_500_lines']) or 'none'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
