"""``smgs list WHAT``: the methods, experiments, datasets, budgets, protocol presets, densification
strategies and renderer backends a command line can name, each with what its config (or its class)
says about it."""

from __future__ import annotations

import sys

from protocols.config_files import config_entries, sentences

GROUPS = {"experiments": "experiment", "datasets": "dataset", "budgets": "budget", "protocols": "protocol"}
LISTED = ("methods", *GROUPS, "strategies", "renderers")
USAGE = "usage: smgs list {" + ",".join(LISTED) + "}"


def dataset_entries() -> list[tuple[str, str]]:
    """The dataset configs (but configs/dataset/plugin.yaml, the runner's stand-in for what follows),
    then the scene formats and datasets registered as plugins without a file of their own."""
    from smgs.data.registry import list_names, plugin_source

    entries = [(n, about) for n, about in config_entries("dataset") if n != "plugin"]
    files = {n for n, _ in entries}
    plugins = {n: plugin_source(n) for n in list_names() if n not in files}
    return entries + [(n, f"a scene format or dataset from a plugin: grid.datasets=[{n}] ({source})")
                      for n, source in plugins.items() if source]


def method_entries() -> list[tuple[str, str]]:
    from baselines.registry import get_spec, list_methods

    out = []
    for name in list_methods():
        spec = get_spec(name)
        about = " — ".join(x for x in (spec.paper_name, spec.description) if x)
        out.append((name, f"{about} ({spec.source})" if spec.source != "builtin" else about))
    return out


def strategy_entries() -> list[tuple[str, str]]:
    """The densification strategies: a built-in's first sentence of its class's doc (read from its
    source, not imported), a plugin's distribution (not imported)."""
    from smgs.plugins import target_doc
    from smgs.train.strategies.registry import BUILTINS, list_strategies, plugin_source

    out = []
    for name in list_strategies():
        pick = f"+method.train.densify.strategy={name}"
        if name in BUILTINS:
            about = sentences(" ".join(target_doc(BUILTINS[name]).split()))[0]
            out.append((name, f"{about} ({pick})"))
        else:
            out.append((name, f"a densification strategy from a plugin: {pick} ({plugin_source(name) or 'registered'})"))
    return out


def renderer_entries() -> list[tuple[str, str]]:
    """The renderer backends and each one's variants (``smgs.raster.backends``; nothing is built)."""
    from smgs.raster.backends import BACKENDS

    out = []
    for name, spec in BACKENDS.items():
        axes = "; ".join(f"renderer.{axis}={'|'.join(choices)}" for axis, choices in spec.axes().items())
        out.append((name, f"{spec.about} (backend={name}{'; ' + axes if axes else ''})"))
    return out


def main(args: list[str]) -> int:
    if args and args[0] in ("-h", "--help"):
        print(f"{USAGE}\n\nWhat a command line can name, one per line with what it is: the methods (method=, "
              "grid.methods=), experiments (+experiment=), datasets (dataset=), budgets (budget=, grid.budgets=), "
              "protocol presets (protocol=), densification strategies (method.train.densify.strategy=) and "
              "renderer backends with their variants (backend=, renderer.kernels=, renderer.glue=).")
        return 0
    what = args[0] if len(args) == 1 else None
    if what not in LISTED:
        print(USAGE, file=sys.stderr)
        return 2
    listed = {"methods": method_entries, "datasets": dataset_entries, "strategies": strategy_entries,
              "renderers": renderer_entries}
    entries = listed[what]() if what in listed else config_entries(GROUPS[what])
    width = max((len(n) for n, _ in entries), default=0)
    for name, about in entries:
        print(f"{name:<{width}}  {about}".rstrip())
    return 0
