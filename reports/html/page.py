"""report.html: the report as one page that opens from disk with no server and no network.

The page holds its styles, its script, its data (one JSON element) and the plotting library
(plotly.js, read from the ``plotly`` package's bundled ``package_data/plotly.min.js``; the Python
package itself is never imported). The runs' images are referenced relative to the report's
directory. Sections mirror report.md.
"""

from __future__ import annotations

import importlib.util
from collections import Counter
from datetime import datetime, timezone
from pathlib import Path
from typing import Callable, Sequence

from protocols.results import RunResult
from reports.aggregate import Cells
from reports.environment import environment_rows, this_machine
from reports.html.escape import esc, script_json
from reports.html.figures import Figure, consistency_figures, params_figure, pareto_figures, run_name, time_figures
from reports.html.images import strips, viewers
from reports.html.tables_html import plain_table, records_table, section_html
from reports.html.videos import players
from reports.runs import LoadedRuns, one_line, presets_summary
from reports.table_model import SEEDS_GUIDE, Section

ASSETS = Path(__file__).resolve().parent / "assets"
RUN_COLUMNS = ["dataset", "scene", "method", "budget", "cap", "seed", "preset", "status", "psnr", "ssim", "lpips",
               "flip", "num_gaussians", "train_seconds", "render_fps", "steps", "error", "path"]
RUN_NUMERIC = ["cap", "seed", "psnr", "ssim", "lpips", "flip", "num_gaussians", "train_seconds", "render_fps", "steps"]


def plotly_js() -> tuple[str | None, str | None]:
    """(plotly.min.js, None) or (None, why not). Located without importing the plotly package."""
    spec = importlib.util.find_spec("plotly")
    if spec is None or not spec.submodule_search_locations:
        return None, "the plotly package is not installed (pip install plotly)"
    path = Path(list(spec.submodule_search_locations)[0]) / "package_data" / "plotly.min.js"
    try:
        js = path.read_text(encoding="utf-8")
    except OSError as e:
        return None, f"cannot read {path}: {e.strerror or e}"
    if "</script" in js.lower() or "<!--" in js:
        return None, f"{path} contains '</script' or '<!--' and cannot be inlined"
    return js, None


