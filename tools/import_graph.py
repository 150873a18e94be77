"""The import graph of the harness, and what in it breaks the layering.

    python tools/import_graph.py [ROOT]

Prints the package-level edges (importer -> imported, with the count of module imports behind each),
then every edge that runs against smgs <- baselines <- protocols <- reports <- smgs_cli and every cycle among
modules; exits 1 if there is either. Every import counts, also one inside a function: a lazy import
is still a dependency.
"""

from __future__ import annotations

import ast
import sys
from collections import Counter
from pathlib import Path

LAYERS = ("smgs", "baselines", "protocols", "reports", "smgs_cli")  # each may import only those before it


def modules(root: Path) -> dict[str, Path]:
    """Dotted name -> file, for every module of the layered packages under ``root``."""
    found = {}
    for pkg in LAYERS:
        for path in sorted((root / pkg).rglob("*.py")):
            parts = list(path.relative_to(root).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            found[".".join(parts)] = path
    return found


def imports(name: str, path: Path, known: dict[str, Path]) -> set[str]:
    """The modules of ``known`` that module ``name`` imports (``from a import b`` names a.b when
    that is a module, else a)."""
    is_pkg = path.name == "__init__.py"
    out = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                here = name.split(".") if is_pkg else name.split(".")[:-1]
                here = here[:len(here) - node.level + 1]
                base = ".".join(here + ([base] if base else []))
            targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in known else base for a in node.names]
        else:
            continue
        for t in targets:
            while t and t not in known:  # `import a.b.c` of a non-module attribute: its module
                t = t.rpartition(".")[0]
            if t and t != name:
                out.add(t)
    return out


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    found = []
    for start in sorted(graph):
        if start in index:
            continue
        work = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on.add(start)
        while work:
            v, it = work[-1]
            w = next(it, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = len(index)
                    stack.append(w)
                    on.add(w)
                    work.append((w, iter(sorted(graph[w]))))
                elif w in on:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                comp = []
                while True:
                    w = stack.pop()
                    on.discard(w)
                    comp.append(w)
                    if w == v:
                        break
                if len(comp) > 1:
                    found.append(sorted(comp))
    return sorted(found)


def report(root: Path) -> tuple[list[str], list[tuple[str, str]], list[list[str]]]:
    """(printable package edges, wrong-way module edges, cycles)."""
    known = modules(root)
    graph = {m: imports(m, p, known) for m, p in known.items()}
    pkg_edges = Counter((a.split(".")[0], b.split(".")[0]) for a, bs in graph.items() for b in bs
                        if a.split(".")[0] != b.split(".")[0])
    lines = [f"{a} -> {b} ({n})" for (a, b), n in sorted(pkg_edges.items())]
    rank = {p: i for i, p in enumerate(LAYERS)}
    wrong = sorted((a, b) for a, bs in graph.items() for b in bs
                   if rank[b.split(".")[0]] > rank[a.split(".")[0]])
    return lines, wrong, cycles(graph)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    root = Path(argv[0]) if argv else Path(__file__).resolve().parents[1]
    lines, wrong, cyc = report(root)
    print("package edges (importer -> imported (module imports)):")
    print("\n".join(f"  {x}" for x in lines))
    print(f"wrong-way edges (against {' <- '.join(LAYERS)}): {len(wrong)}")
    for a, b in wrong:
        print(f"  {a} -> {b}")
    print(f"module cycles: {len(cyc)}")
    for c in cyc:
        print(f"  {' <-> '.join(c)}")
    return 1 if wrong or cyc else 0


if __name__ == "__main__":
    sys.exit(main())
