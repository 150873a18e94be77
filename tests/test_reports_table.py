"""Units of the report: ranking, footnotes, formats, aggregation, the paper's numbers, Pareto fronts."""

from __future__ import annotations

import pytest

from protocols.results import RunResult
from reports.paper import load_paper, paper_key, row_label
from reports.plots import pareto_front
from reports.aggregate import Cells, seed_means
from reports.runs import Value, pattern_cap
from reports.table_model import Column, Row, Table, count, fixed, ratio_text
from reports.tables import dataset_means


def _table(values: list[float | None], better: str = "higher", groups=None) -> Table:
    col = Column("psnr", "PSNR", fixed(2), better, "diff", 2)
    rows = [Row([f"m{i}"], {"psnr": Value(v, n=1) if v is not None else Value.absent("failed: boom")},
                {"psnr": Value(20.0, n=1)}, rank_group=(groups[i] if groups else ()))
            for i, v in enumerate(values)]
    return Table("", ["Method"], [col], rows)


def test_rank_best_second_ties_and_direction():
    t = _table([25.0, 26.004, 26.0, 24.0])
    r = t.ranks()
    assert r[(1, "psnr")] == 1 and r[(2, "psnr")] == 1  # equal as printed: a tie
    assert r[(0, "psnr")] == 2 and (3, "psnr") not in r
    low = _table([0.3, 0.2, 0.25], better="lower").ranks()
    assert low == {(1, "psnr"): 1, (2, "psnr"): 2}


def test_rank_groups_and_single_values_unranked():
    t = _table([25.0, 26.0, 30.0, None], groups=["a", "a", "b", "b"])
    r = t.ranks()
    assert r == {(1, "psnr"): 1, (0, "psnr"): 2}  # group b has one value: nothing to rank
    assert _table([25.0, 25.001, 24.999]).ranks() == {}  # all equal as printed: nothing stands out


def test_markdown_cells_footnotes_and_delta():
    md = _table([25.0, None, 22.5]).markdown()
    lines = md.splitlines()
    assert lines[0] == "| Method | PSNR | paper | Δ |"
    assert "| m0 | **25.00** | 20.00 | +5.00 |" in md
    assert "| m1 | —¹ | 20.00 |  |" in md
    assert "| m2 | *22.50* | 20.00 | +2.50 |" in md
    assert "¹ failed: boom" in md


def test_ratio_columns_and_pipe_escape():
    col = Column("n", "#GS", count, None, "ratio")
    t = Table("", ["Method"], [col], [Row(["a|b"], {"n": Value(2_500_000.0, n=1)}, {"n": Value(2_000_000.0)})])
    md = t.markdown()
    assert "| a\\|b | 2500K | 2000K | ×1.25 |" in md
    assert t.records()[0]["ratio_n"] == pytest.approx(1.25)
    assert count(4) == "4" and count(104_000) == "104K"
    assert [ratio_text(x) for x in (1.0, 0.926, 0.0012, 150.4)] == ["×1.00", "×0.93", "×0.0012", "×150"]


def test_no_compare_marks_delta():
    t = _table([25.0])
    t.rows[0].no_compare["psnr"] = "LPIPS net alex; the paper's is VGG"
    md = t.markdown()
    assert "n/c¹" in md and "¹ LPIPS net alex" in md
    assert t.records()[0]["delta_psnr"] is None


def _run(seed: int, psnr: float | None, status: str = "ok", **kw) -> RunResult:
    return RunResult(method="softmax_gs", dataset="mipnerf360", scene="bicycle", budget="full", seed=seed,
                     status=status, metrics={} if psnr is None else {"psnr": psnr}, **kw)


def _mean(runs: list[RunResult], name: str = "psnr") -> Value:
    """The seed mean of one row (the runs' method), from the results table of ``runs``."""
    return seed_means(Cells.of(runs), ["method"], [name]).get(("softmax_gs",), name)


def test_seed_means_partial_and_absent():
    v = _mean([_run(0, 20.0), _run(1, 22.0)])
    assert v.mean == 21.0 and v.std == pytest.approx(2 ** 0.5) and v.n == 2 and not v.notes
    part = _mean([_run(0, 20.0), _run(1, None, "failed", error="ValueError: x")])
    assert part.mean == 20.0 and part.notes == ("1 of 2 seeds; failed: ValueError: x",)
    none = _mean([_run(0, None, "failed", error="E: a"), _run(1, None, "failed", error="E: b")])
    assert not none.ok and none.reason == "seed 0: failed: E: a; seed 1: failed: E: b"
    nan = _mean([_run(0, float("nan"))])
    assert not nan.ok and nan.reason == "PSNR recorded as nan"
    assert _mean([_run(0, None)]).reason == "PSNR not recorded"
    lp = _mean([_run(0, 20.0, missing={"lpips": "weights absent"})], "lpips")
    assert lp.reason == "LPIPS missing: weights absent"
    assert _mean([]).reason == "no result in the runs directory"


