"""The CUDA backend's Python side, without a GPU.

* Importing ``smgs.raster.cuda`` and asking for the backend never raises; on a machine without a
  CUDA build of torch or without a device it is unavailable with a reason, and ``auto`` keeps the
  reference for CUDA tensors and the cpu backend for CPU tensors.
* The argument plumbing between the autograd Function and the torch binding: a stand-in extension
  takes its parameter names, types and order from the binding's C++ source (cuda_binding.cpp: the
  C++ signatures and their py::arg names) and its output order from the binding's documented return
  list, computes with the reference backend (tests/cuda_standin.py), and the wrapper's images and gradients must equal the
  reference's. A swapped argument, a misplaced saved tensor or a misrouted gradient fails here.
"""

import re

import pytest
import torch
from cuda_standin import BINDING, KEYS, PYTYPE, StandInExtension, cpp_params, py_args, returned

from smgs.raster import backend_available, resolve_backend
from smgs.raster import constants as K
from smgs.raster import cuda as cuda_backend
from smgs.raster.composite_inputs import Splats2D, composite_settings
from smgs.raster.reference import rasterize_splats_reference
from smgs.raster.types import MODES, mode_flags


def test_binding_signatures_and_pybind_names_agree():
    for fn, name in (("forward_torch", "forward"), ("backward_torch", "backward")):
        params = cpp_params(fn)
        assert [n for _, n in params] == py_args(name), fn
        assert all(t in PYTYPE for t, _ in params), params
    assert len(returned("forward_torch")) == 11
    ret = re.search(r"return \{(out\.rgb, [^}]*)\};", BINDING).group(1)
    assert len(ret.split(",")) == len(returned("forward_torch"))


def test_cuda_backend_unavailable_without_a_cuda_build_or_device():
    if torch.version.cuda is not None and torch.cuda.is_available():
        pytest.skip("a CUDA device is present: tests/test_raster_cuda.py covers the backend")
    assert cuda_backend.is_available() is False
    reason = cuda_backend.unavailable_reason()
    assert reason and ("CUDA" in reason or "SMGS_DISABLE_CUDA_BACKEND" in reason)
    assert not backend_available("cuda", "cuda", torch.float32)
    assert not backend_available("cuda", "cpu", torch.float32)
    assert resolve_backend("auto", "cuda", torch.float32) == "reference"
    with pytest.raises(RuntimeError):
        resolve_backend("cuda", "cuda", torch.float32)
    with pytest.raises(RuntimeError, match="unavailable"):
        cuda_backend.extension()


def scene(n=12, w=21, h=17, n_ch=3, n_reg=0, seed=0):
    g = torch.Generator().manual_seed(seed)
    r = lambda *s: torch.rand(*s, generator=g)  # noqa: E731
    sc = dict(means2d=r(n, 2) * torch.tensor([w, h]), conics=torch.stack([0.2 + 0.3 * r(n), 0.05 * (r(n) - 0.5),
                                                                           0.2 + 0.3 * r(n)], 1),
              opacities=0.3 + 0.6 * r(n), colors=r(n, n_ch), depths=1 + 3 * r(n), alpha=0.5 + 2 * r(n),
              beta=8 * r(n), gamma=2 * r(n))
    if n_reg:
        sc["reg_values"] = r(n, n_reg)
    return sc


def run(fn, sc, w, h, mode, **kw):
    """``fn(splats, settings)`` on the scene's splats, with its images' random-weighted loss
    back-propagated."""
    names = KEYS + (["reg_values"] if "reg_values" in sc else [])
    ins = {k: sc[k].clone().requires_grad_(True) for k in names}
    bg = torch.tensor([0.2, 0.5, 0.7][:sc["colors"].shape[1]], requires_grad=True)
    st = composite_settings(w, h, mode, kw.pop("k_max", 3), kw.pop("eq15", "solved"), kw.pop("reg_depth_scale", 1.0),
                            K.T_MIN, kw.pop("scope", "pixel"))
    out = fn(Splats2D(*[ins[k] for k in KEYS], background=bg, reg_values=ins.get("reg_values")), st)
    g = torch.Generator().manual_seed(9)
    loss = sum((t * torch.rand(t.shape, generator=g)).sum() for t in (out.rgb, out.alpha, out.depth))
    if out.reg is not None:
        loss = loss + (out.reg * torch.rand(out.reg.shape, generator=g)).sum()
    loss.backward()
    return out, {**{k: t.grad for k, t in ins.items()}, "background": bg.grad}


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("n_ch,n_reg,eq15,scope", [(3, 0, "solved", "pixel"), (1, 2, "printed", "pixel"),
                                                   (3, 1, "solved", "patch")])
