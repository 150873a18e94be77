"""What a CPU training step no longer makes: the SH parameters reach the compiled projection as they
are (no ``torch.cat``, no select per coefficient), the render outputs the loss does not use get no
[H, W] zero gradients, and the photometric loss hands its gradient over without a product. Each
with the gradients it must still give."""

from __future__ import annotations

import torch

from baselines import create_method
from smgs.camera import Camera
from smgs.data.procedural import make_procedural_scene
from smgs.raster import cpu, rasterize


def _scene_and_method(method: str = "3dgs"):
    scene = make_procedural_scene(n_views=4, size=(32, 24), n_points=300, n_trajectory=0, supersample=1)
    cfg = {"mode": method, "steps": 100, "gaussians": {"init": "sfm"}, "sh_degree_interval": 0}
    return scene, create_method(method, scene, cfg, device="cpu")


def test_the_sh_parameters_reach_the_compiled_projection_as_they_are():
    _, m = _scene_and_method()
    tr = m.trainer
    assert tr.sh_degree() == 3
    out = tr.render(tr.scene.train[0].camera)
    node = out.extras["means2d"].grad_fn
    assert type(node).__name__ == "_ProjectCPUBackward"
    leaves = {id(f.variable) for f, _ in node.next_functions if type(f).__name__ == "AccumulateGrad"}
    g = tr.gaussians.params
    assert id(g["sh0"]) in leaves and id(g["shN"]) in leaves and id(g["means"]) in leaves
    out.rgb.sum().backward()
    assert g["shN"].grad is not None and g["shN"].grad.abs().sum() > 0


def test_unused_outputs_get_no_zero_gradients_and_the_same_result(monkeypatch):
    """A loss of the colours alone hands the CPU backward empty alpha/depth gradients (it reads them
    as zero) and gives the gradients of the same loss plus 0·alpha + 0·depth, to the bit."""
    cam = Camera.look_at([0.1, 0.0, -0.5], [0, 0, 3], [0, -1, 0], 30.0, 30.0, 32, 24)
    g = torch.Generator().manual_seed(2)
    n = 80
    z = 1.5 + 3 * torch.rand(n, generator=g)
    means = torch.stack([(torch.rand(n, generator=g) - 0.5) * z, (torch.rand(n, generator=g) - 0.5) * z, z], 1)
    base = dict(means3d=means, quats=torch.randn(n, 4, generator=g), scales=0.05 + 0.1 * torch.rand(n, 3, generator=g),
                opacities=0.3 + 0.6 * torch.rand(n, generator=g), colors=torch.rand(n, 3, generator=g))
    seen = []
    module = cpu.extension()
    real = module.backward

    def spy(g_rgb, g_alpha, g_depth, *rest):
        seen.append((g_alpha.numel(), g_depth.numel()))
        return real(g_rgb, g_alpha, g_depth, *rest)

    grads = []
    for with_zeros in (False, True):
        s = {k: v.clone().requires_grad_(True) for k, v in base.items()}
        out = rasterize(s["means3d"], s["quats"], s["scales"], s["opacities"], s["colors"], cam, mode="3dgs",
                        backend="cpu")
        loss = (out.rgb * torch.linspace(0, 1, out.rgb.numel()).reshape(out.rgb.shape)).sum()
        if with_zeros:
            loss = loss + 0 * out.alpha.sum() + 0 * out.depth.sum()
        with monkeypatch.context() as mp:
            mp.setattr(cpu, "extension", lambda: _Spy(module, spy))
            loss.backward()
        grads.append({k: v.grad for k, v in s.items()})
    assert seen[0] == (0, 0) and seen[1] == (32 * 24, 32 * 24)
    for k in base:
        assert torch.equal(grads[0][k], grads[1][k]), k


class _Spy:
    """The compiled module with its ``backward`` replaced."""

    def __init__(self, module, backward) -> None:
        self._m, self.backward = module, backward

    def __getattr__(self, name):
        return getattr(self._m, name)


def test_the_photometric_loss_hands_its_gradient_over_without_a_product():
    from smgs.train.image_loss import PhotometricLoss

    x = torch.rand(16, 12, 3, requires_grad=True)
    y = torch.rand(16, 12, 3)
    parts = PhotometricLoss(0.2, fused=True)(x, y)
    saved = parts.total.grad_fn.saved_tensors[0]
    (g1,) = torch.autograd.grad(parts.total, x, retain_graph=True)
    (g3,) = torch.autograd.grad(parts.total * 3.0, x)
    assert g1.data_ptr() == saved.data_ptr()           # the kernel's gradient itself
    torch.testing.assert_close(g3, 3.0 * g1, rtol=0, atol=0)
    assert parts.l1 == float(parts.values[0]) and parts.values.shape == (3,)
