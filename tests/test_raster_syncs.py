"""Host synchronisations of one render through the CUDA backend's Python path, counted without a
GPU (tests/device_mix.py: the splats on a stand-in device, the binding computed on the host by a
stand-in that reports the binding's own waits).

What counts as a wait: reading a device value (``.item()``, ``bool()``, ``_local_scalar_dense``,
``is_nonzero``, ``.tolist()``), an output whose shape depends on the data (``nonzero``, boolean
indexing), a blocking copy between the host and the device, an event the host must wait for. A
non-blocking copy from pinned memory is not one. On a GPU each wait drains the stream, so the host
and the GPU take turns (docs/gpu/README.md).

The lean glue (``SMGS_CUDA_GLUE=lean``; smgs.raster.device_glue) waits once per forward, for the
pair count the binding needs to size the tile list, and never in the backward of the modes
without softmax (the softmax backward reads the most crowded pixel's count to size its scratch).
The verified default waits six times per forward; the count is pinned here so that a change to it
is seen.
"""

from __future__ import annotations

import re

import pytest
import torch
from cuda_standin import BINDING, CSRC
from device_mix import OTHER, simulated_gpu

import smgs.raster.cuda as cuda_backend
from smgs import Camera
from smgs.raster import rasterize
from smgs.raster.backends import GLUE_ENV
from smgs.raster.types import MODES, mode_flags


def _body(fn: str, src: str = BINDING) -> str:
    start = src.index(fn)
    end = src.index("\n}\n", start)
    return src[start:end]


def test_the_binding_waits_for_the_pair_count_and_in_softmax_backwards_only():
    """The stand-in's waits (HostStandIn) are the binding's: one read in the forward (its binning,
    csrc/cuda_binding_common.h's bin), one in the backward under ``use_softmax``, nothing else that
    reads a device value."""
    common = (CSRC / "cuda_binding_common.h").read_text()
    forward = _body("std::vector<at::Tensor> forward_torch(")
    assert "bin(" in forward
    fwd, bwd = forward + _body("Binned bin(", common), _body("std::vector<at::Tensor> backward_torch(")
    assert len(re.findall(r"\.item<", fwd)) == 1 and "offs[N - 1].item<" in fwd
    reads = [line for line in bwd.splitlines() if ".item<" in line]
    assert len(reads) == 1 and "use_softmax &&" in reads[0], reads
    for body in (fwd, bwd):
        assert not re.search(r"\.(cpu|to)\(|nonzero|cudaDeviceSynchronize|cudaStreamSynchronize|cudaMemcpy\b", body)


def _scene(device, n=40, seed=3):
    g = torch.Generator().manual_seed(seed)
    r = lambda *s: torch.rand(*s, generator=g)  # noqa: E731
    z = 1.5 + 3 * r(n)
    means = torch.stack([(r(n) - 0.5) * 1.6 * z, (r(n) - 0.5) * 1.2 * z, z], 1)
    means[:3, 2] = -1.0                         # behind the camera: culled
    means[3:5, 0] = 50.0                        # off the image: culled
    d = dict(means3d=means, quats=torch.randn(n, 4, generator=g), scales=0.03 + 0.1 * r(n, 3),
             opacities=0.3 + 0.6 * r(n), sh=r(n, 4, 3) * 0.4, alpha=0.5 + 2 * r(n), beta=4 * r(n), gamma=2 * r(n))
    return {k: v.to(device).requires_grad_(True) for k, v in d.items()}


def _waits(mode) -> int:
    return sum(v for k, v in mode.counts.items() if "non_blocking" not in k)


def _render_and_count(monkeypatch, glue: str, mode: str, sh: bool = True):
    monkeypatch.setenv(GLUE_ENV, glue)
    cam = Camera.look_at([0.1, 0.0, -0.5], [0, 0, 3], [0, -1, 0], 30.0, 30.0, 32, 24)   # on the host
    with simulated_gpu(monkeypatch) as m:
        s = _scene(OTHER)
        bg = torch.tensor([0.2, 0.3, 0.4]).to(OTHER)
        for _ in range(2):    # the second render is counted: the first makes the cached constants
            m.reset()
            out = rasterize(s["means3d"], s["quats"], s["scales"], s["opacities"],
                            s["sh"] if sh else s["sh"][:, 0], cam, alpha=s["alpha"], beta=s["beta"],
                            gamma=s["gamma"], mode=mode, sh_degree=1 if sh else None, background=bg)
        fwd, fwd_where = _waits(m), list(m.where)
        loss = out.rgb.mean() + out.depth.mean()
        m.reset()
        loss.backward()
        bwd, bwd_where = _waits(m), list(m.where)
        m.reset()
        pairs = out.stats.pairs_evaluated        # lazy: read when asked for, waiting then
        asked = _waits(m)
        assert s["means3d"].grad.device == OTHER
        grads = {k: None if v.grad is None else v.grad.cpu() for k, v in s.items()}
        host = {k: v.cpu() for k, v in (("rgb", out.rgb), ("alpha", out.alpha), ("depth", out.depth),
                                        ("n_contrib", out.stats.n_contrib), ("ids", out.extras["ids"]),
                                        ("radii", out.extras["radii"]))}
    return host, grads, (fwd, fwd_where), (bwd, bwd_where), (pairs, asked)


