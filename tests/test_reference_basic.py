import torch

from smgs.raster import MODES, rasterize_splats


def test_reference_renders_finite_and_alpha_matches_vanilla():
    torch.manual_seed(0)
    n, w, h = 12, 16, 12
    m = torch.rand(n, 2) * torch.tensor([w, h])
    con = torch.stack([0.1 + 0.1 * torch.rand(n), 0.02 * (torch.rand(n) - 0.5), 0.1 + 0.1 * torch.rand(n)], 1)
    args = (m, con, 0.9 * torch.rand(n), torch.rand(n, 3), 1 + 3 * torch.rand(n),
            1 + torch.rand(n), 10 * torch.rand(n), torch.rand(n), w, h)
    outs = {mode: rasterize_splats(*args, mode=mode, backend="reference") for mode in MODES}
    for o in outs.values():
        assert torch.isfinite(o.rgb).all() and torch.isfinite(o.depth).all()
    # softmax keeps the vanilla transmittance (eqs. 14, 16)
    torch.testing.assert_close(outs["softmax_only"].alpha, outs["3dgs"].alpha)
    assert not torch.allclose(outs["softmax_only"].rgb, outs["3dgs"].rgb)
