"""The command lines of the reports' programs (``python -m reports.build``, ``python -m
reports.popping``, and ``smgs report`` / ``smgs popping`` in front of them): their parsers, in a
module that imports nothing heavy, so that ``--help`` answers at once."""

from __future__ import annotations

import argparse
from pathlib import Path


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="python -m reports.build", description="results tree -> report: report.md, "
                                 "report.html, one CSV per table, tables/runs.csv (every run) and plots, into DIR "
                                 "(default RUNS_DIR/report)")
    ap.add_argument("runs_dir", type=Path, nargs="+",
                    help="directory searched recursively for results.json; several: one report of all "
                         "(e.g. a grid split over machines), written below the first unless --out")
    ap.add_argument("--out", type=Path, default=None, help="output directory (default RUNS_DIR/report)")
    ap.add_argument("--no-stability", action="store_true", help="do not run the renderer's stiff-case battery")
    return ap


def popping_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="python -m reports.popping", description="Popping at a depth-order flip: "
                                 "the popping ratio of every method on the synthetic flip scenes and strips of "
                                 "frames around the flip.")
    ap.add_argument("out", type=Path, help="folder for popping.md, popping.csv and the strips")
    return ap
