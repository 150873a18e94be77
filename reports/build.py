"""``python -m reports.build RUNS_DIR [RUNS_DIR ...] [--out DIR] [--no-stability]``: results tree -> report.

Reads every results.json below the RUNS_DIRs (several: one grid run apart, merged as one) and writes, into DIR (default RUNS_DIR/report):
``report.md``, ``tables/<table>.csv`` (one per table, long format), ``tables/runs.csv`` (every run),
``plots/*.png`` and ``report.html`` (the same report as one interactive page, ``reports/html/``). The report is
built in a temporary folder beside DIR and switched in whole at the end, so a failed build leaves the previous
report as it was; files of a previous build that this build does not produce are removed (only those the
previous build listed in its manifest), other files in DIR are kept.
"""

from __future__ import annotations

import contextlib
import csv
import fcntl
import io
import json
import math
import os
import shutil
import sys
import tempfile
import traceback
from collections import Counter
from datetime import datetime, timezone
from pathlib import Path
from typing import Iterator

from protocols.results import RunResult
from smgs.atomic import atomic_write_bytes, atomic_write_text, replace_dir, umask
from reports.aggregate import Cells
from reports.diagnostics import diagnostics_section
from reports.environment import environment_markdown, this_machine
from reports.html import html_report
from reports.paper import load_paper
from reports.plots import Plot, pareto_plots, time_curves
from reports.popping import popping_section, wants_popping
from reports.runs import LoadedRuns, is_pattern, load_runs, one_line, pattern_cap, presets_summary
from reports.stability_section import compute_stability, stability_section
from reports.table_model import SEEDS_GUIDE, Section, md_text
from reports.tables import Context, table1, table2, table3, table4, table5
from reports.tradeoff import tradeoff_points

REPORT = "report.md"
HTML = "report.html"
MANIFEST = ".report_files.json"
MAX_LISTED_FAILURES = 50

READING_GUIDE = """\
How to read the tables: each value of ours is followed by the paper's value and the difference
(Δ = ours − paper; for counts, minutes and FPS ×paper = ours / paper). **Bold** is the best and *italics*
the second best among rows that compete (same group or scene, same protocol preset, and for speed the
same device). "—" means there is no value; its footnote says why (failed with the error, skipped for
missing data, metric not computed, or not in the paper). "[cpu]" marks a row of a reduced protocol
preset, which is never the paper's protocol."""


def build_report(runs_dir: Path | str, out_dir: Path | str | None = None,
                 stability: list[dict] | str | None = None, also: list[Path | str] | tuple = ()) -> Path:
    """Build the report of every run below ``runs_dir`` and the ``also`` directories (a grid split
    over several runs directories is merged as one); returns the path of report.md.

    ``stability``: the stiff-case battery's rows (``smgs.raster.stability.stiff_battery``); None runs the
    battery here if that module is importable; a string is the reason it was not computed.

    One build of a report folder runs at a time (``one_build``), and each reads the results once it
    runs: of two sweeps on one folder that end together, the report built last holds every result
    of both."""
    runs_dir = Path(runs_dir)
    # resolved (also "." and symlinks): the folder itself is swapped, beside it in its parent (``_write``)
    out = (Path(out_dir) if out_dir is not None else runs_dir / "report").resolve()
    check_out(out)   # before anything is written beside it
    with one_build(out):
        return _build(runs_dir, out, stability, also)


@contextlib.contextmanager
def one_build(out: Path) -> Iterator[None]:
    """Hold the lock of the report folder ``out`` (``flock`` on ``.<out>.lock`` beside it, released
    by the kernel however its holder ends), waiting for another build of it to finish (said on
    stderr). With it held, what killed builds left beside ``out`` (half-built folders, a folder put
    aside by a swap) is no one's and is removed."""
    out.parent.mkdir(parents=True, exist_ok=True)
    with open(out.parent / f".{out.name}.lock", "a+") as f:
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            print(f"report: another build of {out} is running; waiting for it, then building with every result",
                  file=sys.stderr, flush=True)
            fcntl.flock(f, fcntl.LOCK_EX)
        try:
            for left in [*out.parent.glob(f".{out.name}.building-*"), *out.parent.glob(f".{out.name}.old-*")]:
                shutil.rmtree(left, ignore_errors=True)
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