def test_wrapper_plumbing_matches_the_reference(mode, n_ch, n_reg, eq15, scope):
    sc = scene(n_ch=n_ch, n_reg=n_reg)
    ext = StandInExtension()

    def via_wrapper(splats, st):
        return cuda_backend.composite(ext, splats, st)

    ow, gw = run(via_wrapper, sc, 21, 17, mode, eq15=eq15, reg_depth_scale=0.6, scope=scope)
    orf, gr = run(rasterize_splats_reference, sc, 21, 17, mode, eq15=eq15, reg_depth_scale=0.6, scope=scope)
    assert ext.calls == ["forward_torch", "backward_torch"]
    for a, b in ((ow.rgb, orf.rgb), (ow.alpha, orf.alpha), (ow.depth, orf.depth)):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    assert (ow.reg is None) == (orf.reg is None)
    if ow.reg is not None:
        torch.testing.assert_close(ow.reg, orf.reg, rtol=0, atol=0)
    assert torch.equal(ow.stats.n_contrib, orf.stats.n_contrib) and ow.stats.k_max == orf.stats.k_max
    assert ow.stats.scope == orf.stats.scope == scope
    assert (ow.stats.list_end is None) == (scope == "pixel")
    if scope == "patch":
        assert torch.equal(ow.stats.list_end, orf.stats.list_end)
    assert ow.stats.pairs_evaluated == 12345
    use_gef, use_soft = mode_flags(mode)
    for k, want in gr.items():
        got = gw[k]
        if want is None:
            assert got is None or (got == 0).all(), k
            continue
        # the same reference graph on both sides, so equal bits; the background's gradient is the
        # wrapper's Σ g_rgb·T with T = 1 - alpha from the stand-in, against autograd's product T
        tol = 1e-5 if k == "background" else 0.0
        torch.testing.assert_close(got, want, rtol=tol, atol=tol, msg=k)
    assert (gw["alpha"] is None) == (not use_gef) and (gw["beta"] is None) == (not use_soft)


@pytest.mark.parametrize("kernels", ["default", "v2"])
@pytest.mark.parametrize("mode", MODES)
def test_wrapper_with_no_splats_renders_the_background_without_calling_the_kernel(mode, kernels):
    """A view with nothing in it (a collapsed model): the kernels read the regulariser's channel
    count from a non-empty reg_values only, so the wrapper (of the default and of the opt-in
    kernels) answers N = 0 itself, with the documented shapes and zero gradients, and never calls
    the extension."""
    from smgs.raster import cuda_v2

    wrapper = cuda_backend if kernels == "default" else cuda_v2
    ext = StandInExtension()
    z = lambda *s: torch.zeros(*s, requires_grad=True)  # noqa: E731
    ins = dict(means2d=z(0, 2), conics=z(0, 3), opacities=z(0), colors=z(0, 3), depths=z(0), alpha=z(0),
               beta=z(0), gamma=z(0))
    rv = z(0, 2)
    bg = torch.tensor([0.2, 0.5, 0.7], requires_grad=True)
    out = wrapper.composite(ext, Splats2D(*ins.values(), background=bg, reg_values=rv),
                            composite_settings(21, 17, mode, 3))
    assert ext.calls == []
    assert torch.equal(out.rgb, bg.detach().expand(17, 21, 3)) and not out.alpha.any() and not out.depth.any()
    assert out.reg.shape == (17, 21, 5) and not out.reg.any() and out.stats.pairs_evaluated == 0
    (out.rgb.sum() + out.alpha.sum() + out.depth.sum() + out.reg.sum()).backward()
    use_gef, use_soft = mode_flags(mode)
    used = ["means2d", "conics", "opacities", "colors", "depths"] + (["alpha"] if use_gef else []) \
        + (["beta", "gamma"] if use_soft else [])
    for k in used:
        assert ins[k].grad is not None and ins[k].grad.shape == ins[k].shape, k
    assert rv.grad is not None and rv.grad.shape == (0, 2)
    assert torch.equal(bg.grad, torch.full((3,), 17.0 * 21))


@pytest.mark.parametrize("which", ["default", "v2", "per-pixel"])
def test_more_splats_than_the_binning_indexes_are_refused_before_the_kernels(which):
    """prepare/emit index each splat's [4] box with 32-bit 4·i: past 2^29 splats it would overflow
    on the GPU, so the wrappers refuse, naming the limit and the way out (meta tensors: no memory)."""
    from smgs.raster import cuda_v2

    n = cuda_backend.MAX_SPLATS + 1
    m = lambda *s: torch.empty(*s, device="meta")  # noqa: E731
    sp = Splats2D(m(n, 2), m(n, 3), m(n), m(n, 3), m(n), None, None, None)
    ext = StandInExtension()
    call = {"default": cuda_backend.composite, "v2": cuda_v2.composite, "per-pixel": cuda_v2.composite_pixel}[which]
    with pytest.raises(ValueError, match=r"536,870,913 splats in one render: the CUDA kernels bin at most "
                                         r"536,870,912 .*prune the model below that, or render with backend='cpu'"):
        call(ext, sp, composite_settings(16, 16, "3dgs", 3))
    assert ext.calls == []
    cuda_backend.check_splat_count(cuda_backend.MAX_SPLATS)   # the largest that fits
