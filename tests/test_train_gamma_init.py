"""γ's default initial value on a real scene's scale: a surface behind an opaque one must not show
through the softmax competition (the speckle of issue 14)."""

import torch

from smgs.camera import Camera
from smgs.raster import rasterize
from smgs.train import GaussianConfig, ParamInit
from smgs.train.gaussians import Gaussians


def _pixel(mode: str, cfg: GaussianConfig, back_depth: float = 5.0) -> torch.Tensor:
    # A scene 10 units across; two splats of size 0.1 on the optical axis, the front one at depth 3,
    # red and opaque but off-centre at the pixel, the back one green and centred there (so it wins
    # the softmax on its exponent if the depth decay lets it compete). Back at 5: 20 sizes apart.
    pts = torch.tensor([[0.01, 0.0, 3.0], [0.0, 0.0, back_depth]])
    cols = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    g = Gaussians.from_points(pts, cols, cfg, extent=10.0, sh_degree=0,
                              scales=torch.full((2, 3), 0.1), device="cpu")
    cam = Camera(torch.tensor([[100.0, 0, 0.5], [0, 100.0, 0.5], [0, 0, 1]]), torch.eye(4), 1, 1)
    ops = torch.tensor([0.99, 0.99])
    with torch.no_grad():
        out = rasterize(g.means, g.quats, g.scales, ops, cols, cam, alpha=g.alpha, beta=g.beta,
                        gamma=g.gamma, mode=mode, backend="reference")
    return out.rgb[0, 0]


def test_default_gamma_keeps_a_back_surface_hidden():
    vanilla = _pixel("3dgs", GaussianConfig())
    assert vanilla[1] < 0.05          # in 3DGS the back splat is hidden
    soft = _pixel("softmax_gs", GaussianConfig())
    assert abs(float(soft[1] - vanilla[1])) < 0.01, soft
    # With the earlier default, γ = 1 per scene extent (decay length 10 units), the back splat
    # twenty splat sizes behind takes much of the pixel: the speckle this default avoids.
    old = _pixel("softmax_gs", GaussianConfig(gamma=ParamInit(1.0), gamma_unit="extent"))
    assert float(old[1]) > 0.2, old


def test_default_gamma_keeps_a_splat_two_sizes_behind_hidden():
    # The full-budget case: after densification a surface is many small splats, and one two splat
    # sizes behind another must not take the pixel either. The earlier default (0.3 per splat
    # size, decay length 3.3 sizes) let it; the current one (3, 1/3 of a size) does not.
    vanilla = _pixel("3dgs", GaussianConfig(), back_depth=3.2)
    assert vanilla[1] < 0.05
    assert abs(float(_pixel("softmax_gs", GaussianConfig(), back_depth=3.2)[1] - vanilla[1])) < 0.01
    earlier = _pixel("softmax_gs", GaussianConfig(gamma=ParamInit(0.3)), back_depth=3.2)
    assert float(earlier[1] - vanilla[1]) > 0.05, earlier
