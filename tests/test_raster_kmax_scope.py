"""The k_max scope switch (docs/kmax-scope.md): ``pixel`` (each pixel's first k_max composited
splats form its softmax head) and ``patch`` (the splats at positions < k_max of its tile's
depth-sorted list).

* the reference's emulation of the tile lists (smgs.raster.tiles) is the compiled CPU binning, list
  by list, including the cases where a splat covers the whole image or is not listed at all;
* the scope matters: a scene built so that a pixel's first composited splats lie past the tile's
  first k_max entries renders differently in the two scopes, exactly where expected, on both backends;
* the ray-stop rule in patch scope: never inside the tile's head, from its first entry past it on;
* the coverage statistic and the argument checks.
The full comparisons of every backend against the reference in both scopes are in
tests/test_raster_cpu.py, tests/test_raster_cpu_pixel_grad.py and tests/test_raster_cuda.py.
"""

import shutil

import pytest
import torch

from smgs.raster import MODES, rasterize_splats
from smgs.raster import constants as K
from smgs.raster.tiles import NOT_LISTED, list_positions, splat_boxes
from smgs.raster.types import RenderStats

if shutil.which("c++") is None:  # a machine without a compiler has no cpu backend; that is not a bug
    pytest.skip("no C++ compiler: the cpu backend cannot be built here", allow_module_level=True)

pytestmark = pytest.mark.usefixtures("cpu_isa")


def _binning_scene(w: int, h: int) -> dict:
    """Random splats plus the binning's edge cases: wholly off screen, opacity below 1/255, a
    non-positive-definite conic and one too elongated for the float32 error bound (both cover the
    whole image), boxes ending on tile edges, depth ties."""
    g = torch.Generator().manual_seed(7)
    n = 60
    means = (torch.rand(n, 2, generator=g) * 1.3 - 0.15) * torch.tensor([w, h])
    sig = 0.5 + 6 * torch.rand(n, 2, generator=g)
    conics = torch.stack([1 / sig[:, 0] ** 2, 0.2 * (torch.rand(n, generator=g) - 0.5) / (sig[:, 0] * sig[:, 1]),
                          1 / sig[:, 1] ** 2], 1)
    opac = 0.05 + 0.9 * torch.rand(n, generator=g)
    depths = torch.rand(n, generator=g)
    means[0] = torch.tensor([-40.0, 10.0])                 # off screen
    opac[1] = 0.5 / 255                                    # never reaches
    conics[2] = torch.tensor([0.1, 0.5, 0.1])              # b² > ac: whole image
    conics[3] = torch.tensor([1.0, 1.0 - 1e-7, 1.0])       # nearly singular: bound too loose, whole image
    means[4] = torch.tensor([15.5, 15.5])                  # centred on a tile corner
    conics[4] = torch.tensor([1.0, 0.0, 1.0])
    depths[5:9] = depths[9]                                # ties, broken by index
    return dict(means2d=means, conics=conics, opacities=opac, depths=depths)


def test_the_emulated_tile_lists_are_the_cpu_kernels(cpu_backend):
    w, h = 53, 37   # 4x3 tiles, partial ones on both edges
    sc = _binning_scene(w, h)
    n = sc["means2d"].shape[0]
    e = torch.empty(0)
    out = cpu_backend.extension().forward(sc["means2d"], sc["conics"], sc["opacities"], torch.rand(n, 3),
                                          sc["depths"], e, e, e, e, e, w, h, False, False, 8, True, 1.0, 1,
                                          K.T_MIN, True)
    ids, box, toff, tlist = out[8].long(), out[10].long(), out[11].long(), out[12].long()
    listed, ref_box = splat_boxes(sc["means2d"], sc["conics"], sc["opacities"], w, h)
    assert sorted(ids.tolist()) == torch.nonzero(listed).flatten().tolist()
    assert not listed[0] and not listed[1] and listed[2] and listed[3]
    assert torch.equal(box, ref_box[ids])
    assert ref_box[2].tolist() == ref_box[3].tolist() == [0, w - 1, 0, h - 1]
    pos, pixel_tile = list_positions(sc["means2d"], sc["conics"], sc["opacities"], sc["depths"], w, h)
    assert pos.shape == (4 * 3, n) and pixel_tile.shape == (w * h,)
    for t in range(pos.shape[0]):
        kernel_list = ids[tlist[toff[t]:toff[t + 1]]].tolist()
        row = pos[t]
        on = torch.nonzero(row != NOT_LISTED).flatten()
        assert row[on].sort().values.tolist() == list(range(len(on)))
        assert on[row[on].argsort()].tolist() == kernel_list, t
    assert pixel_tile[w * 16 + 17].item() == 1 * 4 + 1


def _head_scene():
    """One 16x16 tile, k_max = 2. Two splats in front cover only the tile's left edge; behind them
    two overlapping splats of different colours cover the right side. At a right-hand pixel, the
    first two composited splats are the back pair (pixel scope: softmax between them), but they are
    the tile list's entries 2 and 3 (patch scope: composited the vanilla way)."""
    f = lambda *v: torch.tensor(v, dtype=torch.float32)  # noqa: E731
    means = f([1.0, 8.0], [1.5, 9.0], [12.0, 8.0], [12.5, 8.5])
    conics = f([2.0, 0.0, 0.05], [2.0, 0.0, 0.05], [0.2, 0.0, 0.2], [0.25, 0.02, 0.2])
    return dict(means2d=means, conics=conics, opacities=f(0.7, 0.6, 0.8, 0.75),
                colors=f([1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0], [1.0, 1.0, 0]), depths=f(1.0, 1.1, 2.0, 2.05),
                alpha=f(1.0, 1.2, 1.5, 0.9), beta=f(4.0, 4.0, 6.0, 6.0), gamma=f(1.0, 1.0, 0.5, 0.5))