def _build(runs_dir: Path, out: Path, stability: list[dict] | str | None, also: list[Path | str] | tuple) -> Path:
    loaded = load_runs(runs_dir, *also)
    runs = [x.result for x in loaded.runs]
    paper = load_paper()
    ctx = Context.of(runs, paper, Cells.loaded(loaded))   # every table's numbers: from this results table

    sections = [_guard(f"Table {i}", lambda f=f: f(runs, ctx))
                for i, f in enumerate((table1, table2, table3, table4, table5), start=1)]
    section_plots: dict[str, list[Plot]] = {}
    if wants_popping(runs):    # beside Table 4: rendering its scenes takes seconds, so only there
        pop, section_plots["popping"] = _guard("Popping", lambda: popping_section(runs), with_plots=True)
        sections.insert(4, pop)
    plots, plot_error = _guard_plots(lambda: _tradeoff_plots(runs, ctx.cells))
    diag, diag_plots = _guard("Softmax-GS diagnostics", lambda: diagnostics_section(runs, ctx), with_plots=True)

    computed_here = stability is None
    reason = None
    if stability is None:
        stability, reason = compute_stability()
    elif isinstance(stability, str):
        stability, reason = None, stability
    stab = stability_section(stability, reason, computed_here)

    files: dict[str, bytes] = {}
    for sec in [s for top in [*sections, diag, stab] for s in top.all()]:
        recs = sec.csv_records()
        if recs:
            files[f"tables/{sec.name}.csv"] = _csv(recs)
    run_records = _run_records(loaded)
    files["tables/runs.csv"] = _csv(run_records)
    for p in [*plots, *diag_plots, *(p for ps in section_plots.values() for p in ps)]:
        files[f"plots/{p.name}"] = p.png

    probed = sorted({str(row.get("backend")) for row in stability or [] if row.get("backend")}) if computed_here else []
    machine = this_machine(probed)   # once, for report.md and report.html alike
    md = _markdown(runs_dir, loaded, paper.error, sections, plots, plot_error, diag, diag_plots, stab, runs, files,
                   machine, section_plots)
    files[HTML] = html_report(runs_dir=runs_dir, out=out, loaded=loaded, paper_error=paper.error, tables=sections,
                              plot_error=plot_error, diag=diag, stab=stab, run_records=run_records,
                              csv_link=lambda name: _link(files, name), machine=machine, cells=ctx.cells).encode()
    _write(out, files, md)
    return out / REPORT


def _tradeoff_plots(runs: list[RunResult], cells: Cells) -> list[Plot]:
    plots = time_curves(runs)
    fps_pts, gs_pts = tradeoff_points(runs, cells)
    plots += pareto_plots(fps_pts, "psnr_vs_fps.png", "render FPS", True, True,
                          "PSNR against render FPS, one point per method × budget (dataset means as in Table 2; "
                          "one panel per dataset or pattern); the dashed line and rings mark the Pareto front "
                          "(higher PSNR at higher FPS), per preset; bars: ± sd over seeds.")
    plots += pareto_plots(gs_pts, "psnr_vs_gaussians.png", "#Gaussians", False, True,
                          "PSNR against the number of Gaussians, one point per method × budget (or cap); the "
                          "dashed line and rings mark the Pareto front (higher PSNR with fewer Gaussians), per "
                          "preset; bars: ± sd over seeds.")
    return plots


def _guard(name: str, build, with_plots: bool = False):
    """A section that raises becomes "could not be built: <error>" (traceback on stderr), so one bad
    value does not cost the user the rest of the report at the end of a sweep."""
    try:
        return build()
    except Exception as e:  # noqa: BLE001
        traceback.print_exc()
        sec = Section(name.lower().replace(" ", "_"), name, empty_reason=f"could not be built: {type(e).__name__}: {one_line(str(e), 300)} "
                                               "(a bug in reports/; the traceback went to stderr)")
        return (sec, []) if with_plots else sec


def _guard_plots(build) -> tuple[list[Plot], str | None]:
    try:
        return build(), None
    except Exception as e:  # noqa: BLE001
        traceback.print_exc()
        return [], f"{type(e).__name__}: {one_line(str(e), 300)}"


# ---- markdown -----------------------------------------------------------------------------------

