"""``smgs results RUNS_DIR... [--out FILE] [--format csv|parquet|json] [--per-view | --curves]``: the
results table (``smgs.results``: one row per cell, failed and skipped cells with their reason; or one
row per cell and test view; or the error-against-time curves) written as a file, or to stdout."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from smgs.cells import table   # light: pandas loads when a table is made


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="smgs results", description=(
        "Write the results table of every results.json below the RUNS_DIRs: one row per cell (failed and skipped "
        "cells with their reason), or per cell and test view, or the error-against-time curves. In Python: "
        "smgs.results(RUNS_DIR), smgs.curves(RUNS_DIR) (docs/reports.md, Results as data)."))
    ap.add_argument("runs_dir", type=Path, nargs="+", help="directories searched recursively for results.json")
    ap.add_argument("--out", type=Path, default=None, help="file to write (default: stdout; parquet needs a file)")
    ap.add_argument("--format", choices=table.FORMATS, default=None,
                    help="default: from the --out suffix (.csv, .parquet, .json), else csv")
    which = ap.add_mutually_exclusive_group()
    which.add_argument("--per-view", action="store_true", help="one row per cell and test view")
    which.add_argument("--curves", action="store_true", help="the error-against-time curves, one row per evaluation")
    args = ap.parse_args(argv)
    fmt = args.format or table.format_for(args.out)
    if fmt == "parquet" and args.out is None:
        print("error: --format parquet writes a file: give --out FILE.parquet", file=sys.stderr)
        return 2
    try:
        df = table.curves(*args.runs_dir) if args.curves else table.results(*args.runs_dir, per_view=args.per_view)
        if args.out is None:
            sys.stdout.write(table.encode(df, fmt).decode())
            return 0
        table.write(df, args.out, fmt)
    except (FileNotFoundError, table.ParquetUnavailable) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except OSError as e:   # a full disk, a folder without write permission: nothing half-written is left
        print(f"error: {args.out} was not written ({e})", file=sys.stderr)
        return 1
    print(f"results: {len(df)} rows -> {args.out} ({fmt})", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
