"""``smgs run --help`` (``python -m protocols.run --help``): the run's own options, read from the
config tree (its experiments, groups and top-level settings with their comments), and the hint for
a setting written ``--key value``. Light: no Hydra, no torch, so the help answers at once."""

from __future__ import annotations

import textwrap

from protocols.config_files import config_entries, config_names, top_level_settings

HYDRA_FLAGS = ("--cfg", "-c", "--package", "-p", "--info", "-i", "--run", "-r", "--multirun", "-m",
               "--shell-completion", "-sc", "--config-path", "-cp", "--config-name", "-cn", "--config-dir", "-cd",
               "--experimental-rerun", "--resolve", "--hydra-help", "--version")
"""Hydra 1.3's own command-line flags: a command line with one of them is Hydra's to answer."""
OWN_FLAGS = ("--force", "-h", "--help")
WIDTH = 100
SHOWN = 8   # names of a group shown before "…"


def _wrap(head: str, text: str, indent: int) -> list[str]:
    return textwrap.wrap(text, WIDTH, initial_indent=f"  {head:<{indent}}  ", subsequent_indent=" " * (indent + 4),
                         break_on_hyphens=False) or [f"  {head}"]


def _names(group: str) -> str:
    names = [n for n in config_names(group) if n != "plugin"]
    return ", ".join(names[:SHOWN]) + (f", … ({len(names)}: smgs list {group}s)" if len(names) > SHOWN else "")


def run_help() -> str:
    lines = ["usage: smgs run [+experiment=NAME] [KEY=VALUE ...] [--force]",
             "       (python -m protocols.run, the same arguments)", "",
             *textwrap.wrap("Run an experiment's grid (methods × scenes × budgets × seeds), each run resumable, then "
                            "build its report in <out_dir>/report/. Settings are written KEY=VALUE, never --KEY VALUE; "
                            "a key that nothing reads is refused, naming the nearest one. A single value on the "
                            "command line (method=, dataset=, scene=, budget=, seed=, seeds=N) replaces the "
                            "experiment's list of that axis, and the run says so.", WIDTH), "",
             "experiments (+experiment=NAME):"]
    entries = config_entries("experiment")
    width = max(len(n) for n, _ in entries)
    for name, about in entries:
        lines += _wrap(name, about, width)
    lines += ["", "groups (GROUP=NAME; smgs list methods|datasets|budgets|protocols for what each is):"]
    for group, note in (("method", "or several: grid.methods=[3dgs,softmax_gs]"),
                        ("dataset", "colmap and transforms take dataset.path=DIR (your own scene)"),
                        ("budget", "or several: grid.budgets=[...]"), ("protocol", "protocol.steps=N and its other keys")):
        lines += _wrap(group, f"{_names(group)}; {note}", 8)
    lines += ["", "settings (configs/config.yaml, with their defaults):"]
    settings = top_level_settings()
    width = max(len(k) for k, _, _ in settings)
    for key, value, comment in settings:
        lines += _wrap(key, " — ".join(x for x in (value, comment) if x), width)
    lines += ["", "flags:",
              "  --force   redo cells that already have a finished result (force=true)",
              "  -h, --help   this text; Hydra's own: --cfg job (the composed config), --info, --hydra-help", "",
              "the rest: the method's training keys (method.train.*, smgs.train.config.TrainConfig), a scene "
              "format's",
              "keys (dataset.*), densification strategies (smgs list strategies), renderer backends (smgs list "
              "renderers);",
              "docs/usage.md has the guide."]
    return "\n".join(lines)


def flag_problem(args: list[str]) -> str | None:
    """A setting written as a flag (``--protocol.steps 300``, ``--steps=300``): the KEY=VALUE form."""
    for i, arg in enumerate(args):
        if not arg.startswith("--") or arg in OWN_FLAGS or arg.split("=", 1)[0] in HYDRA_FLAGS:
            continue
        key = arg[2:]
        if "=" not in key:
            nxt = args[i + 1] if i + 1 < len(args) else None
            key = f"{key}={nxt}" if nxt is not None and not nxt.startswith("-") and "=" not in nxt else f"{key}=VALUE"
        return f"{arg}: settings are written KEY=VALUE, without dashes: {key} (smgs run --help lists them)"
    return None


def hydra_flags(args: list[str]) -> bool:
    """Whether the command line asks Hydra itself for something (``--cfg job``, ``--info``, ``-m``)."""
    return any(a.split("=", 1)[0] in HYDRA_FLAGS for a in args)