def _markdown(runs_dir: Path, loaded: LoadedRuns, paper_error: str | None, sections: list[Section],
              plots: list[Plot], plot_error: str | None, diag: Section, diag_plots: list[Plot], stab: Section,
              runs: list[RunResult], files: dict[str, bytes], machine: dict[str, str],
              section_plots: dict[str, list[Plot]] | None = None) -> str:
    status = Counter(r.status for r in runs)
    when = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    out = ["# smgs report", "",
           ("Runs directories: " + ", ".join(md_text(Path(d).resolve()) for d in loaded.roots)
            if len(loaded.roots) > 1 else f"Runs directory: {md_text(runs_dir.resolve())}")
           + f" · built {when} · {len(runs)} results ("
           + ", ".join(f"{n} {s}" for s, n in sorted(status.items())) + ")", ""]
    presets = presets_summary(runs)
    if presets:
        out += [f"Protocol presets: {md_text(presets)}.", ""]
    out.append(f"Paper's numbers: {md_text(paper_error)}." if paper_error else
               "Paper's numbers: Softmax-GS paper, Tables 1–5 (reports/paper_tables/).")
    out += ["", READING_GUIDE, "", SEEDS_GUIDE, ""]
    out.append(_problems(loaded, runs))
    for sec in sections:
        out.append(sec.markdown(link=lambda name: _link(files, name)))
        for p in (section_plots or {}).get(sec.name, []):
            out += [f"![{p.caption}](plots/{p.name})", "", f"*{p.caption}*", ""]
    out.append("## Error against run time\n")
    if plots:
        for p in plots:
            out += [f"![{p.caption}](plots/{p.name})", "", f"*{p.caption}*", ""]
    elif plot_error:
        out.append(f"Not produced: the plots could not be drawn: {md_text(plot_error)} (traceback on stderr).\n")
    else:
        out.append("Not produced: no finished run records a training curve, FPS or Gaussian count.\n")
    out.append(diag.markdown(link=lambda name: _link(files, name)))
    for p in diag_plots:
        out += [f"![{p.caption}](plots/{p.name})", "", f"*{p.caption}*", ""]
    out.append(stab.markdown(link=lambda name: _link(files, name)))
    out += ["## Environment", "", environment_markdown(runs, machine)]
    return "\n".join(out).rstrip() + "\n"


def _link(files: dict[str, bytes], name: str) -> str | None:
    path = f"tables/{name}.csv"
    return path if path in files else None


def _problems(loaded: LoadedRuns, runs: list[RunResult]) -> str:
    bad = sorted((r for r in runs if r.status != "ok"), key=lambda r: (r.dataset, r.scene, r.method, r.budget, r.seed))
    out = ["## Runs that did not finish", ""]
    if not bad and not loaded.unreadable and not loaded.duplicates:
        return "\n".join(out + ["Every run finished.", ""])
    if bad:
        out += ["| Run | Status | Error |", "|:--|:--|:--|"]
        for r in bad[:MAX_LISTED_FAILURES]:
            key = f"{r.dataset}/{r.scene}/{r.method}/{r.budget}/seed{r.seed}" + \
                ("" if r.preset == "paper" else f" [{r.preset}]")
            out.append(f"| {md_text(key)} | {md_text(r.status)} | {md_text(one_line(r.error or 'no error recorded', 300))} |")
        if len(bad) > MAX_LISTED_FAILURES:
            out.append(f"\n… and {len(bad) - MAX_LISTED_FAILURES} more (tables/runs.csv lists every run).")
        out.append("")
    for path, err in loaded.unreadable:
        out.append(f"- Unreadable results file, left out: {md_text(path)}: {md_text(one_line(err, 300))}")
    for dropped, kept in loaded.duplicates:
        out.append(f"- Duplicate result for the same run, left out: {md_text(dropped)} (kept {md_text(kept)})")
    return "\n".join(out) + "\n"


# ---- files --------------------------------------------------------------------------------------

def _run_records(loaded: LoadedRuns) -> list[dict]:
    recs = []
    for run in sorted(loaded.runs, key=lambda x: str(x.path)):
        r = run.result
        recs.append({"dataset": r.dataset, "scene": r.scene, "method": r.method, "budget": r.budget,
                     "cap": pattern_cap(r) if is_pattern(r) else None, "seed": r.seed, "preset": r.preset,
                     "status": r.status, "error": r.error or "",
                     **{k: r.metrics.get(k) for k in ("psnr", "ssim", "lpips", "flip")},
                     "lpips_net": r.lpips_net, "num_gaussians": r.num_gaussians, "train_seconds": r.train_seconds,
                     "render_fps": r.render_fps, "render_device": r.render_device, "steps": r.steps,
                     "missing": "; ".join(f"{k}: {v}" for k, v in r.missing.items()),
                     "config_hash": r.config_hash, "path": str(run.path)})
    return recs


