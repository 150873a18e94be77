"""The longest functions of the harness, by source lines (first line of the ``def`` to its last line,
decorators left out, docstring and comments counted: what a reader has to take in at once).

    python tools/long_functions.py [ROOT] [-n N]

Prints the N (default 10) longest functions and methods of smgs, baselines, protocols and reports
under ROOT (default: this repository), longest first, as ``lines  module:qualified.name``.
"""

from __future__ import annotations

import argparse
import ast
from dataclasses import dataclass
from pathlib import Path

PACKAGES = ("smgs", "baselines", "protocols", "reports")


@dataclass(frozen=True)
class Function:
    lines: int
    module: str
    name: str

    def __str__(self) -> str:
        return f"{self.lines:5d}  {self.module}:{self.name}"


def functions(path: Path, module: str) -> list[Function]:
    """Every function and method of one file, with its qualified name (``Class.method``,
    ``outer.inner``)."""
    out: list[Function] = []

    def visit(node: ast.AST, prefix: str) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)):
                out.append(Function(child.end_lineno - child.lineno + 1, module, prefix + child.name))
                visit(child, f"{prefix}{child.name}.")
            elif isinstance(child, ast.ClassDef):
                visit(child, f"{prefix}{child.name}.")

    visit(ast.parse(path.read_text(), str(path)), "")
    return out


def longest(root: Path, n: int = 10) -> list[Function]:
    found: list[Function] = []
    for pkg in PACKAGES:
        for path in sorted((root / pkg).rglob("*.py")):
            module = ".".join(path.relative_to(root).with_suffix("").parts)
            found.extend(functions(path, module))
    return sorted(found, key=lambda f: (-f.lines, f.module, f.name))[:n]


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("root", nargs="?", type=Path, default=Path(__file__).resolve().parents[1])
    ap.add_argument("-n", type=int, default=10, help="how many functions to list (default 10)")
    args = ap.parse_args(argv)
    for f in longest(args.root, args.n):
        print(f)


if __name__ == "__main__":
    main()
