"""tools/densify_gradients.py: where splats at different depths compete (γ 0.3 per splat size, the
earlier default) the same Gaussians put a screen-space gradient on their 2D means that grows with β;
at the default γ (3) it is 3DGS's at any β (docs/studies/gamma-init.md); with α = 1 at initialisation GEF-only is 3DGS exactly."""

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))

import densify_gradients as dg  # noqa: E402


def test_cross_depth_competition_scales_the_densifiers_gradient_with_beta_and_gef_at_alpha_one_does_not():
    s = {m: dg.gradient_stats(m, views=2, size=(64, 48)) for m in ("3dgs", "gef_only")}
    soft = {b: dg.gradient_stats("softmax_gs", views=2, size=(64, 48), beta_init=b, gamma_init=0.3)
            for b in (1.0, 20.0)}
    assert s["3dgs"].n == soft[1.0].n == soft[20.0].n > 100
    assert s["gef_only"].mean == s["3dgs"].mean
    assert soft[20.0].mean > 1.3 * s["3dgs"].mean
    assert soft[20.0].over[0] > soft[1.0].over[0]
    assert abs(soft[1.0].mean / s["3dgs"].mean - 1) < 0.15
    default = dg.gradient_stats("softmax_gs", views=2, size=(64, 48), beta_init=20.0)
    assert abs(default.mean / s["3dgs"].mean - 1) < 0.1 < soft[20.0].mean / s["3dgs"].mean - 1
    assert s["3dgs"].row().startswith("| 3dgs | – | ") and soft[1.0].row().startswith("| softmax_gs | 1 | ")


def test_trace_records_each_refinement_and_its_count_adds_up():
    """--trace: every refinement of the scaled full-budget schedule (every 10 steps from 60) is
    recorded, and each one's count after cloning, splitting and pruning is the next one's start."""
    rows = dg.refinement_trace("softmax_gs", steps=80, size=(64, 48))
    assert [r.step for r in rows] == [60, 70, 80]
    assert rows[0].n == 3000 and rows[0].beta is not None and rows[0].l1 > 0
    for a, b in zip(rows, rows[1:]):
        assert b.n == a.n + a.cloned + a.split - a.pruned   # a split adds two and removes the original
    assert rows[0].cloned + rows[0].split > 0 and 0 < rows[0].over <= 1
    assert dg.refinement_trace("3dgs", steps=61, size=(64, 48))[0].beta is None
