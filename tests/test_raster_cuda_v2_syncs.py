"""The fused v2 path (``rasterize(..., backend=Renderer(kernels="v2"))``) on a stand-in device (tests/device_mix.py):
no operator mixes the host camera with the device's tensors, and the host synchronisations of one
forward and one backward are counted: the binding's pair count is the only one of its own (the
projection adds none: no ``nonzero``, no camera copies), the backward has none without softmax and
one with (the most crowded pixel's count), and a forward costs fewer than the default path's. The
bindings are the stand-ins of tests/cuda_v2_standin.py, run on the host values outside the mode
(that is the GPU's own work), their synchronisations counted where the real bindings make them.
"""

from __future__ import annotations

import contextlib

import pytest
import torch
from cuda_v2_standin import OnHost, StandInCompositing, StandInProjection
from device_mix import CPU, OTHER, simulated_gpu

from smgs.camera import Camera
from smgs.raster import Renderer, cuda_v2, projection_cuda, rasterize
from smgs.raster.types import MODES, mode_flags


def _lean_camera() -> Camera:
    return Camera.look_at([0.1, -0.2, -1.0], [0, 0, 3], [0, -1, 0], 40.0, 42.0, 24, 18)


@contextlib.contextmanager
def _lean_v2(monkeypatch):
    """The v2 kernels under the lean glue on the stand-in device: (its counts, the compositing)."""
    monkeypatch.setenv("SMGS_CUDA_GLUE", "lean")
    with simulated_gpu(monkeypatch) as m:
        proj = OnHost(StandInProjection(), m)
        comp = OnHost(StandInCompositing(), m, "binding forward: the pair count")
        monkeypatch.setattr(projection_cuda, "extension", lambda: proj)
        monkeypatch.setattr(cuda_v2, "extension", lambda t_min=None: comp)
        yield m, comp


def _splats(n: int, device, sh: bool) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(4)
    r = lambda *s: torch.rand(*s, generator=g)  # noqa: E731
    means = (r(n, 3) - 0.5) * torch.tensor([2.0, 1.6, 1.0]) + torch.tensor([0.0, 0.0, 3.0])
    means[:3, 2] = -2.0   # behind the camera
    s = dict(means3d=means, quats=r(n, 4) - 0.5, scales=0.05 + 0.1 * r(n, 3), opacities=0.3 + 0.6 * r(n),
             colors=0.5 * (r(n, 4, 3) - 0.5) if sh else r(n, 3), alpha=0.5 + 2 * r(n), beta=8 * r(n), gamma=2 * r(n))
    return {k: v.to(device).requires_grad_(True) for k, v in s.items()}


def _render(s, cam, mode, sh, **kw):
    bg = torch.tensor([0.1, 0.2, 0.3], device=s["means3d"].device)
    return rasterize(s["means3d"], s["quats"], s["scales"], s["opacities"], s["colors"], cam, alpha=s["alpha"],
                     beta=s["beta"], gamma=s["gamma"], mode=mode, k_max=4, sh_degree=1 if sh else None, background=bg,
                     **kw)


def _counted(mode_obj, fn) -> tuple[int, list[str]]:
    before, where = sum(mode_obj.counts.values()), len(mode_obj.where)
    fn()
    return sum(mode_obj.counts.values()) - before, mode_obj.where[where:]


@pytest.mark.parametrize("mode", MODES)
def test_fused_path_on_another_device_keeps_the_camera_on_the_host_and_syncs_once(monkeypatch, mode):
    cam = Camera.look_at([0.1, -0.2, -1.0], [0, 0, 3], [0, -1, 0], 40.0, 42.0, 24, 18)
    sh = mode in ("gef_only", "softmax_gs")
    want = _splats(60, CPU, sh)
    ref = _render(want, cam, mode, sh, backend="reference")
    (ref.rgb.mean() + ref.depth.mean()).backward()
    with simulated_gpu(monkeypatch) as m:
        proj = OnHost(StandInProjection(), m)
        comp = OnHost(StandInCompositing(), m, "binding forward: the pair count",
                       "binding backward: the most crowded pixel's count")
        monkeypatch.setattr(projection_cuda, "extension", lambda: proj)
        monkeypatch.setattr(cuda_v2, "extension", lambda t_min=None: comp)
        s = _splats(60, OTHER, sh)
        box = {}
        n_fwd, where_fwd = _counted(m, lambda: box.update(out=_render(s, cam, mode, sh, backend=Renderer(kernels="v2"))))
        out = box["out"]
        n_bwd, where_bwd = _counted(m, lambda: (out.rgb.mean() + out.depth.mean()).backward())
        assert proj.base.calls == ["project_forward_torch", "project_backward_torch"]
        assert comp.base.calls == ["forward_v2", "backward_v2"]
        assert out.rgb.device == OTHER and s["means3d"].grad.device == OTHER
        torch.testing.assert_close(out.rgb.cpu(), ref.rgb, rtol=1e-5, atol=1e-6)
        for k, v in s.items():
            if want[k].grad is None:
                assert v.grad is None or (v.grad.cpu() == 0).all(), k
            else:
                torch.testing.assert_close(v.grad.cpu(), want[k].grad, rtol=1e-4, atol=1e-6, msg=k)
        # the default path on the same device, for comparison (device_mix's stand-in of the default binding)
        s2 = _splats(60, OTHER, sh)
        n_default, _ = _counted(m, lambda: _render(s2, cam, mode, sh))
    ours = [w for w in where_fwd if "smgs/raster/projection" in w or "smgs/raster/cuda_v2" in w]
    assert not ours, where_fwd
    assert sum("the pair count" in w for w in where_fwd) == 1, where_fwd
    assert n_fwd < n_default, (n_fwd, n_default, where_fwd)
    assert n_bwd == (1 if mode_flags(mode)[1] else 0), where_bwd


