"""The reports of the test suite's fixture run trees, as golden files: every table CSV and report.md
(up to its machine-dependent Environment section) of each case below, built at 9235246 (before the
report was computed from ``smgs.results``' DataFrame) and compared by tests/test_reports_golden.py
with what the code builds now.

    python tests/report_golden.py            # (re)write tests/data/report_golden/ (only to accept a change)

Cases: the main fixture tree (patterns, Mip-NeRF360, a skipped dataset, the cpu preset, failed cells,
consistency, the reference renderer), two sweeps in one runs folder (with a duplicate cell and an
unreadable file), three seeds, one seed, seeds that must not be pooled, a paired section without
values, a Table 2 mean over scenes with different seed counts, Table 4 with a method the paper flags
and a grid run apart in two runs folders (the ordering check). Paths and the build time are
replaced by placeholders; the popping section (renders synthetic scenes, not computed from runs) is
left out of every case.
"""

from __future__ import annotations

import csv
import io
import math
import os
import re
import sys
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Iterator

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
GOLDEN = HERE / "data" / "report_golden"
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(ROOT))

from protocols.results import RunResult, read_result, write_result  # noqa: E402
from reports_tree import _ok, make_seed_tree, make_tree  # noqa: E402

STAMP = 1_700_000_000   # every results.json gets this mtime (plus an offset): duplicates resolve the same way


def _stamp(root: Path, offset: Callable[[Path], int] = lambda p: 0) -> None:
    for p in sorted(root.rglob("results.json")):
        os.utime(p, (STAMP + offset(p), STAMP + offset(p)))


def _edit(path: Path, edit: Callable[[RunResult], None]) -> None:
    r = read_result(path / "results.json")
    edit(r)
    write_result(path, r)


def case_main(root: Path) -> list[Path]:
    make_tree(root, images=True)
    return [root]


def case_two_sweeps(root: Path) -> list[Path]:
    """Two experiments in one runs folder: the main tree and the seed tree; the seed tree's fern runs
    (seed 0) duplicate the main tree's, and one results.json is unreadable."""
    make_tree(root / "main")
    make_seed_tree(root / "seeds")
    (root / "broken" / "x").mkdir(parents=True)
    (root / "broken" / "x" / "results.json").write_text("{not json")
    _stamp(root, lambda p: 10 if "seeds" in p.parts else 0)   # the seed sweep is newer: its fern seed 0 wins
    return [root]


def case_three_seeds(root: Path) -> list[Path]:
    make_seed_tree(root)
    return [root]


def case_one_seed(root: Path) -> list[Path]:
    make_seed_tree(root, seeds=(0,))
    return [root]


def case_not_pooled(root: Path) -> list[Path]:
    """blocks: a softmax_gs seed of another step count; fern: a 3dgs seed of another init opacity."""
    make_seed_tree(root)

    def longer(r: RunResult) -> None:
        r.config["protocol"]["steps"] = 400
        r.steps = 400
    _edit(root / "procedural/blocks/softmax_gs/full/seed1", longer)
    for seed, opacity in ((0, 0.1), (1, 0.1), (2, 0.5)):
        _edit(root / f"colmap/fern/3dgs/5pct/seed{seed}",
              lambda r, o=opacity: r.config.update(method={"name": "3dgs", "train": {"init_opacity": o}}))
    return [root]


def case_baseline_failed(root: Path) -> list[Path]:
    make_seed_tree(root)

    def failed(r: RunResult) -> None:
        r.status, r.error, r.metrics = "failed", "RuntimeError: out of memory", {}
    for scene, budget in (("procedural/blocks", "full"), ("colmap/fern", "5pct")):
        for seed in range(3):
            _edit(root / f"{scene}/3dgs/{budget}/seed{seed}", failed)
    return [root]


def case_scene_seeds(root: Path) -> list[Path]:
    """Tanks&Temples: train with seeds 0, 1, truck with 0, 1, 2, two methods; one truck seed collapsed,
    one without FPS, one PSNR recorded as NaN; an evaluated pretrained model."""
    psnr = {"train": (20.0, 21.0), "truck": (24.0, 24.0, 27.0)}
    for m, gain in (("3dgs", 0.0), ("softmax_gs", 0.7)):
        for scene, vals in psnr.items():
            for seed, v in enumerate(vals):
                r = _ok(m, "tandt", scene, "full", seed, v + gain + 0.1 * seed * (m == "3dgs"), gs=1_500_000 + seed,
                        seconds=1800.0 + seed, fps=90.0 - seed)
                if (m, scene, seed) == ("softmax_gs", "truck", 2):
                    r.diagnostics["collapse"] = {"collapsed": True, "what": "#GS fell to 12",
                                                 "likely_cause": "learning rate too high"}
                if (m, scene, seed) == ("3dgs", "truck", 1):
                    r.render_fps = None
                write_result(root / "tandt" / scene / m / "full" / f"seed{seed}", r)
    nan = _ok("softmax_gs", "tandt", "train", "light", 0, float("nan"), gs=900_000)
    write_result(root / "tandt" / "train" / "softmax_gs" / "light" / "seed0", nan)
    pre = _ok("3dgs", "tandt", "train", "light", 0, 21.5, gs=800_000,
              source={"kind": "pretrained", "ply": "elsewhere/point_cloud.ply", "trained_here": False})
    write_result(root / "tandt" / "train" / "3dgs" / "light" / "seed0", pre)
    return [root]


