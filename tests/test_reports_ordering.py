"""Table 1 through the report alone: the ordering check (Softmax-GS > GEF-only > {softmax-only,
3DGS} on seed means) and a grid run apart in two runs directories merged into one report."""

from __future__ import annotations

import csv
import sys
from pathlib import Path

from reports.build import main
from reports.ordering import ordering, ordering_section

sys.path.insert(0, str(Path(__file__).parent))
from report_golden import case_apart  # noqa: E402


def _block(md: str, title: str) -> str:
    start = md.index(title)
    nxt = md.find("\n## ", start + 3)
    return md[start: nxt if nxt > 0 else len(md)]


def test_ordering_check():
    means = {"softmax_gs": 30.0, "gef_only": 25.0, "softmax_only": 20.0, "3dgs": 21.0}
    assert ordering(means) == {"softmax_gs_best": True, "gef_over_rest": True,
                               "order": "softmax_gs > gef_only > 3dgs > softmax_only"}
    assert ordering({**means, "gef_only": 20.5}) == {"softmax_gs_best": True, "gef_over_rest": False,
                                                     "order": "softmax_gs > 3dgs > gef_only > softmax_only"}
    assert not ordering({**means, "3dgs": 30.5})["softmax_gs_best"]
    sec = ordering_section({("p", 4, "paper"): means, ("p", 16, "paper"): {"3dgs": 1.0}},
                           {("p", 4): 31.25})
    (rec,) = sec.csv_records()       # the cap without all four methods is not checked
    assert (rec["pattern"], rec["cap"], rec["softmax_gs_vs_paper"]) == ("p", 4, -1.25)
    assert (rec["softmax_gs_best"], rec["gef_over_rest"], rec["within_paper_slack"]) == (True, True, True)
    assert rec["order"] == "softmax_gs > gef_only > 3dgs > softmax_only" and rec["psnr_3dgs"] == 21.0
    assert ordering_section({("p", 4, "paper"): means}, {("p", 4): 31.6}).csv_records()[0]["within_paper_slack"] is False
    assert ordering_section({}, {}).empty_reason.startswith("no pattern and cap with seed means of all four")


def test_a_grid_run_apart_is_one_table1(tmp_path):
    case_apart(tmp_path)   # the four methods of a Table 1 grid, run apart in tmp_path/a and tmp_path/b
    out = tmp_path / "report"
    assert main([str(tmp_path / "a"), str(tmp_path / "b"), "--out", str(out), "--no-stability"]) == 0
    md = (out / "report.md").read_text()
    assert f"Runs directories: {(tmp_path / 'a').resolve()}, {(tmp_path / 'b').resolve()}" in md
    t1 = _block(md, "## Table 1 —")
    assert "**circle4**" in t1 and "**rect4**" in t1
    order = _block(md, "### Table 1 — ordering check (seed means)")
    gt = " &gt; "    # report.md escapes HTML
    order_text = gt.join(("softmax_gs", "gef_only", "softmax_only", "3dgs"))
    assert f"| circle4 | 4 | paper | +0.59 | yes | yes | yes | {order_text} |" in order   # paper 28.91
    assert f"| rect4 | 4 | paper | +4.84 | yes | yes | yes | {order_text} |" in order     # paper 24.66
    with (out / "tables" / "table1_ordering.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert [(r["pattern"], float(r["psnr_softmax_gs"])) for r in rows] == [("circle4", 29.5), ("rect4", 29.5)]


def test_paper_table1_values_the_report_compares_with():
    from reports.paper import load_paper

    p = load_paper()
    assert len(p.table1) == 3 * 4 * 6
    assert p.t1("circle4", "softmax_gs", 4) == 28.91 and p.t1("rect4", "3dgs", 4096) == 59.91
    assert p.t1("oval4", "gef_only", 16) == 28.77
