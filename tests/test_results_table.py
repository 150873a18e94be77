"""smgs.results / smgs.curves: every cell of a runs folder as a pandas DataFrame, with pinned columns
and dtypes; failed and skipped cells are rows with their reason; several experiments in one folder;
per-view rows; the curves' long table; bad input named; ``import smgs`` does not load pandas."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

import smgs
from protocols.results import RunResult, read_result, write_result

sys.path.insert(0, str(Path(__file__).parent))
from reports_tree import MISSING_DATA, NO_LPIPS, OOM, make_seed_tree, make_tree  # noqa: E402

# The documented columns (docs/reports.md, "Results as data"), written out here so that a change to
# the table is a change to this test too.
KEYS = {"method": "string", "dataset": "string", "scene": "string", "budget": "string", "cap": "Int64",
        "preset": "string", "seed": "int64", "experiment": "string"}
CELL = {**KEYS, "status": "string", "reason": "string",
        "psnr": "float64", "ssim": "float64", "lpips": "float64", "flip": "float64",
        "psnr_missing": "string", "ssim_missing": "string", "lpips_missing": "string", "flip_missing": "string",
        "lpips_net": "string", "num_gaussians": "Int64", "train_seconds": "float64", "build_seconds": "float64",
        "render_fps": "float64", "peak_memory_mb": "float64", "steps": "Int64",
        "consistency_psnr": "float64", "consistency_mse": "float64", "consistency_flip": "float64",
        "consistency_pop_ratio": "float64", "consistency_popped_fraction": "float64",
        "consistency_psnr_missing": "string", "consistency_mse_missing": "string",
        "consistency_flip_missing": "string", "consistency_pop_ratio_missing": "string",
        "consistency_popped_fraction_missing": "string", "consistency_flip_name": "string",
        "consistency_flow": "string", "consistency_mask": "string", "frac_within_kmax": "float64",
        "collapsed": "boolean", "device": "string", "render_device": "string", "backend": "string",
        "renderer": "string", "threads": "Int64", "config_hash": "string", "inputs_fingerprint": "string",
        "source": "string", "git": "string", "path": "string"}
VIEW = {**KEYS, "status": "string", "reason": "string", "view": "string", "view_index": "Int64",
        "psnr": "float64", "ssim": "float64", "lpips": "float64", "flip": "float64", "path": "string"}
CURVE = {**KEYS, "step": "int64", "seconds": "float64", "psnr": "float64", "num_gaussians": "Int64", "path": "string"}


def _dtypes(df) -> dict[str, str]:
    return {c: str(t) for c, t in df.dtypes.items()}


@pytest.fixture(scope="module")
def sweeps(tmp_path_factory) -> Path:
    """Two experiments in one runs folder: the report fixture tree and three seeds of two methods."""
    root = tmp_path_factory.mktemp("results")
    make_tree(root / "main", images=True)
    make_seed_tree(root / "seeds")
    for p in (root / "seeds").rglob("results.json"):
        r = read_result(p)
        r.config["experiment_name"] = "seeds"
        r.diagnostics["train_conditions"] = {"threads": 2, "cells_in_parallel": 1}
        write_result(p.parent, r)
    return root


def test_one_row_per_cell_with_pinned_columns(sweeps):
    df = smgs.results(sweeps)
    assert _dtypes(df) == CELL
    # 21 cells of the main tree + 12 of the seed tree, less the two fern seed-0 cells both hold
    assert len(df) == 31 and not df.duplicated(["method", "dataset", "scene", "budget", "cap", "preset", "seed"]).any()
    assert len(df.attrs["duplicates"]) == 2 and df.attrs["unreadable"] == []
    both = smgs.results([sweeps / "main", sweeps / "seeds"])    # a list of runs folders, as one
    assert both.drop(columns="path").equals(df.drop(columns="path"))
    assert df["status"].value_counts().to_dict() == {"ok": 28, "failed": 2, "skipped": 1}
    assert df.loc[df.experiment == "seeds", "threads"].eq(2).all() and df.experiment.isna().sum() == 19


def test_failed_and_skipped_cells_are_rows_with_their_reason(sweeps):
    df = smgs.results(sweeps).set_index(["dataset", "scene", "method", "budget"])
    oom = df.loc[("mipnerf360", "garden", "softmax_gs", "full")]
    assert oom.status == "failed" and oom.reason == OOM and math.isnan(oom.psnr) and oom.num_gaussians is smgs_na()
    assert oom.psnr_missing is smgs_na()        # the reason column says why, not a per-metric one
    skipped = df.loc[("tandt", "train", "softmax_gs", "full")]
    assert skipped.status == "skipped" and skipped.reason == MISSING_DATA
    assert df.loc[("mipnerf360", "bicycle", "3dgs", "full"), "reason"] is smgs_na()


def smgs_na():
    import pandas as pd

    return pd.NA


def test_values_and_why_a_value_is_missing(sweeps):
    df = smgs.results(sweeps)
    bike = df[(df.scene == "bicycle") & (df.method == "3dgs")].set_index("budget")
    assert bike.loc["5pct", "lpips_missing"] == NO_LPIPS and math.isnan(bike.loc["5pct", "lpips"])
    assert bike.loc["full", "lpips"] == pytest.approx(0.3) and bike.loc["full", "lpips_net"] == "lpips_vgg_v0.1"
    assert bike.loc["full", "consistency_flip"] == 0.032 and bike.loc["full", "consistency_flow"] == "geometric"
    assert bike.loc["full", "consistency_pop_ratio"] == 41.0 and bike.loc["full", "consistency_mask"] == "per-method"
    assert bike.loc["5pct", "consistency_flow"] is smgs_na()        # consistency not computed
    assert bike.loc["full", "num_gaussians"] == 4_600_000 and bike.loc["full", "train_seconds"] == 2700.0
    assert bike.loc["full", "render_fps"] == 50.0 and bike.loc["full", "steps"] == 30000
    fits = df[(df.dataset == "patterns") & (df.method == "softmax_gs")]
    assert sorted(fits.cap) == [4, 4, 16, 16] and set(fits.budget) == {"cap"}   # the cap from config["cap"]
    fern = df[(df.scene == "fern") & (df.method == "3dgs")].set_index("seed")
    assert fern.loc[0, "backend"] == "cpu" and fern.loc[0, "psnr"] == 20.0   # the seed sweep's copy, kept
    ref = df[(df.dataset == "colmap")]
    assert (ref.preset == "cpu").all() and ref.device.eq("cpu").all()


def test_a_recorded_nan_and_a_text_are_told_from_not_recorded(tmp_path):
    write_result(tmp_path / "a", RunResult(method="3dgs", dataset="d", scene="s", budget="full", seed=0,
                                           metrics={"psnr": float("nan"), "ssim": "n/a"}, config_hash="abc",
                                           inputs={"files": {"a.png": {"size": 3, "sha256": "beef"}},
                                                   "digest": "f00d", "folder": "/x"}))
    (row,) = smgs.results(tmp_path).itertuples()
    assert math.isnan(row.psnr) and row.psnr_missing is smgs_na()      # recorded as NaN: kept
    assert row.ssim_missing == "not a number ('n/a')" and row.lpips_missing == "not recorded"
    assert row.config_hash == "abc" and row.inputs_fingerprint == "f00d" and not row.collapsed


def test_per_view_rows(sweeps):
    v = smgs.results(sweeps, per_view=True)
    assert _dtypes(v) == VIEW
    bike = v[(v.scene == "bicycle") & (v.method == "softmax_gs") & (v.budget == "full")]
    assert list(bike.view) == ["_DSC8679.JPG", "_DSC8687.JPG", "_DSC8695.JPG"] and list(bike.view_index) == [0, 1, 2]
    assert list(bike.psnr) == pytest.approx([25.3, 25.8, 26.3])
    # a cell without per-view values (failed, or not saved) is one row with no view, never dropped
    cells = smgs.results(sweeps)
    assert v.groupby("path").ngroups == len(cells)
    failed = v[v.status == "failed"]
    assert len(failed) == 2 and failed.view.isna().all() and failed.reason.notna().all()


def test_the_curves_long_table(sweeps):
    c = smgs.curves(sweeps)
    assert _dtypes(c) == CURVE
    one = c[(c.scene == "blocks") & (c.method == "3dgs") & (c.seed == 0)]
    assert list(one.step) == [100, 250, 500, 1000] and list(one.seconds) == pytest.approx([6.0, 15.0, 30.0, 60.0])
    assert one.psnr.iloc[-1] == 30.0
    assert c.path.nunique() == 28        # every finished cell recorded a curve; failed ones none


def test_empty_missing_and_unreadable(tmp_path):
    (tmp_path / "empty").mkdir()
    assert _dtypes(smgs.results(tmp_path / "empty")) == CELL and len(smgs.results(tmp_path / "empty")) == 0
    assert _dtypes(smgs.curves(tmp_path / "empty")) == CURVE
    with pytest.raises(FileNotFoundError, match="nope is not a directory: smgs.results reads every results.json"):
        smgs.results(tmp_path / "nope")
    with pytest.raises(TypeError, match="at least one runs directory"):
        smgs.results()
    (tmp_path / "bad" / "x").mkdir(parents=True)
    (tmp_path / "bad" / "x" / "results.json").write_text("{not json")
    with pytest.warns(UserWarning, match="left out, unreadable: .*results.json"):
        df = smgs.results(tmp_path / "bad")
    assert len(df) == 0 and df.attrs["unreadable"][0][0].endswith("results.json")


def test_import_smgs_does_not_load_pandas():
    code = "import sys, smgs; assert 'pandas' not in sys.modules, 'pandas loaded'; print(json.dumps(1))"
    done = subprocess.run([sys.executable, "-c", "import json; " + code], capture_output=True, text=True,
                          cwd=Path(__file__).resolve().parents[1])
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout) == 1
