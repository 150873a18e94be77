"""``smgs list WHAT``: the methods, experiments, datasets and budgets a command line can name, each
with the line its config (or its class) gives about it."""

from __future__ import annotations

import sys
from pathlib import Path

from protocols.run import CONFIG_DIR

GROUPS = {"experiments": "experiment", "datasets": "dataset", "budgets": "budget"}


def first_comment(path: Path) -> str:
    """The first comment line of a config file (what it is), without the ``@package`` directive."""
    for line in path.read_text().splitlines():
        text = line.lstrip("# ").strip()
        if line.startswith("#") and text and not text.startswith("@package"):
            return text
    return ""


def config_entries(group: str) -> list[tuple[str, str]]:
    return [(p.stem, first_comment(p)) for p in sorted((Path(CONFIG_DIR) / group).glob("*.yaml"))]


def method_entries() -> list[tuple[str, str]]:
    from baselines.registry import get_spec, list_methods

    out = []
    for name in list_methods():
        spec = get_spec(name)
        about = " — ".join(x for x in (spec.paper_name, spec.description) if x)
        out.append((name, f"{about} ({spec.source})" if spec.source != "builtin" else about))
    return out


def main(args: list[str]) -> int:
    what = args[0] if len(args) == 1 else None
    if what not in ("methods", *GROUPS):
        print("usage: smgs list {methods,experiments,datasets,budgets}", file=sys.stderr)
        return 2
    entries = method_entries() if what == "methods" else config_entries(GROUPS[what])
    width = max((len(n) for n, _ in entries), default=0)
    for name, about in entries:
        print(f"{name:<{width}}  {about}".rstrip())
    return 0
