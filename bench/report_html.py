"""report.html at scale: build the report of a synthetic 200-run tree and open it in headless Chromium.

    python bench/report_html.py [--out /tmp/report200] [--screenshots DIR]

Prints the tree's size, the build time, report.html's size (and the share of plotly.js), and in the
browser: the time to the load event, to the page's script being ready, to every plot drawn (each
scrolled into view), images loaded at first paint, and the console problems. Not a test.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "tests")]

from browser import Browser, find_chromium  # noqa: E402
from reports.build import build_report  # noqa: E402
from reports.html.page import plotly_js  # noqa: E402
from reports_tree import make_large_tree  # noqa: E402


def du(path: Path) -> tuple[int, int]:
    files = [p for p in path.rglob("*") if p.is_file()]
    return len(files), sum(p.stat().st_size for p in files)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("/tmp/smgs-report200"))
    ap.add_argument("--screenshots", type=Path, default=None)
    args = ap.parse_args()
    if args.out.exists():
        shutil.rmtree(args.out)
    t0 = time.perf_counter()
    root = make_large_tree(args.out / "runs")
    n_files, n_bytes = du(root)
    print(f"tree: 200 runs, {n_files} files, {n_bytes / 1e6:.1f} MB, made in {time.perf_counter() - t0:.1f} s")
    t0 = time.perf_counter()
    md = build_report(root, stability="skipped (bench)")
    print(f"build_report: {time.perf_counter() - t0:.1f} s")
    html = md.parent / "report.html"
    js, _ = plotly_js()
    size = html.stat().st_size
    print(f"report.html: {size / 1e6:.2f} MB ({len(js or '') / 1e6:.2f} MB of it plotly.js), "
          f"report.md: {md.stat().st_size / 1e3:.0f} kB")
    exe, why = find_chromium()
    if exe is None:
        print(f"browser: not measured: {why}")
        return 0
    with Browser(exe) as b:
        t_load = b.open(html)
        t0 = time.perf_counter()
        b.wait_for("document.documentElement.getAttribute('data-report-ready') === '1'")
        t_ready = t_load + time.perf_counter() - t0
        counts = b.eval("[document.querySelectorAll('.plot').length, document.images.length, "
                        "[...document.images].filter(i => i.complete && i.naturalWidth > 0).length, "
                        "document.querySelectorAll('*').length]")
        drawn_first = b.eval("document.querySelectorAll('.plot[data-state=drawn]').length")
        if args.screenshots:
            args.screenshots.mkdir(parents=True, exist_ok=True)
            b.screenshot(args.screenshots / "r200_top.png")
        t0 = time.perf_counter()
        b.eval("(async () => { for (const d of document.querySelectorAll('.plot')) { d.scrollIntoView(); "
               "await new Promise(r => setTimeout(r, 20)); } })()", timeout=300)
        b.wait_for("[...document.querySelectorAll('.plot')].every(d => d.getAttribute('data-state') === 'drawn')",
                   timeout=300)
        t_plots = time.perf_counter() - t0
        print(f"browser ({exe}): load event {t_load:.2f} s, script ready {t_ready:.2f} s; {counts[0]} plots "
              f"({drawn_first} drawn before scrolling), all drawn after scrolling through in {t_plots:.1f} s; "
              f"{counts[1]} <img> in the DOM at load, {counts[2]} loaded (lazy); {counts[3]} elements")
        t0 = time.perf_counter()
        b.click("#runs-table thead th:nth-child(9)")
        b.eval("1")
        print(f"sort of the 200-row runs table by a click: {1e3 * (time.perf_counter() - t0):.0f} ms (round trip)")
        if args.screenshots:
            for name, sel in (("r200_pareto", "#fig-fps-0"), ("r200_viewer", "#viewer-0"), ("r200_table2", "#table2_realworld-t0"),
                              ("r200_consistency", "#fig-cons-0"), ("r200_strip", "figure.strip")):
                b.screenshot(args.screenshots / f"{name}.png", sel)
            b.eval("(() => { const s = document.querySelector('#viewer-0 select[aria-label=layout]'); s.value = 'flip'; "
                   "s.dispatchEvent(new Event('change')); })()")
            time.sleep(0.5)
            b.screenshot(args.screenshots / "r200_flip.png", "#viewer-0")
        problems = b.problems()
        print(f"console problems: {len(problems)}" + "".join(f"\n  {p}" for p in problems[:10]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