def test_consistency_values_and_missing():
    r = _run(0, 25.0, consistency={"psnr": 25.1, "mse": {"missing": "empty mask"}, "flip_minsub": 0.01,
                                   "flip_name": "flip_minsub", "estimator": "opencv"})
    def q(r: RunResult, name: str):
        return Cells.of([r]).quantity(name).iloc[0]
    assert q(r, "consistency_psnr").value == 25.1
    assert q(r, "consistency_mse").reason == "mse missing: empty mask"
    assert q(r, "consistency_flip").value == 0.01
    assert q(_run(0, 25.0), "consistency_mse").reason == "view consistency not computed"
    no_psnr = _run(0, 24.0, consistency={"mse": 0.1, "estimator": "geometric"})
    assert q(no_psnr, "consistency_psnr").value == 24.0        # the test-view PSNR, the same quantity
    assert q(no_psnr, "consistency_flip").reason == "flip not recorded"
    nan = _run(0, 24.0, consistency={"psnr": float("nan"), "mse": "n/a", "estimator": "geometric"})
    assert q(nan, "consistency_psnr").reason == "psnr recorded as nan"
    assert q(nan, "consistency_mse").reason == "mse not a number ('n/a')"


def test_pattern_cap_conventions():
    base = dict(method="3dgs", dataset="patterns", scene="circle4", seed=0)
    assert pattern_cap(RunResult(budget="cap", config={"cap": 64}, **base)) == 64
    assert pattern_cap(RunResult(budget="cap256", config={"budget": {"cap": 256}}, **base)) == 256
    assert pattern_cap(RunResult(budget="cap1024", **base)) == 1024
    assert pattern_cap(RunResult(budget="cap", num_gaussians=16, **base)) == 16


def test_paper_numbers():
    p = load_paper()
    assert p.error is None
    assert p.t1("oval4", "softmax_gs", 4096) == 50.37
    assert p.t2("softmax_gs", "5pct", "tandt", "psnr") == 22.0
    assert p.t2("3dgs", "full", "mipnerf360", "num_gaussians") == 2593000
    assert p.t3("softmax_gs", "mini", "bicycle", "render_fps") == 152
    assert p.t4("3dgs", "full", "train", "flip") == 0.048
    assert p.t5("softmax_gs", "full", "drjohnson", "num_gaussians") == 2900000
    assert p.t2("gef_only", "full", "mipnerf360", "psnr") is None
    assert paper_key("softmax_gs", "cap") is None and paper_key("3dgs", "light") == "3dgs_light"
    assert row_label("softmax_gs", "5pct") == "Softmax-GS 5%" and row_label("3dgs", "full") == "3D GS"
    broken = load_paper("/nonexistent")
    assert broken.error and "not readable" in broken.error and broken.t1("circle4", "3dgs", 4) is None


def test_dataset_means_over_common_scenes_only():
    def r(m, scene, psnr, status="ok"):
        return RunResult(method=m, dataset="tandt", scene=scene, budget="full", seed=0, status=status,
                         error=None if status == "ok" else "boom", metrics={"psnr": psnr} if psnr else {})
    runs = [r("3dgs", "train", 22.0), r("3dgs", "truck", 25.0), r("softmax_gs", "train", 23.0),
            r("softmax_gs", "truck", None, "failed")]
    dm = dataset_means(Cells.of(runs), "tandt", ["psnr"])
    assert dm.common["paper"] == ["train"]
    assert dm.values[("3dgs", "full", "paper")]["psnr"].mean == 22.0  # truck left out for both rows
    assert "mean over 1 of 2 scenes" in dm.subset_note[("3dgs", "full", "paper")]
    full = dataset_means(Cells.of(runs[:2] + [r("softmax_gs", "truck", 26.0), runs[2]]), "tandt", ["psnr"])
    assert full.values[("softmax_gs", "full", "paper")]["psnr"].mean == 24.5 and not full.subset_note


def test_pareto_front():
    pts = [(10.0, 20.0), (20.0, 19.0), (5.0, 25.0), (30.0, 18.0), (15.0, 18.5)]
    assert sorted(pareto_front(pts, x_higher_better=True)) == [0, 1, 2, 3]  # (15, 18.5) is beaten by (20, 19)
    assert sorted(pareto_front(pts, x_higher_better=False)) == [2]           # fewest and best
