"""tools/run_table.py: one row per run with its k_max scope, means over seeds, failed runs named."""

import importlib.util
from pathlib import Path

from protocols.results import RunResult, write_result

TOOL = Path(__file__).resolve().parents[1] / "tools" / "run_table.py"


def _tool():
    spec = importlib.util.spec_from_file_location("run_table", TOOL)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _result(tmp_path, seed, scope, psnr, status="ok", pop=None):
    cfg = {"method": {"name": "softmax_gs", "train": {"k_max": 128, "k_max_scope": scope}}}
    r = RunResult(method="softmax_gs", dataset="procedural", scene="blocks", budget="full", seed=seed,
                  status=status, error=None if status == "ok" else "boom", config=cfg,
                  metrics={"psnr": psnr, "ssim": 0.9}, num_gaussians=1000 + seed, train_seconds=12.0,
                  diagnostics={"frac_within_kmax": 0.5},
                  consistency={} if pop is None else {"pop_ratio": pop, "popped_fraction": 0.01,
                                                      "mse": {"missing": "why"}})
    write_result(tmp_path / scope / f"seed{seed}", r)


def test_rows_means_and_failures(tmp_path, capsys):
    _result(tmp_path, 0, "pixel", 30.0, pop=2.0)
    _result(tmp_path, 1, "pixel", 32.0)
    _result(tmp_path, 0, "patch", 29.0)
    _result(tmp_path, 1, "patch", 0.0, status="failed")
    _tool().main([str(tmp_path), "--mean"])
    out = capsys.readouterr().out
    lines = [s for s in out.splitlines() if s.startswith("| procedural")]
    assert len(lines) == 3 + 2                     # three ok runs, two cells' means
    assert "| pixel | 0 | 30.00 | 0.900 | – | 1000 | 12 | 0.500 | – | – | 2.00 | 1.00 |" in out
    assert "| pixel | 2 | 31.00 ± 1.41 |" in out    # mean ± sd over the two seeds
    assert "| patch | 1 | 29.00 |" in out
    assert "failed: procedural/blocks softmax_gs full seed 1: boom" in out
