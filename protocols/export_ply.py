"""``python -m protocols.export_ply RUN_DIR [RUN_DIR ...] [--out FILE]``: the model of a finished run
as a 3DGS PLY (``RUN_DIR/point_cloud.ply`` by default), for any splat viewer (SuperSplat, the web
viewers) or any tool that reads the original 3DGS output. The run's scene is not needed: the file
is written from the run's last checkpoint, atomically.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m protocols.export_ply", description=__doc__.splitlines()[0])
    ap.add_argument("run_dirs", type=Path, nargs="+", help="run directories (with checkpoint.json)")
    ap.add_argument("--out", type=Path, default=None, help="output file (one run directory only; default: RUN_DIR/point_cloud.ply)")
    args = ap.parse_args(argv)
    if args.out is not None and len(args.run_dirs) > 1:
        ap.error("--out names one file; give one run directory with it")
    from protocols.ply import export_run   # after the arguments: --help answers without torch
    from protocols.refused import EXIT_REFUSED

    failed = 0
    for run_dir in args.run_dirs:
        try:
            path, step, status = export_run(run_dir, args.out)
        except (OSError, ValueError) as e:
            print(f"error: {e}", file=sys.stderr)
            failed += 1
            continue
        note = "" if status == "ok" else f" (run {status}: this is its checkpoint of step {step}, not a final model)"
        print(f"{path}: step {step}{note}")
    return EXIT_REFUSED if failed else 0   # a run without a model to export is refused, as every refusal


if __name__ == "__main__":
    sys.exit(main())
