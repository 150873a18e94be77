"""Seeds in the report: mean ± sd (n), the spread of a dataset mean, paired differences with their
Student t interval (checked by hand), the spread-aware best / tie, and one seed changing nothing but a note."""

from __future__ import annotations

import csv
import math
import sys
from pathlib import Path

import pytest

from protocols.results import RunResult
from reports.build import build_report
from reports.aggregate import Cells, paired
from reports.runs import Value
from reports.stats import mean_of_means, t_quantile
from reports.table_model import TIE, Column, Row, Table, fixed
from reports.tables import dataset_means

sys.path.insert(0, str(Path(__file__).parent))
from reports_tree import make_seed_tree  # noqa: E402
from test_reports_build import footnote, row, section  # noqa: E402

T_975_2 = 4.302652729749557   # t_(0.975, 2), from a printed t table (4.303) to more digits


@pytest.fixture(scope="module")
def three(tmp_path_factory) -> tuple[Path, str]:
    root = make_seed_tree(tmp_path_factory.mktemp("seeds"))
    path = build_report(root, stability="not wanted here")
    return path, path.read_text()


def test_t_quantiles_match_the_printed_table():
    for df, t in ((1, 12.706), (2, 4.303), (3, 3.182), (4, 2.776), (9, 2.262), (29, 2.045)):
        assert t_quantile(0.975, df) == pytest.approx(t, abs=5e-4)
    assert t_quantile(0.975, 2) == pytest.approx(T_975_2, abs=1e-9)
    assert t_quantile(0.025, 2) == pytest.approx(-T_975_2, abs=1e-9)
    assert t_quantile(0.975, 100000) == pytest.approx(1.95996, abs=1e-4)   # the normal's
    with pytest.raises(ValueError):
        t_quantile(0.975, 0)


# t quantiles of the report before it used scipy (9235246: its own t density, Simpson's rule, bisection):
# right to ~1e-12, so scipy's must agree with them
BEFORE_SCIPY = {(0.975, 1): 12.706204736174936, (0.975, 2): 4.302652729749557, (0.975, 3): 3.1824463052838103,
                (0.975, 4): 2.7764451051978405, (0.975, 9): 2.2621571627981893, (0.975, 29): 2.0452296421327034,
                (0.95, 2): 2.9199855803537673, (0.995, 5): 4.032142983555801, (0.9, 1): 3.07768353717523}


def test_t_quantiles_are_scipys_and_agree_with_the_report_before():
    from scipy import stats

    for (p, df), before in BEFORE_SCIPY.items():
        assert t_quantile(p, df) == float(stats.t.ppf(p, df))
        assert t_quantile(p, df) == pytest.approx(before, rel=1e-12, abs=0)


def test_paired_interval_by_hand():
    # blocks: Softmax-GS − 3D GS per seed = 31.0 − 30.0, 31.9 − 30.4, 31.8 − 29.8 = 1.0, 1.5, 2.0
    # mean 1.5; sd = √(((−0.5)² + 0² + 0.5²) / 2) = √0.25 = 0.5; se = 0.5 / √3 = 0.288675
    # half width = 4.302653 · 0.288675 = 1.242069 → [0.257931, 2.742069]: excludes 0
    p = paired([(0, 31.0), (1, 31.9), (2, 31.8)], [(0, 30.0), (1, 30.4), (2, 29.8)])
    assert p.n == 3 and p.mean == pytest.approx(1.5) and p.sd == pytest.approx(0.5)
    assert p.low == pytest.approx(1.5 - T_975_2 * 0.5 / math.sqrt(3)) == pytest.approx(0.257931, abs=1e-6)
    assert p.high == pytest.approx(2.742069, abs=1e-6) and p.excludes_zero
    # seeds pair by number; a seed one side lacks is left out and named
    q = paired([(0, 2.0), (1, 3.0), (5, 9.0)], [(0, 1.0), (1, 1.0)])
    assert [s for s, _ in q.diffs] == [0, 1] and q.only_a == (5,) and q.only_b == ()
    one = paired([(0, 2.0)], [(0, 1.0)])
    assert one.n == 1 and one.low is None and not one.excludes_zero
    assert paired([(0, 1.0)], [(1, 1.0)]) is None


