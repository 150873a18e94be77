"""report.html: built beside report.md from a fixture runs tree; self-contained; escaping; and, where a
Chromium is installed, opened headless from disk: no console error, every plot drawn, every image
loaded, a table sorted by a click, a screenshot saved."""

from __future__ import annotations

import json
import os
import re
from pathlib import Path
from urllib.parse import unquote

import pytest

from reports.build import build_report
from reports.html.escape import script_json
from reports_tree import (HOSTILE_ERROR, HOSTILE_METHOD, HOSTILE_PRESET, HOSTILE_SCENE, make_hostile_tree,
                          make_tree)

CHROMIUM_REASON = ""
try:
    from browser import Browser, find_chromium

    CHROMIUM, CHROMIUM_REASON = find_chromium()
except ImportError as e:  # pragma: no cover
    CHROMIUM, CHROMIUM_REASON = None, str(e)
needs_browser = pytest.mark.skipif(CHROMIUM is None, reason=f"browser test skipped: {CHROMIUM_REASON}")


@pytest.fixture(scope="module")
def built(tmp_path_factory) -> Path:
    root = make_tree(tmp_path_factory.mktemp("html") / "runs", images=True)
    md = build_report(root, stability="skipped")
    return md.parent / "report.html"


@pytest.fixture(scope="module")
def hostile(tmp_path_factory) -> Path:
    root = make_hostile_tree(tmp_path_factory.mktemp("hostile") / "runs")
    md = build_report(root, stability="skipped")
    return md.parent / "report.html"


def page_data(html: str) -> dict:
    m = re.search(r'<script type="application/json" id="report-data">(.*?)</script>', html, re.S)
    return json.loads(m.group(1))


def test_written_beside_report_md_and_in_the_manifest(built):
    out = built.parent
    assert (out / "report.md").is_file() and built.is_file()
    assert "report.html" in json.loads((out / ".report_files.json").read_text())


def test_self_contained_no_network(built):
    html = built.read_text()
    assert "plotly.js v" in html  # the library is inlined
    assert "<script src" not in html and "<link" not in html
    # no external resource in the page's own markup (the library's code has link texts, not loads):
    # every src/href is relative or a fragment
    own = re.sub(r"<script>/\*\*\s*\* plotly\.js.*?</script>", "", html, count=1, flags=re.S)
    assert len(own) < len(html) - 1_000_000
    for attr in re.findall(r'(?:src|href)="([^"]*)"', own):
        assert not re.match(r"^[a-z]+:|^//", attr), attr
    assert "default-src 'none'" in html  # a Content-Security-Policy that forbids network requests


def test_sections_mirror_report_md(built):
    html = built.read_text()
    for title in ("Table 1", "Table 2", "Table 3", "Table 4", "Table 5", "Error against run time", "Test views",
                  "View consistency and popping", "Softmax-GS diagnostics", "Numerical stability", "Every run",
                  "Environment", "Runs that did not finish"):
        assert title in html, title
    # the paper's value and Δ beside ours, and the footnotes of "—"
    assert "<th scope=\"col\" class=\"num\" title=\"sort\">paper</th>" in html and ">Δ</th>" in html
    assert "LPIPS missing: LPIPS weights not found" in html


def test_every_image_referenced_exists(built):
    out = built.parent
    data = page_data(built.read_text())
    paths = []
    for v in data["viewers"]:
        paths += list(v["gt"].values())
        for g in v["groups"]:
            for r in g["runs"]:
                paths += list(r["render"].values()) + list(r["error"].values())
    paths += re.findall(r'<img src="([^"]+)"', built.read_text())
    assert len(paths) >= 20
    for p in paths:
        assert not p.startswith("/") and (out / unquote(p)).is_file(), p
    assert {v["scene"] for v in data["viewers"]} == {"mipnerf360/bicycle", "mipnerf360/garden"}
    assert len(data["figures"]) >= 6


def test_hostile_strings_are_text(hostile):
    html = hostile.read_text()
    for raw in (HOSTILE_METHOD, HOSTILE_PRESET, HOSTILE_ERROR, "<b>bold"):
        assert raw not in html, raw
    assert "&lt;img src=x onerror=window.__pwned=1&gt;" in html
    assert html.count("<script") == 3  # plotly.js, the data, the page's script: nothing injected


def test_script_json_cannot_close_its_element():
    s = script_json({"a": "</script><!-- \u2028", "n": float("nan")})
    assert "<" not in s and ">" not in s and "\u2028" not in s
    assert json.loads(s) == {"a": "</script><!-- \u2028", "n": None}


# ---- in a browser ----------------------------------------------------------------------------------