def _csv(records: list[dict]) -> bytes:
    fields: list[str] = []
    for rec in records:
        fields += [k for k in rec if k not in fields]
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=fields, lineterminator="\n")
    w.writeheader()
    for rec in records:
        w.writerow({k: _cell(rec.get(k)) for k in fields})
    return buf.getvalue().encode()


def _cell(v: object) -> object:
    if v is None:
        return ""
    if isinstance(v, float) and not math.isfinite(v):
        return ""
    return v


def _write(out: Path, files: dict[str, bytes], md: str) -> None:
    """The whole report is written into a new folder beside ``out`` and switched in for the old one
    at the end (``smgs.atomic.replace_dir``): a build that fails (a full disk, an error) leaves
    the previous report as it was, never new tables beside an old report.md. Files of the old
    folder that the report does not write (the user's own) are carried over; those of our own that
    the previous build listed in its manifest and this one does not produce are not. ``out`` is
    resolved and checked (``check_out``) by ``build_report``, its parent made by ``one_build``."""
    tmp = Path(tempfile.mkdtemp(dir=out.parent, prefix=f".{out.name}.building-"))
    try:
        os.chmod(tmp, 0o777 & ~umask())   # mkdtemp makes 0700; the report folder follows the umask
        for rel, data in files.items():
            atomic_write_bytes(tmp / rel, data)
        atomic_write_text(tmp / REPORT, md)
        atomic_write_text(tmp / MANIFEST, json.dumps(sorted(files)))
        if out.is_dir():
            _carry_over(out, tmp, set(files))
        replace_dir(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def check_out(out: Path) -> None:
    """Refuse a report folder that holds files and is not a report's: the swap would walk and relink
    a folder of other files (a runs folder, a home)."""
    if out.is_dir() and not ((out / MANIFEST).exists() or (out / REPORT).exists()) and any(out.iterdir()):
        raise FileExistsError(f"{out} holds files and is not a report folder (no {REPORT}); give --out a new "
                              "or empty folder, or the report folder of an earlier build")


def _carry_over(old: Path, new: Path, written: set[str]) -> None:
    """Link (or copy) into ``new`` every file of ``old`` that is not the report's: neither one this
    build wrote nor a table or plot of ours that the previous build's manifest lists."""
    try:
        listed = json.loads((old / MANIFEST).read_text())
    except (OSError, ValueError):
        listed = []
    stale = {str(rel) for rel in (listed if isinstance(listed, list) else []) if _ours(old, str(rel))}
    ours = written | stale | {REPORT, HTML, MANIFEST}
    for dirpath, dirnames, filenames in os.walk(old):
        here = Path(dirpath)
        rel_dir = here.relative_to(old)
        (new / rel_dir).mkdir(exist_ok=True)
        for name in filenames + [d for d in dirnames if (here / d).is_symlink()]:
            rel = (rel_dir / name).as_posix()
            src, dst = here / name, new / rel_dir / name
            if rel in ours or dst.exists() or dst.is_symlink() or name.startswith(f".{REPORT}.") or \
                    name.startswith(f".{HTML}."):
                continue
            if src.is_symlink():
                os.symlink(os.readlink(src), dst)
                continue
            try:
                os.link(src, dst)
            except OSError:
                shutil.copy2(src, dst)


def _ours(out: Path, rel: str) -> bool:
    """Only a file this code writes may be removed: ``tables/<name>.csv`` or ``plots/<name>.png``
    directly below the report folder (the manifest is data in a shared folder, never trusted)."""
    parts = Path(rel).parts
    if len(parts) != 2 or (parts[0], Path(parts[1]).suffix) not in (("tables", ".csv"), ("plots", ".png")):
        return False
    p = out / rel
    return p.is_file() and not p.is_symlink() and p.resolve().parent == (out / parts[0]).resolve()


def main(argv: list[str] | None = None) -> int:
    from reports.commands import build_parser

    args = build_parser().parse_args(argv)
    for d in args.runs_dir:
        if not d.is_dir():
            print(f"error: {d} is not a directory", file=sys.stderr)
            return 2
    stability = "skipped (--no-stability)" if args.no_stability else None
    try:
        path = build_report(args.runs_dir[0], args.out, stability=stability, also=args.runs_dir[1:])
    except OSError as e:   # a full disk, a folder without write permission: one line, naming the path
        out = args.out if args.out is not None else args.runs_dir[0] / "report"
        print(f"error: the report was not written ({e}); the previous report in {out}, if any, is left as it "
              "was", file=sys.stderr)
        return 1
    print(f"report: {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