def test_dataset_mean_propagates_the_scene_spreads():
    # two scenes with sd 0.3 and 0.4: one seed's mean over both spreads by √(0.09 + 0.16) / 2 = 0.25
    assert mean_of_means([(20.0, 0.3), (30.0, 0.4)]) == (25.0, pytest.approx(0.25))
    assert mean_of_means([(20.0, 0.3), (30.0, None)]) == (25.0, None)

    def r(scene, seed, psnr):
        return RunResult(method="3dgs", dataset="tandt", scene=scene, budget="full", seed=seed, metrics={"psnr": psnr})
    runs = [r("train", 0, 20.0), r("train", 1, 21.0), r("truck", 0, 24.0), r("truck", 1, 24.0), r("truck", 2, 27.0)]
    v = dataset_means(Cells.of(runs), "tandt", ["psnr"]).values[("3dgs", "full", "paper")]["psnr"]
    # train 20.5 ± 0.7071 (2 seeds), truck 25.0 ± 1.7321 (3 seeds): mean 22.75, sd √(0.5 + 3) / 2 = 0.9354
    assert v.mean == pytest.approx(22.75) and v.std == pytest.approx(math.sqrt(3.5) / 2) and v.n == 2
    assert v.seeds == ((0, 22.0), (1, 22.5))          # per-seed dataset means over the seeds both scenes ran
    assert any("seeds per scene: train 2, truck 3" in n for n in v.notes)


def test_tables_2_and_5_show_mean_sd_n_and_the_paired_interval(three):
    path, md = three
    t5 = section(md, "Table 5")
    sg = row(t5, "| blocks | Softmax-GS [cpu]")
    g = row(t5, "| blocks | 3D GS [cpu]")
    # 31.0, 31.9, 31.8: mean 31.5667, sd √(0.48667 / 2) = 0.4933; 30.0, 30.4, 29.8: 30.0667 ± 0.3055
    assert "**31.57 ± 0.49**" in sg and "*30.07 ± 0.31*" in g   # lead 1.5 > spread 0.49: best, second
    assert "± is the standard deviation over seeds (n = 3 per value" in t5
    # fern: 20.30 ± 0.10 against 20.00 ± 0.50: a lead of 0.3 inside the spread is a tie, not a best
    assert "20.30 ± 0.10 (tie)" in row(t5, "| fern | Softmax-GS 5% [cpu]")
    assert "20.00 ± 0.50 (tie)" in row(t5, "| fern | 3D GS 5% [cpu]")
    paired5 = section(md, "Table 5")[t5.index("### Paired differences"):]
    line = row(paired5, "| blocks |")
    assert "| Softmax-GS − 3D GS [cpu]" in line and "+1.50 [+0.26, +2.74]✱" in line and "| 0, 1, 2 |" in line
    fern = row(paired5, "| fern |")
    # 0.3, −0.3, 0.9: mean 0.3, sd 0.6, half width 4.302653 · 0.6 / √3 = 1.490483 → [−1.19, +1.79], no ✱
    assert "+0.30 [-1.19, +1.79] |" in fern and "✱" not in fern
    assert "the paper's Table 2 A − B at this budget: +1.60 (Mip-NeRF360)" in footnote(paired5, fern, 4)
    t2 = section(md, "Table 2")
    assert "**31.57 ± 0.49**" in row(t2, "| dense | Softmax-GS [cpu]")
    assert "+1.50 [+0.26, +2.74]✱" in row(t2[t2.index("### Paired"):], "| procedural |")
    tables = path.parent / "tables"
    with (tables / "table5_paired.csv").open() as f:
        recs = {r["scene"]: r for r in csv.DictReader(f)}
    b = recs["blocks"]
    assert float(b["psnr"]) == pytest.approx(1.5) and float(b["psnr_std"]) == pytest.approx(0.5)
    assert float(b["psnr_ci_low"]) == pytest.approx(0.257931, abs=1e-6) and b["psnr_excludes_0"] == "1"
    assert b["psnr_n"] == "3" and b["psnr_per_seed"] == "0:1;1:1.5;2:2" and b["a"] == "softmax_gs"
    assert recs["fern"]["psnr_excludes_0"] == "0"
    with (tables / "table5_per_scene.csv").open() as f:
        t5csv = [r for r in csv.DictReader(f) if r["scene"] == "fern"]
    assert {r["psnr_rank"] for r in t5csv} == {TIE} and {r["psnr_n"] for r in t5csv} == {"3"}
    html = (path.parent / "report.html").read_text()
    assert "31.57 ± 0.49" in html and "+1.50 [+0.26, +2.74]✱" in html and "20.30 ± 0.10 (tie)" in html


