"""tools/collapse_trace.py (docs/studies/fox-collapse.md): every row's count is the last one's plus
what refinement cloned and split minus what it pruned, and the pruning is told apart by rule: with
the screen-size rule at 1 px (on fox's random points) it takes Gaussians after the first reset, with
the default (off) it takes none."""

import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))

import collapse_trace as ct  # noqa: E402

FOX = ROOT.parent / "shared" / "data" / "fox"
needs_fox = pytest.mark.skipif(not (FOX / "transforms.json").is_file(),
                               reason=f"fixture {FOX} absent (CI keeps ../shared beside the checkout)")

# 40 steps of the scaled 30K schedule: refinement every step from 2 to 19, opacity reset every 4
ARGS = [str(FOX), "--steps", "40", "--width", "32", "--n-random", "2000", "--every", "5", "--budget", "full"]


def _check_counts(out: dict) -> None:
    """A split replaces one Gaussian by two (+1), a clone adds one, each pruned one goes."""
    prev = 2000
    for r in out["rows"]:
        assert r["n"] == prev + r["cloned"] + r["split"] - r["pruned_transparent"] - r["pruned_big"], r
        prev = r["n"]
    assert out["final"] == prev and out["peak"] >= 2000


@needs_fox
def test_rows_add_up_and_the_screen_rule_is_counted_apart(capsys):
    on = ct.main(ARGS + ["--prune-screen-px", "1"])
    _check_counts(on)
    assert sum(r["big_screen"] for r in on["rows"]) > 0
    assert sum(r["big_screen"] for r in on["rows"] if r["step"] <= 4) == 0   # only after the first reset
    off = ct.main(ARGS)
    _check_counts(off)
    assert sum(r["big_screen"] for r in off["rows"]) == 0
    assert "| step | #GS |" in capsys.readouterr().out
