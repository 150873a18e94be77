"""The import graph of the harness, and what in it breaks the layering.

    python tools/import_graph.py [ROOT]

Prints the package-level edges (importer -> imported, with the count of module imports behind each),
then every edge that runs against smgs <- baselines <- protocols <- reports <- smgs_cli, or inside
smgs against SMGS_LAYERS, and every cycle among modules; exits 1 if there is any. Every import
counts, also one inside a function: a lazy import is still a dependency. So does an import by name:
a literal module passed to ``importlib.import_module`` (or ``__import__``), and a ``"module:attr"``
string naming a module of the harness (the form every registry of things imported lazily uses:
methods, renderer backends, scene formats), wherever it is written.
"""

from __future__ import annotations

import ast
import re
import sys
from collections import Counter
from pathlib import Path

LAYERS = ("smgs", "baselines", "protocols", "reports", "smgs_cli")  # each may import only those before it

# Inside smgs, each group may import its own and those before it: plain helpers that import no other
# smgs module (version, env, atomic writes, the device setting, the camera, a setting's ranges, the
# nearest spelling of a key, a package's names on first use, what
# the plug-in registries share), then the renderer, the
# scenes, the metrics, training, a cell's identity (its settings and inputs, as the runner and the
# reports compare them), model files (the PLY and its mapping onto the trainer), run results
# (results.json and the pandas tables of them), and the package's front (smgs/__init__.py, the
# demo). A dotted name covers its package and submodules;
# "smgs" is the package's own __init__ only. A module in no group is reported, to be placed.
SMGS_LAYERS: tuple[tuple[str, ...], ...] = (
    ("smgs.version", "smgs.env", "smgs.atomic", "smgs.device", "smgs.camera", "smgs.ranges", "smgs.plugins",
     "smgs.spelling", "smgs.lazy"),
    ("smgs.raster",),
    ("smgs.data",),
    ("smgs.metrics",),
    ("smgs.train",),
    ("smgs.identity",),
    ("smgs.io",),
    ("smgs.cells",),
    ("smgs.demo", "smgs"),
)
UNPLACED = "(no group of SMGS_LAYERS)"
BY_NAME = re.compile(r"([A-Za-z_][\w.]*):[A-Za-z_][\w.]*")   # "module:attr", as the registries write them
IMPORT_FUNCTIONS = ("import_module", "__import__")


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
        elif isinstance(node, (ast.Call, ast.Constant)):
            targets = by_name(node, known)
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


def by_name(node: ast.Call | ast.Constant, known: dict[str, Path]) -> list[str]:
    """The module a call of ``importlib.import_module`` / ``__import__`` with a literal name imports,
    or that a ``"module:attr"`` string names when it is one of ``known``."""
    if isinstance(node, ast.Call):
        func = node.func
        called = func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", None)
        first = node.args[0] if node.args else None
        is_literal = isinstance(first, ast.Constant) and isinstance(first.value, str)
        return [first.value] if called in IMPORT_FUNCTIONS and is_literal else []
    match = BY_NAME.fullmatch(node.value) if isinstance(node.value, str) else None
    return [match.group(1)] if match and match.group(1) in known else []


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


def group_of(module: str, layers: tuple[tuple[str, ...], ...]) -> int | None:
    """The index of the group of ``layers`` that holds ``module`` (the longest name that covers it)."""
    best, found = -1, None
    for i, group in enumerate(layers):
        for name in group:
            covers = module == name or ("." in name and module.startswith(name + "."))
            if covers and len(name) > best:
                best, found = len(name), i
    return found


def report(root: Path, smgs_layers: tuple[tuple[str, ...], ...] = SMGS_LAYERS
           ) -> tuple[list[str], list[tuple[str, str]], list[list[str]]]:
    """(printable package edges, wrong-way module edges, cycles). An smgs module in no group of
    ``smgs_layers`` is a wrong edge to ``UNPLACED``."""
    known = modules(root)
    graph = {m: imports(m, p, known) for m, p in known.items()}
    pkg_edges = Counter((a.split(".")[0], b.split(".")[0]) for a, bs in graph.items() for b in bs
                        if a.split(".")[0] != b.split(".")[0])
    lines = [f"{a} -> {b} ({n})" for (a, b), n in sorted(pkg_edges.items())]
    rank = {p: i for i, p in enumerate(LAYERS)}
    wrong = [(a, b) for a, bs in graph.items() for b in bs if rank[b.split(".")[0]] > rank[a.split(".")[0]]]
    inner = {m: group_of(m, smgs_layers) for m in graph if m.split(".")[0] == "smgs"}
    wrong += [(m, UNPLACED) for m, g in inner.items() if g is None]
    wrong += [(a, b) for a, bs in graph.items() if a in inner for b in bs
              if b in inner and None not in (inner[a], inner[b]) and inner[b] > inner[a]]
    return lines, sorted(wrong), cycles(graph)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    root = Path(argv[0]) if argv else Path(__file__).resolve().parents[1]
    lines, wrong, cyc = report(root)
    print("package edges (importer -> imported (module imports)):")
    print("\n".join(f"  {x}" for x in lines))
    print(f"wrong-way edges (against {' <- '.join(LAYERS)}, and SMGS_LAYERS inside smgs): {len(wrong)}")
    for a, b in wrong:
        print(f"  {a} -> {b}")
    print(f"module cycles: {len(cyc)}")
    for c in cyc:
        print(f"  {' <-> '.join(c)}")
    return 1 if wrong or cyc else 0


if __name__ == "__main__":
    sys.exit(main())