def case_table4(root: Path) -> list[Path]:
    flips = {"3dgs": (0.030, 0.031, 0.032), "stopthepop": (0.034, 0.036, 0.035),
             "softmax_gs": (0.030, 0.032, 0.031)}
    for m, f in flips.items():
        for s in range(3):
            r = RunResult(method=m, dataset="mipnerf360", scene="bicycle", budget="full", seed=s,
                          metrics={"psnr": 25.0 + 0.1 * s}, num_gaussians=1000, train_seconds=60.0, render_fps=10.0,
                          consistency={"psnr": 25.0, "mse": 0.017 + 0.001 * s, "flip": f[s], "estimator": "geometric"})
            write_result(root / "mipnerf360" / "bicycle" / m / "full" / f"seed{s}", r)
    return [root]


def case_apart(root: Path) -> list[Path]:
    """A Table 1 grid of all four methods, run apart in two runs folders (the ordering check)."""
    psnr = {"softmax_gs": 29.0, "gef_only": 24.0, "softmax_only": 19.0, "3dgs": 18.0}
    for part, pattern in (("a", "circle4"), ("b", "rect4")):
        for m, v in psnr.items():
            for seed in (0, 1):
                r = _ok(m, "patterns", pattern, "cap4", seed, v + seed, gs=4,
                        config={"budget": {"name": "cap4", "cap": 4}})
                write_result(root / part / "patterns" / pattern / m / "cap4" / f"seed{seed}", r)
    return [root / "a", root / "b"]


CASES: dict[str, Callable[[Path], list[Path]]] = {
    "main": case_main, "two_sweeps": case_two_sweeps, "three_seeds": case_three_seeds, "one_seed": case_one_seed,
    "not_pooled": case_not_pooled, "baseline_failed": case_baseline_failed, "scene_seeds": case_scene_seeds,
    "table4": case_table4, "apart": case_apart}


@contextmanager
def _no_popping() -> Iterator[None]:
    import reports.build as rb

    old = rb.wants_popping
    rb.wants_popping = lambda runs: False
    try:
        yield
    finally:
        rb.wants_popping = old


def normalise(text: str, roots: list[Path]) -> str:
    """Paths of the run trees as RUNS, the build time as WHEN."""
    for i, r in sorted(enumerate(roots), key=lambda x: -len(str(x[1]))):
        for form in {str(r.resolve()), str(r)}:
            text = text.replace(form, "RUNS" if len(roots) == 1 else f"RUNS{i}")
    return re.sub(r"built \d{4}-\d\d-\d\d \d\d:\d\d UTC", "built WHEN", text)


def build(name: str, work: Path) -> dict[str, str]:
    """The case's files: relative name -> normalised text (report.md cut before its Environment)."""
    from reports.build import build_report

    roots = CASES[name](work / name / "runs")
    if name != "two_sweeps":
        _stamp(work / name / "runs")
    out = work / name / "report"
    with _no_popping():
        build_report(roots[0], out, stability="not computed for the golden files", also=roots[1:])
    md = (out / "report.md").read_text()
    files = {"report.md": normalise(md[:md.index("## Environment")], roots)}
    for p in sorted((out / "tables").glob("*.csv")):
        files[f"tables/{p.name}"] = normalise(p.read_text(), roots)
    return files


def csv_differences(want: str, got: str, rel: float = 1e-9) -> list[str]:
    """Where two CSVs differ: header, row count, or a cell (numbers to ``rel``, text exactly)."""
    a, b = list(csv.reader(io.StringIO(want))), list(csv.reader(io.StringIO(got)))
    if not a or not b or a[0] != b[0]:
        return [f"header: {a[:1]} != {b[:1]}"]
    if len(a) != len(b):
        return [f"{len(a) - 1} rows != {len(b) - 1} rows"]
    out = []
    for i, (ra, rb) in enumerate(zip(a[1:], b[1:]), start=1):
        for col, x, y in zip(a[0], ra, rb):
            if x != y and not _close(x, y, rel):
                out.append(f"row {i} {col}: {x!r} != {y!r}")
    return out


def _close(x: str, y: str, rel: float) -> bool:
    try:
        fx, fy = float(x), float(y)
    except ValueError:
        return False
    return math.isclose(fx, fy, rel_tol=rel, abs_tol=1e-12) or (math.isnan(fx) and math.isnan(fy))


def main() -> int:
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        for name in CASES:
            for rel, text in build(name, Path(tmp)).items():
                dst = GOLDEN / name / rel
                dst.parent.mkdir(parents=True, exist_ok=True)
                dst.write_text(text)
            print(f"{name}: written")
    return 0


if __name__ == "__main__":
    sys.exit(main())