def html_report(*, runs_dir: Path, out: Path, loaded: LoadedRuns, paper_error: str | None,
                tables: Sequence[Section], plot_error: str | None, diag: Section, stab: Section,
                run_records: list[dict], csv_link: Callable[[str], str | None],
                machine: dict[str, str] | None = None, cells: Cells | None = None) -> str:
    """The page; ``cells``: the runs' results table where the caller made it (the trade-off points are
    computed from it, as report.md's are)."""
    runs = loaded.runs
    results = [x.result for x in runs]
    used: set[str] = set()

    def ids(name: str) -> str:  # unique, safe element ids
        base = "".join(ch if ch.isalnum() or ch in "-_" else "-" for ch in name) or "s"
        k, i = base, 2
        while k in used:
            k, i = f"{base}-{i}", i + 1
        used.add(k)
        return k

    figures: list[Figure] = []

    def plots(figs: list[Figure]) -> str:
        figures.extend(figs)
        return "\n".join(f'<h4>{esc(f.title)}</h4><div class="plot" id="{f.id}" role="img" aria-label="{esc(f.title)}">'
                         f'</div><p class="caption">{esc(f.caption)}</p>' for f in figs)

    body = [_header(runs_dir, results, paper_error), _problems(loaded, runs_dir)]
    body += [section_html(s, ids, csv_link) for s in tables]

    body.append(f'<h2 id="{ids("tradeoff")}">Error against run time</h2>')
    try:
        time_figs, pareto_figs = time_figures(runs, runs_dir), pareto_figures(runs, runs_dir, cells)
    except Exception as e:  # noqa: BLE001 - the rest of the page still matters
        time_figs, pareto_figs, plot_error = [], [], plot_error or f"{type(e).__name__}: {one_line(str(e), 300)}"
    if time_figs or pareto_figs:
        body += [plots(time_figs), plots(pareto_figs)]
    elif plot_error:
        body.append(f'<p class="empty">Not produced: the plots could not be drawn: {esc(plot_error)}</p>')
    else:
        body.append('<p class="empty">Not produced: no finished run records a training curve, FPS or Gaussian count.</p>')

    view_data = viewers(runs, runs_dir, out)
    body.append(f'<h2 id="{ids("test-views")}">Test views</h2>')
    if view_data:
        body.append("<p>Per scene: the ground truth, each method's render and its |render − ground truth| map (mean "
                    "over RGB of the 8-bit images; black 0, red → yellow → white at ≥ 0.25), for one configuration "
                    "(budget, seed) and test view at a time; \"flip\" shows them one at a time in the same place.</p>")
        body += [f'<h3>{esc(v["scene"])}</h3>' + (f'<p class="note">{esc(v["note"])}</p>' if v["note"] else "")
                 + f'<div class="viewer" id="{v["id"]}"></div>' for v in view_data]
    else:
        body.append('<p class="empty">Not produced: no finished run saved renders (eval.save_renders=false, or no '
                    'run finished).</p>')

    body.append(f'<h2 id="{ids("consistency-video")}">View consistency and popping along the video</h2>')
    player_data, no_video = players(runs, runs_dir, out)
    body += _players(player_data, no_video)
    cons = consistency_figures(runs, runs_dir)
    strip_data = strips(runs, runs_dir, out)
    if cons or strip_data:
        body.append("<p>Table 4 above has the means. Here: each frame pair's warped error along the video, and the "
                    "frames around the worst pair of each run.</p>")
        body.append(plots(cons))
        body += [_strip(s) for s in strip_data]
    else:
        body.append('<p class="empty">Not produced: no run computed view consistency (eval.consistency=true).</p>')

    body.append(section_html(diag, ids, csv_link))
    pf = params_figure(runs)
    if pf:
        body.append(plots([pf]))
    body.append(section_html(stab, ids, csv_link))

    body.append(f'<h2 id="{ids("runs")}">Every run</h2>')
    body.append('<p><label>Filter <input id="runs-filter" type="search" placeholder="text in any column"></label> '
                f'({len(run_records)} runs; tables/runs.csv has them too)</p>')
    body.append(records_table(run_records, RUN_COLUMNS, "runs-table", RUN_NUMERIC))
    body.append(_environment(results, machine))

    js, missing = plotly_js()
    data = {"figures": [f.spec() for f in figures], "viewers": view_data, "players": player_data,
            "plotly_missing": missing or ""}
    nav = _nav("\n".join(body))
    css = (ASSETS / "report.css").read_text(encoding="utf-8")
    script = (ASSETS / "report.js").read_text(encoding="utf-8")
    return "\n".join([
        "<!DOCTYPE html>", '<html lang="en"><head><meta charset="utf-8">',
        '<meta name="viewport" content="width=device-width, initial-scale=1">',
        # nothing leaves the page: no network request is allowed, inline script and local images only
        "<meta http-equiv=\"Content-Security-Policy\" content=\"default-src 'none'; img-src 'self' file: data: blob:; "
        "media-src 'self' file: blob:; "
        "style-src 'unsafe-inline'; script-src 'unsafe-inline' 'unsafe-eval'; font-src data:\">",
        f"<title>smgs report — {esc(runs_dir.name)}</title>", f"<style>{css}</style>",
        f"<script>{js}</script>" if js else "", "</head><body>", body[0], nav, *body[1:],
        f'<script type="application/json" id="report-data">{script_json(data)}</script>',
        f"<script>{script}</script>", "</body></html>", ""])


def _header(runs_dir: Path, runs: list[RunResult], paper_error: str | None) -> str:
    status = Counter(r.status for r in runs)
    when = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    out = ["<h1>smgs report</h1>",
           f"<p>Runs directory: <code>{esc(runs_dir.resolve())}</code> · built {when} · {len(runs)} results ("
           + esc(", ".join(f"{n} {s}" for s, n in sorted(status.items()))) + ")</p>"]
    presets = presets_summary(runs)
    if presets:
        out.append(f"<p>Protocol presets: {esc(presets)}.</p>")
    out.append(f"<p>Paper's numbers: {esc(paper_error)}.</p>" if paper_error else
               "<p>Paper's numbers: Softmax-GS paper, Tables 1–5 (reports/paper_tables/).</p>")
    out.append("<p>How to read the tables: each value of ours is followed by the paper's value and the difference "
               "(Δ = ours − paper; for counts, minutes and FPS ×paper = ours / paper). <strong>Bold</strong> is the best "
               "and <em>italics</em> the second best among rows that compete. \"—\" means there is no value; its "
               "footnote says why. \"[cpu]\" marks a row of a reduced protocol preset. Click a column header to sort; "
               "hover a plot for its runs; click a legend entry to hide or show a method.</p>")
    out.append(f"<p>{esc(SEEDS_GUIDE)}</p>")
    return "\n".join(out)