@pytest.mark.parametrize("mode", ["softmax_only", "softmax_gs"])
def test_the_scope_matters_where_a_pixels_head_is_past_the_tiles(mode):
    sc = _head_scene()
    args = [sc[k] for k in ("means2d", "conics", "opacities", "colors", "depths", "alpha", "beta", "gamma")]
    outs = {(scope, backend): rasterize_splats(*args, 16, 16, mode=mode, k_max=2, backend=backend,
                                               k_max_scope=scope)
            for scope in ("pixel", "patch") for backend in ("reference", "cpu")}
    for scope in ("pixel", "patch"):   # the CPU backend is the reference in either scope
        torch.testing.assert_close(outs[scope, "cpu"].rgb, outs[scope, "reference"].rgb, rtol=0, atol=2e-6)
        assert torch.equal(outs[scope, "cpu"].stats.n_contrib, outs[scope, "reference"].stats.n_contrib)
    pix, pat = outs["pixel", "reference"], outs["patch", "reference"]
    diff = (pix.rgb - pat.rgb).abs().amax(-1)
    # left columns: the front pair leads every pixel there, positions 0 and 1 in both scopes
    front_only = (pix.stats.n_contrib <= 2) & (torch.arange(16) < 4)[None, :]
    assert front_only.any() and float(diff[front_only].max()) == 0.0
    # right side: only the back pair reaches; softmax (pixel) against vanilla (patch)
    assert float(diff[8, 12]) > 1e-3
    assert pat.stats.list_end[8, 12].item() == 4 and pat.stats.frac_within_kmax < pix.stats.frac_within_kmax
    # 3DGS compositing has no head: the scope changes nothing
    plain = [rasterize_splats(*args, 16, 16, mode="3dgs", k_max=2, backend="cpu", k_max_scope=s) for s in
             ("pixel", "patch")]
    assert torch.equal(plain[0].rgb, plain[1].rgb)


def test_the_ray_stop_in_patch_scope_holds_from_the_tiles_first_entry_past_k_max():
    """Three splats with a ≈ 0.9 at one pixel, behind two that miss it; t_min 0.05. Pixel scope: the
    first two composited are the head (never stopped), the third stops (T 0.001 < 0.05). Patch
    scope with k_max 2: all three are past the tile's head, so the second already stops (T ≈ 0.009)."""
    f = lambda *v: torch.tensor(v, dtype=torch.float32)  # noqa: E731
    n = 5
    means = f([1.0, 1.0], [2.0, 1.0], [10.0, 10.0], [10.2, 10.1], [9.9, 10.2])
    conics = f(*([[0.5, 0.0, 0.5]] * n))
    sc = dict(means2d=means, conics=conics, opacities=f(0.9, 0.9, 0.99, 0.99, 0.99), colors=torch.rand(n, 3),
              depths=f(1.0, 1.1, 2.0, 2.1, 2.2), alpha=torch.ones(n), beta=torch.ones(n), gamma=torch.ones(n))
    args = [sc[k] for k in ("means2d", "conics", "opacities", "colors", "depths", "alpha", "beta", "gamma")]
    for backend in ("reference", "cpu"):
        cnt = {s: rasterize_splats(*args, 16, 16, mode="softmax_gs", k_max=2, t_min=0.05, backend=backend,
                                   k_max_scope=s).stats.n_contrib[10, 10].item() for s in ("pixel", "patch")}
        assert cnt == {"pixel": 2, "patch": 1}, backend
        # inside the tile's head nothing stops: with k_max 5 every splat is in it
        full = rasterize_splats(*args, 16, 16, mode="softmax_gs", k_max=5, t_min=0.05, backend=backend,
                                k_max_scope="patch")
        assert full.stats.n_contrib[10, 10].item() == 3, backend


@pytest.mark.parametrize("mode", MODES)
def test_cpu_leaders_in_patch_scope_match_the_reference(mode, cpu_backend):
    """The per-pixel kernel (leaders, global order) takes the scope too."""
    from test_raster_cpu import W, H, random_scene

    sc = random_scene(40, W, H, seed=3)
    args = [sc[k] for k in ("means2d", "conics", "opacities", "colors", "depths", "alpha", "beta", "gamma")]
    ref = rasterize_splats(*args, W, H, mode=mode, k_max=2, backend="reference", leaders=True, k_max_scope="patch")
    got = rasterize_splats(*args, W, H, mode=mode, k_max=2, backend="cpu", leaders=True, k_max_scope="patch")
    assert torch.equal(got.leaders, ref.leaders)
    assert torch.equal(got.stats.n_contrib, ref.stats.n_contrib)
    assert torch.equal(got.stats.list_end, ref.stats.list_end)
    torch.testing.assert_close(got.rgb, ref.rgb, rtol=0, atol=2e-6)


def test_coverage_reads_the_list_end_in_patch_scope():
    n = torch.tensor([[0, 3], [5, 2]])
    assert RenderStats(n, 0, 4).frac_within_kmax == pytest.approx(2 / 3)
    assert RenderStats(n, 0, 4, "patch", torch.tensor([[0, 9], [5, 4]])).frac_within_kmax == pytest.approx(1 / 3)


def test_an_unknown_scope_is_refused_with_the_choices():
    sc = _head_scene()
    args = [sc[k] for k in ("means2d", "conics", "opacities", "colors", "depths", "alpha", "beta", "gamma")]
    with pytest.raises(ValueError, match="unknown k_max scope 'tile'.*pixel, patch"):
        rasterize_splats(*args, 16, 16, k_max_scope="tile")