# Each plot is scrolled into view and left there until the page has begun drawing it: the page draws a
# plot when its IntersectionObserver sees it, and on a loaded machine a plot passed in a fixed 30 ms
# could be scrolled away before the observer's next frame, never to be drawn ("timed out waiting for
# every plot drawn" at load 5-12). The bounds below are generous ceilings, never a fixed wait.
ALL_PLOTS = """(async () => {
  for (const d of document.querySelectorAll('.plot')) {
    d.scrollIntoView();
    const t0 = performance.now();
    while (!d.getAttribute('data-state') && performance.now() - t0 < 120000) await new Promise(r => setTimeout(r, 20));
  }
})()"""
PATIENCE = 300   # seconds: the most a step may take on a loaded machine before the test calls it stuck
PLOTS_DRAWN = "[...document.querySelectorAll('.plot')].every(d => d.getAttribute('data-state') === 'drawn')"
TRACES = "[...document.querySelectorAll('.plot')].map(d => d.querySelectorAll('g.trace').length)"
IMAGES = """(async () => {
  const bad = []; let n = 0;
  const check = async () => {
    for (const img of document.images) {
      img.scrollIntoView(); n += 1;
      try { await img.decode(); } catch (e) { bad.push(img.getAttribute('src')); continue; }
      if (!img.naturalWidth) bad.push(img.getAttribute('src'));
    }
  };
  await check();
  // every configuration and view of every viewer, side by side
  for (const v of document.querySelectorAll('.viewer')) {
    const [group, view, layout] = v.querySelectorAll('select');
    layout.value = 'grid'; layout.dispatchEvent(new Event('change'));
    for (let g = 0; g < group.options.length; g++) {
      for (let i = 0; i < view.options.length; i++) {
        group.value = String(g); view.value = String(i); view.dispatchEvent(new Event('change'));
        for (const img of v.querySelectorAll('img')) {
          img.scrollIntoView(); n += 1;
          try { await img.decode(); } catch (e) { bad.push(img.getAttribute('src')); continue; }
          if (!img.naturalWidth) bad.push(img.getAttribute('src'));
        }
      }
    }
  }
  return [n, bad, document.querySelectorAll('figure.broken').length];
})()"""
COLUMN = """[...document.querySelectorAll('#runs-table tbody tr')].map(tr => {
  const i = [...document.querySelectorAll('#runs-table thead th')].findIndex(th => th.textContent.trim().startsWith('psnr'));
  const s = tr.cells[i].getAttribute('data-sort'); return s === null ? null : parseFloat(s); })"""


def _sorted_with_blanks_last(vals: list, reverse: bool) -> bool:
    nums = [v for v in vals if v is not None]
    return vals == sorted(nums, reverse=reverse) + [None] * (len(vals) - len(nums))