BAD_INPUTS = [("means3d", (5, 1), float("nan"), r"means3d has 1 NaN or inf"),
              ("scales", (6, 0), -0.1, r"scales has 1 negative value"),
              ("opacities", (7,), float("inf"), r"opacities has 1 NaN or inf"),
              ("gamma", (8,), -float("inf"), r"gamma has 1 NaN or -inf"),
              ("colors", (9, 2, 1), float("nan"), r"colors_or_sh has 1 NaN or inf")]


@pytest.mark.parametrize("name, at, value, message", BAD_INPUTS)
def test_the_lean_glue_checks_the_fused_inputs_in_the_projection_and_renders_nothing_of_a_bad_one(
        monkeypatch, name, at, value, message):
    """v2 + lean glue: the fused projection checks every per-Gaussian input itself (a device flag,
    no launch of its own); a bad Gaussian is culled there, so the compositing renders nothing of it
    (a NaN splat's box is the whole image), and the flag, copied before the compositing's one wait,
    is read after it: the same error as the verified glue's, naming the input."""
    cam = _lean_camera()
    with _lean_v2(monkeypatch) as (m, comp):
        s = _splats(60, OTHER, sh=True)
        with torch.no_grad():
            s[name][at] = value
        m.reset()
        with pytest.raises(ValueError, match=message):
            _render(s, cam, "softmax_gs", True, backend=Renderer(kernels="v2"))
        assert m.counts["binding forward: the pair count"] == 1     # rendered, then refused
        # the flag went to the host without a wait and rode on the pair count's; only the naming
        # after it (checks.finite's exact count, the error path) reads the device again
        assert m.counts["copy to host, non_blocking"] == 1
        assert not [w for w in m.where if "smgs/raster" in w and "checks.py" not in w], m.where
        v = comp.base.saved["v"]
        row = at[0]
        assert (v["radii"][row] == 0).all()                          # culled in the projection
        assert all(torch.isfinite(t).all() for t in (comp.base.outs["rgb"], comp.base.outs["alpha"]))


def test_the_lean_glue_renders_an_infinite_gamma_without_complaint(monkeypatch):
    """γ = +inf is valid (a hard depth decay): the kernel's check lets it through."""
    cam = _lean_camera()
    with _lean_v2(monkeypatch) as (m, comp):
        s = _splats(60, OTHER, sh=False)
        with torch.no_grad():
            s["gamma"][:5] = float("inf")
        out = _render(s, cam, "softmax_gs", False, backend=Renderer(kernels="v2"))
        assert (comp.base.saved["v"]["radii"][5:10] != 0).any() and torch.isfinite(out.rgb.cpu()).all()


def test_the_lean_glue_refuses_a_bad_input_also_with_the_camera_on_the_device(monkeypatch):
    """A camera on the device is checked with deferred values of its own, copied before the render;
    the fused projection's flag, raised after that copy, is still read: a bad Gaussian is refused,
    not silently culled."""
    cam = _lean_camera()
    with _lean_v2(monkeypatch) as (m, comp):
        on_device = Camera(cam.K.to(OTHER), cam.viewmat.to(OTHER), cam.width, cam.height)
        s = _splats(60, OTHER, sh=True)
        with torch.no_grad():
            s["means3d"][5, 1] = float("nan")
        with pytest.raises(ValueError, match=r"means3d has 1 NaN or inf"):
            _render(s, on_device, "softmax_gs", True, backend=Renderer(kernels="v2"))
        s = _splats(60, OTHER, sh=True)   # and a good one renders
        out = _render(s, on_device, "softmax_gs", True, backend=Renderer(kernels="v2"))
        assert torch.isfinite(out.rgb.cpu()).all()
