"""One markdown row per finished run under the given folders, with the settings that tell runs of
one cell apart (the k_max scope, docs/kmax-scope.md) and what each run measured.

    python tools/run_table.py RUNS_DIR [RUNS_DIR ...] [--mean]

Columns: dataset/scene, method, budget, seed, k_max and its scope, test PSNR, SSIM, LPIPS, #GS,
train seconds, pixels within the softmax head (``diagnostics.frac_within_kmax``), and Table 4's
MSE7, FLIP7, Pop7 and Popped % where the run scored view consistency ("–" where it did not, or
where the value is missing; a failed run is listed with its error). ``--mean`` adds one row per
cell and scope: the mean ± sd over its seeds.
"""

from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from protocols.results import find_results, read_result  # noqa: E402

COLS = ("psnr", "ssim", "lpips", "gs", "train_s", "within", "mse7", "flip7", "pop7", "popped")
HEAD = ("PSNR", "SSIM", "LPIPS", "#GS", "train s", "within head", "MSE7", "FLIP7", "Pop7", "Popped %")


def _num(v) -> float | None:
    return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else None


def row(r) -> tuple[tuple, dict]:
    """(cell key, values) of one result."""
    train = (r.config.get("method") or {}).get("train") or {}
    key = (f"{r.dataset}/{r.scene}", r.method, r.budget, str(train.get("k_max", "?")),
           str(train.get("k_max_scope", "pixel")))
    c, m = r.consistency or {}, r.metrics or {}
    popped = _num(c.get("popped_fraction"))
    vals = dict(psnr=_num(m.get("psnr")), ssim=_num(m.get("ssim")), lpips=_num(m.get("lpips")),
                gs=_num(r.num_gaussians), train_s=_num(r.train_seconds),
                within=_num((r.diagnostics or {}).get("frac_within_kmax")), mse7=_num(c.get("mse")),
                flip7=_num(c.get("flip")), pop7=_num(c.get("pop_ratio")),
                popped=None if popped is None else 100 * popped)
    return key, vals


FMT = dict(psnr="{:.2f}", ssim="{:.3f}", lpips="{:.3f}", gs="{:.0f}", train_s="{:.0f}", within="{:.3f}",
           mse7="{:.4f}", flip7="{:.3f}", pop7="{:.2f}", popped="{:.2f}")


def cell(vals: list[float | None], k: str) -> str:
    got = [v for v in vals if v is not None]
    if not got:
        return "–"
    if len(got) == 1:
        return FMT[k].format(got[0])
    return f"{FMT[k].format(statistics.mean(got))} ± {FMT[k].format(statistics.stdev(got))}"


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("roots", nargs="+")
    ap.add_argument("--mean", action="store_true", help="also the mean ± sd over seeds of each cell and scope")
    args = ap.parse_args(argv)
    runs, failed = [], []
    for root in args.roots:
        for path in find_results(root):
            r = read_result(path)
            (runs if r.status == "ok" else failed).append(r)
    print("| scene | method | budget | k_max | scope | seed | " + " | ".join(HEAD) + " |")
    print("|---|---|---|---|---|--:|" + "--:|" * len(HEAD))
    groups: dict[tuple, list[dict]] = {}
    for r in sorted(runs, key=lambda r: (row(r)[0], r.seed)):
        key, vals = row(r)
        groups.setdefault(key, []).append(vals)
        print("| " + " | ".join(key) + f" | {r.seed} | " + " | ".join(cell([vals[k]], k) for k in COLS) + " |")
    if args.mean:
        print()
        print("| scene | method | budget | k_max | scope | seeds | " + " | ".join(HEAD) + " |")
        print("|---|---|---|---|---|--:|" + "--:|" * len(HEAD))
        for key, vs in groups.items():
            print("| " + " | ".join(key) + f" | {len(vs)} | " + " | ".join(cell([v[k] for v in vs], k) for k in COLS)
                  + " |")
    for r in failed:
        print(f"\n- failed: {r.dataset}/{r.scene} {r.method} {r.budget} seed {r.seed}: {r.error}")


if __name__ == "__main__":
    main()