@needs_browser
def test_report_in_a_headless_browser(built, tmp_path):
    shots = Path(os.environ.get("SMGS_SCREENSHOT_DIR") or tmp_path)
    shots.mkdir(parents=True, exist_ok=True)
    with Browser(CHROMIUM, timeout=PATIENCE) as b:
        b.open(built)
        b.wait_for("document.documentElement.getAttribute('data-report-ready') === '1'", what="the page's script")
        b.screenshot(shots / "report_top.png")
        n_plots = b.eval("document.querySelectorAll('.plot').length")
        assert n_plots == len(page_data(built.read_text())["figures"]) >= 6
        b.eval(ALL_PLOTS)
        b.wait_for(PLOTS_DRAWN, what="every plot drawn")
        assert all(n > 0 for n in b.eval(TRACES)), "a plot without traces"
        # hover names the run, method, budget, seed and value
        b.eval("(() => { const d = document.getElementById('fig-time-0'); d.scrollIntoView(); "
               "Plotly.Fx.hover(d, [{curveNumber: 0, pointNumber: 3}]); })()")
        b.wait_for("document.querySelector('#fig-time-0 .hovertext') !== null", what="a hover label")
        hover = b.eval("document.querySelector('#fig-time-0 .hovertext').textContent")
        for part in ("run mipnerf360/bicycle/3dgs/5pct/seed0", "method 3D GS", "budget 5pct", "seed 0", "PSNR 23.00 dB"):
            assert part in hover, (part, hover)
        b.screenshot(shots / "report_plot.png", "#fig-time-0")
        # a click on a legend entry hides that method's curves (every budget and seed)
        b.click("#fig-time-0 .legend .traces")
        b.wait_for("document.getElementById('fig-time-0').data.filter(t => t.legendgroup === '3dgs')"
                   ".every(t => t.visible === 'legendonly')", what="3D GS hidden by its legend entry")
        assert b.eval("document.getElementById('fig-time-0').data.filter(t => t.legendgroup === 'softmax_gs')"
                      ".every(t => t.visible !== 'legendonly')")

        n, bad, broken = b.eval(IMAGES)
        assert n >= 30 and bad == [] and broken == 0, bad
        b.screenshot(shots / "report_viewer.png", "#viewer-0")
        # flip between methods at the same view: the slider changes the one image shown
        b.eval("(() => { const s = document.querySelector('#viewer-0 select[aria-label=layout]'); s.value = 'flip'; "
               "s.dispatchEvent(new Event('change')); })()")
        first = b.eval("document.querySelector('#viewer-0 .flip img').getAttribute('src')")
        b.eval("(() => { const r = document.querySelector('#viewer-0 input[type=range]'); r.value = '0'; "
               "r.dispatchEvent(new Event('input')); })()")
        assert b.eval("document.querySelector('#viewer-0 .flip img').getAttribute('src')") != first
        assert "ground truth" in b.eval("document.querySelector('#viewer-0 .stage .cap').textContent")

        # sort the runs table by PSNR with a real click on its header, then back
        before = b.eval(COLUMN)
        assert not _sorted_with_blanks_last(before, False)
        b.click("#runs-table thead th:nth-child(9)")
        assert b.eval("document.querySelector('#runs-table thead th:nth-child(9)').textContent") == "psnr"
        assert _sorted_with_blanks_last(b.eval(COLUMN), False)
        b.click("#runs-table thead th:nth-child(9)")
        assert _sorted_with_blanks_last(b.eval(COLUMN), True)
        # a results table sorts by its numbers too (Table 5: PSNR)
        b.click("#table5_per_scene-t0 thead th:nth-child(3)")
        vals = b.eval("[...document.querySelectorAll('#table5_per_scene-t0 tbody tr')].map(tr => "
                      "{ const s = tr.cells[2].getAttribute('data-sort'); return s === null ? null : parseFloat(s); })")
        assert _sorted_with_blanks_last(vals, False) and len(vals) >= 6

        assert b.problems() == []
        b.screenshot(shots / "report_table.png", "#table5_per_scene-t0")
        # on a wide screen the every-run table takes the window's width, not the text column's 1400 px
        b.send("Emulation.setDeviceMetricsOverride", {"width": 2200, "height": 900, "deviceScaleFactor": 1,
                                                      "mobile": False}, session=True)
        box = b.eval("(() => { const r = document.getElementById('runs-table').parentElement.getBoundingClientRect(); "
                     "return [r.left, r.right]; })()")
        assert box[0] >= 0 and box[1] <= 2200 and box[1] - box[0] > 2000, box
        assert b.eval("getComputedStyle(document.querySelector('.empty') || document.body).color") != "rgb(170, 51, 51)"
    for name in ("report_top.png", "report_plot.png", "report_viewer.png", "report_table.png"):
        png = (shots / name).read_bytes()
        assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 5000, name


@needs_browser
def test_hostile_strings_stay_text_in_the_browser(hostile, tmp_path):
    with Browser(CHROMIUM, timeout=PATIENCE) as b:
        b.open(hostile)
        b.wait_for("document.documentElement.getAttribute('data-report-ready') === '1'", what="the page's script")
        b.eval(ALL_PLOTS)
        b.wait_for(PLOTS_DRAWN, what="every plot drawn")
        b.eval(IMAGES)
        assert b.eval("typeof window.__pwned") == "undefined"
        assert b.eval("document.querySelectorAll('img[src=x], img[onerror], b').length") == 0
        assert b.eval("document.querySelectorAll('script').length") == 3
        text = b.eval("document.body.innerText")
        for raw in (HOSTILE_METHOD, HOSTILE_PRESET, HOSTILE_ERROR, HOSTILE_SCENE):
            assert raw in text, raw
        legend = b.eval("[...document.querySelectorAll('.legendtext')].map(t => t.textContent)")
        assert HOSTILE_METHOD in legend
        hover = b.eval("(() => { const d = document.getElementById('fig-time-0'); d.scrollIntoView(); "
                       "const i = d.data.findIndex(t => t.name && t.name.includes('onerror')); "
                       "Plotly.Fx.hover(d, [{curveNumber: i, pointNumber: 0}]); "
                       "return document.querySelector('#fig-time-0 .hovertext').textContent; })()")
        assert f"method {HOSTILE_METHOD}" in hover, hover
        assert b.problems() == []
        shots = Path(os.environ.get("SMGS_SCREENSHOT_DIR") or tmp_path)
        shots.mkdir(parents=True, exist_ok=True)
        b.screenshot(shots / "report_hostile.png", "#problems-table")
