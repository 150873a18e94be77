"""Seconds to write and read a 3DGS PLY of N Gaussians (default 1M, SH degree 3, Softmax-GS extras:
65 float32 properties, 260 bytes each), through ``smgs.io.ply`` (plyfile underneath).

    python -m bench.ply [--n 1000000] [--degree 3] [--repeats 3] [--json FILE]

Times (wall clock, and this process's CPU time, which a busy shared host inflates less), per
repeat: ``write_ply`` (checks, column packing, plyfile write, fsync, rename), and ``read_ply``
(plyfile parse, checks incl. NaN/inf counts, SH unpacking); best and median of the repeats, with
the file size and the write/read throughput. The file goes to a temporary folder
(``--dir`` to choose one: the disk's speed is part of the figure).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:       # `python bench/ply.py` from a checkout
    sys.path.insert(0, str(ROOT))

from smgs.env import cpu_model  # noqa: E402
from smgs.io.ply import EXTRAS, PlySplats, read_ply, write_ply  # noqa: E402


def random_splats(n: int, degree: int, seed: int = 0) -> PlySplats:
    g = np.random.default_rng(seed)
    f = (lambda *shape: g.standard_normal(shape, dtype=np.float32))
    return PlySplats(f(n, 3), f(n, (degree + 1) ** 2, 3), f(n), f(n, 3), f(n, 4), {e: f(n) for e in EXTRAS},
                     {"mode": "softmax_gs"})


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.ply", description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=1_000_000)
    ap.add_argument("--degree", type=int, default=3)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--dir", type=Path, default=None)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    splats = random_splats(args.n, args.degree)
    writes, reads, cpu_w, cpu_r = [], [], [], []
    with tempfile.TemporaryDirectory(dir=args.dir) as d:
        path = Path(d) / "bench.ply"
        for _ in range(args.repeats):
            t0, c0 = time.perf_counter(), time.process_time()
            write_ply(path, splats)
            t1, c1 = time.perf_counter(), time.process_time()
            back = read_ply(path)
            t2, c2 = time.perf_counter(), time.process_time()
            writes.append(t1 - t0)
            reads.append(t2 - t1)
            cpu_w.append(c1 - c0)
            cpu_r.append(c2 - c1)
        size = path.stat().st_size
    assert np.array_equal(back.sh, splats.sh) and np.array_equal(back.extras["softmax_gamma"],
                                                                 splats.extras["softmax_gamma"])
    mb = size / 2 ** 20
    row = {"n": args.n, "degree": args.degree, "properties": 17 + 3 * ((args.degree + 1) ** 2 - 1) + len(EXTRAS),
           "file_mib": round(mb, 1), "write_s_best": min(writes), "write_s_median": statistics.median(writes),
           "read_s_best": min(reads), "read_s_median": statistics.median(reads), "write_cpu_s_best": min(cpu_w),
           "read_cpu_s_best": min(cpu_r), "repeats": args.repeats,
           "cpu": cpu_model(), "numpy": np.__version__}
    print(f"{args.n} Gaussians, SH degree {args.degree}, {mb:.0f} MiB on {row['cpu']}")
    print(f"  write: best {min(writes):.2f} s, median {statistics.median(writes):.2f} s "
          f"({mb / min(writes):.0f} MiB/s), process CPU {min(cpu_w):.2f} s")
    print(f"  read:  best {min(reads):.2f} s, median {statistics.median(reads):.2f} s "
          f"({mb / min(reads):.0f} MiB/s), process CPU {min(cpu_r):.2f} s")
    if args.json:
        args.json.write_text(json.dumps(row, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
