"""protocols.patterns: the Table 1 grid runner at a tiny size (a few steps, 12x12 targets)."""

import csv
from pathlib import Path

import pytest

from protocols.patterns import apply_overrides, main, ordering_checks, paper_table1, read_cells


def test_paper_values_from_the_reports_csv():
    t = paper_table1()
    assert len(t) == 3 * 4 * 6
    assert t[("circle4", "softmax_gs", 4)] == 28.91 and t[("rect4", "3dgs", 4096)] == 59.91
    assert t[("oval4", "gef_only", 16)] == 28.77


def test_overrides():
    cfg = {"gaussians": {"beta": {"init": 20.0}}, "steps": 3}
    apply_overrides(cfg, ["gaussians.beta.init=5", "steps=7"])
    assert cfg == {"gaussians": {"beta": {"init": 5}}, "steps": 7}
    with pytest.raises(KeyError, match="unknown key"):
        apply_overrides(cfg, ["gaussians.beta.int=5"])


def test_grid_writes_cells_tables_and_resumes(tmp_path, capsys):
    args = ["--patterns", "circle4", "oval4", "--methods", "softmax_gs", "3dgs", "--counts", "4",
            "--seeds", "0", "1", "--steps", "3", "--size", "12", "--out", str(tmp_path)]
    assert main(args) == 0
    rows = read_cells(tmp_path / "cells.csv")
    assert len(rows) == 8 and all(r["status"] == "ok" for r in rows)
    r = next(r for r in rows if r["pattern"] == "circle4" and r["method"] == "softmax_gs")
    assert float(r["paper_psnr"]) == 28.91 and float(r["psnr"]) > 0 and r["hparams"] == "3dgs2023+softmaxgs_patterns"
    assert abs(float(r["delta_vs_paper"]) - (float(r["psnr"]) - 28.91)) < 1e-2
    with (tmp_path / "table1.csv").open() as f:
        summary = list(csv.DictReader(f))
    assert len(summary) == 4 and {s["seeds"] for s in summary} == {"2"}
    md = (tmp_path / "table1.md").read_text()
    assert "## circle4" in md and "28.91" in md
    assert (tmp_path / "renders" / "oval4_3dgs_n4_s1.png").exists()
    capsys.readouterr()
    main(args)                                   # everything done: nothing re-runs
    assert "0 cell(s) to run" in capsys.readouterr().out
    assert len(read_cells(tmp_path / "cells.csv")) == 8


def test_two_runs_merge(tmp_path, capsys):
    common = ["--methods", "3dgs", "--counts", "4", "--seeds", "0", "--steps", "2", "--size", "12", "--no-renders"]
    main(["--patterns", "circle4", *common, "--out", str(tmp_path / "a")])
    main(["--patterns", "rect4", *common, "--out", str(tmp_path / "b")])
    main(["--merge", str(tmp_path / "a"), str(tmp_path / "b"), str(tmp_path / "a"), "--out", str(tmp_path / "m")])
    rows = read_cells(tmp_path / "m" / "cells.csv")
    assert sorted(r["pattern"] for r in rows) == ["circle4", "rect4"]
    with (tmp_path / "m" / "table1.csv").open() as f:
        assert len(list(csv.DictReader(f))) == 2
    assert "## rect4" in (tmp_path / "m" / "table1.md").read_text()


def test_ordering_check():
    rows = [dict(pattern="p", n_gaussians=4, method=m, psnr_mean=v)
            for m, v in (("softmax_gs", 30), ("gef_only", 25), ("softmax_only", 20), ("3dgs", 21))]
    (c,) = ordering_checks(rows)
    assert c["softmax_gs_best"] and c["gef_over_rest"] and c["order"].startswith("softmax_gs > gef_only")
    assert c["softmax_gs_vs_paper"] is None                       # no paper value in these rows
    rows[0]["paper_psnr"] = 31.25
    assert ordering_checks(rows)[0]["softmax_gs_vs_paper"] == -1.25
    rows[1]["psnr_mean"] = 20.5
    assert not ordering_checks(rows)[0]["gef_over_rest"]
    rows.append(dict(pattern="p", n_gaussians=4, method="softmax_gs [t_min=0]", psnr_mean=19))
    (v,) = ordering_checks(rows, "softmax_gs [t_min=0]")
    assert not v["softmax_gs_best"] and v["softmax_gs_row"] == "softmax_gs [t_min=0]"