def test_one_seed_changes_nothing_but_a_note(tmp_path):
    md = build_report(make_seed_tree(tmp_path / "runs", seeds=(0,)), stability="x").read_text()
    for title in ("Table 2", "Table 3", "Table 5"):
        sec = section(md, title)
        cells = "\n".join(ln for ln in sec.splitlines() if ln.startswith("|"))
        assert "±" not in cells and "(tie)" not in cells
        assert "One seed per value: no spread available" in sec
    t5 = section(md, "Table 5")
    assert "**31.00**" in row(t5, "| blocks | Softmax-GS [cpu]") and "*30.00*" in row(t5, "| blocks | 3D GS [cpu]")
    assert "Not produced: one seed per run: a paired difference needs two or more seeds" in t5


def test_rank_with_spread():
    def table(vals):
        col = Column("psnr", "PSNR", fixed(2), "higher")
        return Table("", ["M"], [col], [Row([str(i)], {"psnr": Value(m, sd, 3 if sd else 1)})
                                         for i, (m, sd) in enumerate(vals)], seeds=True)
    assert table([(25.0, 0.2), (24.0, 0.3), (22.0, 0.3)]).ranks() == {(0, "psnr"): 1, (1, "psnr"): 2}
    # the runner-up within the spread of the third: no second
    assert table([(25.0, 0.2), (24.0, 0.3), (23.8, 0.3)]).ranks() == {(0, "psnr"): 1}
    # best within the spread: every value inside it ties, nobody is second
    assert table([(25.0, 0.5), (24.7, 0.1), (22.0, 0.1)]).ranks() == {(0, "psnr"): TIE, (1, "psnr"): TIE}
    # a one-seed value beside a seed mean: the mean's sd is the spread
    assert table([(25.0, None), (24.9, 0.2)]).ranks() == {(0, "psnr"): TIE, (1, "psnr"): TIE}
    md = table([(25.0, 0.2), (24.0, 0.3)]).markdown()
    assert "**25.00 ± 0.20**" in md and "*24.00 ± 0.30*" in md and "n = 3 per value" in md


def test_time_curves_show_the_seed_band(three):
    from reports.plots import seed_bands
    from reports.runs import load_runs

    runs = [x.result for x in load_runs(three[0].parent.parent).runs if x.result.scene == "blocks"]
    bands = {b.method: b for b in seed_bands(runs)}
    g = bands["3dgs"]
    assert g.seeds == [0, 1, 2] and g.steps == [100, 250, 500, 1000]
    assert (g.low[-1], g.high[-1]) == (29.8, 30.4) and g.mean[-1] == pytest.approx(30.0667, abs=1e-4)
    assert g.seconds[-1] == pytest.approx(61.0)   # 60, 61, 62 s: the mean
    html = (three[0].parent / "report.html").read_text()
    assert html.count('"fill":"toself"') == 4    # 2 methods × 2 scenes
    assert "a shaded band from the lowest to the highest seed" in three[1]


def test_table4_pairs_each_method_with_3dgs_and_flags_the_opposite_sign():
    from reports.paper import load_paper
    from reports.tables import Context, table4

    # bicycle, 3 seeds; paper: StopThePop − 3D GS FLIP = 0.028 − 0.032 = −0.004 (StopThePop ahead)
    flips = {"3dgs": (0.030, 0.031, 0.032), "stopthepop": (0.034, 0.036, 0.035), "softmax_gs": (0.030, 0.032, 0.031)}
    runs = [RunResult(method=m, dataset="mipnerf360", scene="bicycle", budget="full", seed=s, metrics={"psnr": 25.0},
                      consistency={"psnr": 25.0, "mse": 0.017, "flip": f[s], "estimator": "geometric"})
            for m, f in flips.items() for s in range(3)]
    md = table4(runs, Context.of(runs, load_paper())).markdown()
    sub = md[md.index("### Paired"):]
    stp = row(sub, "StopThePop − 3D GS")
    # d = 0.004, 0.005, 0.003: mean 0.004, sd 0.001, half width 4.302653 · 0.001 / √3 = 0.002484
    assert "+0.004 [+0.002, +0.006]✱ | -0.004" in stp
    assert "other side of the paper's difference" in footnote(sub, stp, 7)
    sg = row(sub, "Softmax-GS − 3D GS")
    # d = 0, 0.001, −0.001: mean 0, no ✱; the paper's −0.001 sits beside it without a footnote
    assert "+0.000 [-0.002, +0.002] | -0.001 |" in sg
    assert "| 0, 1, 2 |" in sg