def _problems(loaded: LoadedRuns, runs_dir: Path) -> str:
    bad = sorted((x for x in loaded.runs if x.result.status != "ok"),
                 key=lambda x: (x.r.dataset, x.r.scene, x.r.method, x.r.budget, x.r.seed))
    out = ['<h2 id="problems">Runs that did not finish</h2>']
    if not bad and not loaded.unreadable and not loaded.duplicates:
        return out[0] + "<p>Every run finished.</p>"
    if bad:
        head = "".join(f'<th scope="col" class="txt">{h}</th>' for h in ("Run", "Status", "Error"))
        out.append(plain_table(head, (f'<tr><td class="txt">{esc(run_name(x, runs_dir))}</td><td class="txt">'
                                      f'{esc(x.r.status)}</td><td class="txt">{esc(x.r.error or "no error recorded")}'
                                      "</td></tr>" for x in bad), "problems-table"))
    items = [f"<li>Unreadable results file, left out: <code>{esc(p)}</code>: {esc(one_line(e, 300))}</li>"
             for p, e in loaded.unreadable]
    items += [f"<li>Duplicate result for the same run, left out: <code>{esc(d)}</code> (kept <code>{esc(k)}</code>)</li>"
              for d, k in loaded.duplicates]
    if items:
        out.append("<ul>" + "".join(items) + "</ul>")
    return "\n".join(out)


PLAYERS_GUIDE = (
    "Each method's flythrough along the view-consistency video, the frames exactly as the metric scored them "
    "(8-bit), side by side for one configuration at a time, in step: one play/pause and one timeline for all. "
    "The strip under the timeline is the flow-warped MSE of the pair (i → i+{step}) ending at each frame, one row "
    "per method (black 0 → red → yellow → white at the highest of the configuration; a blank cell: no pair ends there or none is scored); "
    "▼ marks the worst pair of all, a blue tick each method's worst. Click the strip to go to that frame. "
    "\"Warped error\" shows instead, over each frame dimmed, |frame i warped onto frame i+{step} − frame i+{step}| "
    "(mean over RGB; black 0 → red → yellow → white at ≥ 0.25, the scale of the test views' maps); darker still: "
    "pixels not scored (occluded, out of view, within 20 px of the border).")


def _players(player_data: list[dict], no_video: dict[str, list[tuple[str, str]]]) -> list[str]:
    """The video players of the consistency section, and why a scene's runs have no video."""
    out = []
    if player_data:
        steps = sorted({p["step"] for p in player_data})
        out.append(f"<p>{esc(PLAYERS_GUIDE.format(step='/'.join(map(str, steps))))}</p>")
    for p in player_data:
        out.append(f'<h3>{esc(p["scene"])}</h3><div class="player" id="{p["id"]}"></div>'
                   + (f'<p class="caption">{esc(p["cost"])}</p>' if p["cost"] else ""))
    if no_video:
        items = []
        for scene, lst in sorted(no_video.items()):
            by_reason: dict[str, list[str]] = {}
            for run, why in lst:
                by_reason.setdefault(why, []).append(run)
            for why, names in by_reason.items():
                shown = ", ".join(names[:3]) + (f" and {len(names) - 3} more" if len(names) > 3 else "")
                items.append(f"<li>{esc(scene)}: {len(names)} run{'s' if len(names) > 1 else ''} without a video "
                             f"({esc(shown)}): {esc(why)}</li>")
        out.append('<p class="note">Runs without a video:</p><ul class="novideo">' + "".join(items) + "</ul>")
    return out


def _strip(s: dict) -> str:
    frames = s.get("frames") or []
    what = (f"frames {frames[0]}–{frames[-1]}" if frames else "frames") + \
        (f", warped MSE of the pair {s['mse']:.4g}" if isinstance(s.get("mse"), (int, float)) else "")
    return (f'<figure class="strip"><img src="{esc(s["src"])}" alt="{esc(s["run"])} frame strip" loading="lazy" '
            f'decoding="async"><figcaption class="caption">{esc(s["scene"])} · {esc(s["method"])} · '
            f'<code>{esc(s["run"])}</code>: {esc(what)} ({esc(s["why"])})</figcaption></figure>')


def _environment(runs: list[RunResult], machine: dict[str, str] | None) -> str:
    rows = environment_rows(runs, machine if machine is not None else this_machine())
    head = "".join(f'<th scope="col" class="txt">{h}</th>' for h in ("", "runs", "this machine (report build)"))
    body = (f'<tr><th scope="row">{esc(a)}</th><td class="txt">{esc(b)}</td><td class="txt">{esc(c)}</td></tr>'
            for a, b, c in rows)
    return '<h2 id="environment">Environment</h2>' + plain_table(head, body, "environment-table")


def _nav(body: str) -> str:
    """Contents: every h2 of the page."""
    import re

    links = re.findall(r'<h2 id="([^"]+)">(.*?)</h2>', body)
    return "<nav><ul>" + "".join(f'<li><a href="#{i}">{t}</a></li>' for i, t in links) + "</ul></nav>"