@pytest.mark.parametrize("mode", MODES)
def test_the_lean_glue_waits_once_per_forward_and_not_in_a_plain_backward(monkeypatch, mode):
    _, grads, (fwd, fw), (bwd, bw), (pairs, asked) = _render_and_count(monkeypatch, "lean", mode)
    assert fwd == 1, "\n".join(fw)
    assert fw[0].startswith("binding forward")
    assert bwd == (1 if mode_flags(mode)[1] else 0), "\n".join(bw)
    assert pairs == 12345 and asked == 1      # the stand-in's pair count, read on demand


def test_the_verified_glue_waits_six_times_per_forward(monkeypatch):
    """Input checks (3D finite, scales >= 0, 2D finite), the projection's two compactions and the
    binding's pair count; none in a 3dgs backward."""
    _, _, (fwd, fw), (bwd, bw), _ = _render_and_count(monkeypatch, "verified", "3dgs")
    assert fwd == 6, "\n".join(fw)
    assert sum("nonzero" in w for w in fw) == 2 and bwd == 0, "\n".join(bw)


@pytest.mark.parametrize("mode", ["3dgs", "softmax_gs"])
@pytest.mark.parametrize("sh", [False, True])
def test_the_lean_glue_renders_what_the_verified_glue_renders(monkeypatch, mode, sh):
    """Dense projection (culled Gaussians at opacity 0) against compaction, deferred checks against
    immediate ones: the same images and gradients (the same operations on the kept rows; the
    stand-in binding renders with the CPU backend): equal to the bit."""
    a, ga, *_ = _render_and_count(monkeypatch, "verified", mode, sh)
    b, gb, *_ = _render_and_count(monkeypatch, "lean", mode, sh)
    for k in ("rgb", "alpha", "depth", "n_contrib"):
        torch.testing.assert_close(b[k], a[k], rtol=0, atol=0, msg=k)
    for k in ga:
        if ga[k] is not None:
            torch.testing.assert_close(gb[k], ga[k], rtol=0, atol=0, msg=k)
    assert torch.equal(b["ids"], torch.arange(len(b["ids"])))     # every Gaussian keeps its row
    assert torch.equal(b["radii"][a["ids"]], a["radii"])           # the survivors' radii; 0 elsewhere
    culled = torch.ones(len(b["radii"]), dtype=torch.bool)
    culled[a["ids"]] = False
    assert culled[:5].all() and b["radii"][culled].eq(0).all()


def test_the_lean_glue_names_a_bad_input_after_the_render(monkeypatch):
    from smgs.raster.checks import NonFiniteInputError

    monkeypatch.setenv(GLUE_ENV, "lean")
    cam = Camera.look_at([0.1, 0.0, -0.5], [0, 0, 3], [0, -1, 0], 30.0, 30.0, 32, 24)
    with simulated_gpu(monkeypatch) as m:
        s = _scene(OTHER)
        with torch.no_grad():
            s["means3d"][7, 1] = float("nan")
            s["scales"][9, 0] = -0.1
        m.reset()
        with pytest.raises(NonFiniteInputError, match=r"means3d has 1 NaN or inf"):
            rasterize(s["means3d"], s["quats"], s["scales"], s["opacities"], s["sh"][:, 0], cam, mode="3dgs")
        assert m.counts["binding forward: the pair count"] == 1     # rendered, then refused
        # ... but nothing of it rendered: the opacities reached the binding as NaN (every backend skips
        # such a splat), not the NaN splat's whole-image box
        ext = cuda_backend.extension().base     # the stand-in keeps what it was given and what it made
        assert torch.isnan(ext.given["opacities"]).all()
        assert torch.isfinite(ext.saved["rgb"]).all() and not ext.saved["alpha"].any()
        with torch.no_grad():
            s["means3d"][7, 1] = 0.0
        with pytest.raises(ValueError, match=r"scales has 1 negative value"):
            rasterize(s["means3d"], s["quats"], s["scales"], s["opacities"], s["sh"][:, 0], cam, mode="3dgs")


def test_an_unknown_glue_is_refused(monkeypatch):
    from smgs.raster.backends import Renderer, variant

    monkeypatch.setenv(GLUE_ENV, "fast")
    with pytest.raises(ValueError, match=r"SMGS_CUDA_GLUE='fast' names no cuda glue variant; expected one of verified, lean"):
        variant(Renderer(), "cuda")
    monkeypatch.setenv(GLUE_ENV, "lean")
    assert variant(Renderer(), "cuda").lean(torch.device("cuda"))
    assert not variant(Renderer(), "cuda").lean(torch.device("cpu"))   # the CPU never takes it (nothing there waits)
