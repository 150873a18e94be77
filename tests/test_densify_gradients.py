"""tools/densify_gradients.py: the same Gaussians put a larger screen-space gradient on their 2D
means under softmax competition than under 3DGS compositing (README: Softmax-GS over-densifies at
the full budget); with α = 1 at initialisation GEF-only is 3DGS exactly."""

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))

import densify_gradients as dg  # noqa: E402


def test_softmax_scales_the_densifiers_gradient_and_gef_at_alpha_one_does_not():
    s = {m: dg.gradient_stats(m, views=2, size=(64, 48)) for m in ("3dgs", "gef_only", "softmax_gs")}
    assert s["3dgs"].n == s["softmax_gs"].n > 100
    assert s["gef_only"].mean == s["3dgs"].mean
    assert s["softmax_gs"].mean > 1.3 * s["3dgs"].mean
    assert s["softmax_gs"].over[0] > s["3dgs"].over[0]
    assert s["3dgs"].row().startswith("| 3dgs | ")
