"""`smgs results` writes the results table as CSV, JSON or parquet (a clear error where no parquet engine
is installed), and docs/reports.md's notebook example runs as written on a fixture runs tree."""

from __future__ import annotations

import io
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest

from smgs_cli.main import main

sys.path.insert(0, str(Path(__file__).parent))
from reports_tree import OOM, make_seed_tree, make_tree  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("export") / "runs"
    make_tree(root / "budget5", images=True)
    make_seed_tree(root / "seeds")
    return root


def test_csv_file_and_json_stdout(runs, tmp_path, capsys):
    out = tmp_path / "cells.csv"
    assert main(["results", str(runs), "--out", str(out)]) == 0
    assert "results: 31 rows" in capsys.readouterr().err
    df = pd.read_csv(out)
    assert len(df) == 31 and list(df.columns)[:8] == ["method", "dataset", "scene", "budget", "cap", "preset", "seed",
                                                      "experiment"]
    oom = df[(df.scene == "garden") & (df.status == "failed")]
    assert list(oom.reason) == [OOM] and oom.psnr.isna().all()
    assert main(["results", str(runs), "--format", "json"]) == 0
    recs = json.loads(capsys.readouterr().out)
    assert len(recs) == 31 and {r["status"] for r in recs} == {"ok", "failed", "skipped"}
    skipped = next(r for r in recs if r["status"] == "skipped")
    assert skipped["psnr"] is None and skipped["num_gaussians"] is None   # missing: null, never 0


def test_per_view_and_curves(runs, tmp_path, capsys):
    assert main(["results", str(runs), "--per-view", "--out", str(tmp_path / "views.json")]) == 0
    views = json.loads((tmp_path / "views.json").read_text())
    bike = [v for v in views if v["scene"] == "bicycle" and v["method"] == "3dgs" and v["budget"] == "full"]
    assert [v["view"] for v in bike] == ["_DSC8679.JPG", "_DSC8687.JPG", "_DSC8695.JPG"]
    assert main(["results", str(runs), "--curves"]) == 0
    curves = pd.read_csv(io.StringIO(capsys.readouterr().out))
    assert set(curves.columns) >= {"step", "seconds", "psnr", "num_gaussians"} and len(curves) == 4 * 28


def test_parquet_keeps_the_dtypes(runs, tmp_path):
    if not (importable("pyarrow") or importable("fastparquet")):
        pytest.skip("no parquet engine here (pip install pyarrow, or the test extras' fastparquet)")
    out = tmp_path / "cells.parquet"
    assert main(["results", str(runs), "--out", str(out)]) == 0
    back = pd.read_parquet(out)
    assert len(back) == 31 and str(back["num_gaussians"].dtype) == "Int64" and str(back["psnr"].dtype) == "float64"
    assert back["collapsed"].dtype == "boolean" and str(back["seed"].dtype) == "int64"


def importable(name: str) -> bool:
    import importlib.util

    return importlib.util.find_spec(name) is not None


def test_parquet_without_an_engine_says_how_to_get_one(runs, tmp_path):
    """pyarrow and fastparquet made unimportable, as on an install without them."""
    out = tmp_path / "cells.parquet"
    code = ("import sys; sys.modules['pyarrow'] = None; sys.modules['fastparquet'] = None\n"
            "from smgs_cli.main import main; sys.exit(main(sys.argv[1:]))")
    done = subprocess.run([sys.executable, "-c", code, "results", str(runs), "--out", str(out)], cwd=REPO,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 2, done.stderr
    assert "error: parquet needs pyarrow (or fastparquet)" in done.stderr and "pip install pyarrow" in done.stderr
    assert "Traceback" not in done.stderr and not out.exists()


def test_bad_input_is_one_line(tmp_path, capsys):
    assert main(["results", str(tmp_path / "nope")]) == 2
    assert f"error: {tmp_path / 'nope'} is not a directory" in capsys.readouterr().err
    (tmp_path / "r").mkdir()
    assert main(["results", str(tmp_path / "r"), "--format", "parquet"]) == 2
    assert "give --out FILE.parquet" in capsys.readouterr().err


def notebook_example() -> str:
    """The fenced python block of docs/reports.md's "In a notebook" section."""
    text = (REPO / "docs" / "reports.md").read_text()
    section = text[text.index("### In a notebook"):]
    return re.search(r"```python\n(.*?)```", section, re.S).group(1)


def test_the_notebook_example_in_the_docs_runs(tmp_path):
    code = notebook_example()
    assert 8 <= len(code.strip().splitlines()) <= 12 and 'smgs.results("runs")' in code
    make_tree(tmp_path / "runs" / "budget5")
    path = os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])
    env = {**os.environ, "MPLBACKEND": "Agg", "PYTHONPATH": path}
    done = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=env, capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    assert lines[0].split() == ["scene", "bicycle", "fern", "garden"]          # methods × scenes at 5 %
    assert lines[-2].split() == ["3dgs", "23.0", "20.1", "25.0"] and lines[-1].split() == ["softmax_gs", "24.1",
                                                                                          "21.3", "26.1"]
    assert (tmp_path / "psnr_vs_train_time.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
