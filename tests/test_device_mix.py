"""No operation mixes the run's device with the host's, checked without a GPU.

Every ``device=cuda`` run once failed at its first render: the input check stacked the camera's
sums (the camera stays on the host) with the splats' (on the GPU), and ``torch.stack`` refuses
tensors of two devices. On a CPU-only machine both are CPU tensors, so nothing noticed. Here the
splats, the model and the training images live on a stand-in device (tests/device_mix.py: tensors
that report ``meta`` and compute on the CPU) while cameras and scenes stay on the host as in a
GPU run; any operator whose tensor inputs sit on both raises ``MixedDevices`` naming our line. The
renders take the CUDA backend's Python path (its binding replaced by a stand-in that computes with
the CPU backend), so the 3D render, a training step and a protocol cell's evaluation (metrics, FPS,
view consistency) run the code a GPU run runs.
"""

from __future__ import annotations

import pytest
import torch
from device_check import fit_config
from device_mix import OTHER, MixedDevices, Remote, other_device, simulated_gpu

from baselines import create_method
from smgs import Camera
from smgs.data.patterns import pattern_scene
from smgs.raster import rasterize
from smgs.raster.types import MODES

CPU = torch.device("cpu")


def test_the_stand_in_refuses_what_cuda_refuses_and_allows_what_it_allows():
    with other_device():
        x = torch.arange(4.0).to(OTHER)
        assert isinstance(x, Remote) and x.device == OTHER
        host_sum = torch.ones(3).sum()
        with pytest.raises(MixedDevices, match=r"aten\.stack.*tests/test_device_mix.py"):
            torch.stack([x.sum(), host_sum])            # the bug: one sum per device, stacked
        with pytest.raises(MixedDevices, match=r"aten\.mm"):
            x[None, :] @ torch.ones(4, 1)
        y = x * host_sum + torch.tensor(2.0)           # 0-dim host tensors are scalars to CUDA too
        assert y.device == OTHER and y.cpu().tolist() == [2.0, 5.0, 8.0, 11.0]
        assert torch.zeros(2, device=OTHER).device == OTHER and torch.tensor([1.0], device=OTHER).device == OTHER


def _splats(n: int, device, seed: int = 0, sh: bool = False) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    r = lambda *s: torch.rand(*s, generator=g)  # noqa: E731
    z = 2 + 2 * r(n)
    d = dict(means3d=torch.stack([(r(n) - 0.5) * z, (r(n) - 0.5) * z, z], 1), quats=torch.randn(n, 4, generator=g),
             scales=0.05 + 0.1 * r(n, 3), opacities=0.3 + 0.6 * r(n),
             colors=r(n, 4, 3) * 0.3 if sh else r(n, 3), alpha=0.5 + 2 * r(n), beta=4 * r(n), gamma=2 * r(n))
    return {k: v.to(device).requires_grad_(True) for k, v in d.items()}


def _render(s, cam, mode, backend="auto", sh=False):
    bg = torch.tensor([0.1, 0.2, 0.3], device=s["means3d"].device)
    return rasterize(s["means3d"], s["quats"], s["scales"], s["opacities"], s["colors"], cam, alpha=s["alpha"],
                     beta=s["beta"], gamma=s["gamma"], mode=mode, sh_degree=1 if sh else None, background=bg,
                     backend=backend)


@pytest.mark.parametrize("mode", MODES)
def test_a_3d_render_and_its_gradients_with_the_camera_on_the_host(monkeypatch, mode):
    """The camera as the trainer passes it (host tensors); splats on the other device, through the
    CUDA backend's Python path. The images and gradients are the CPU backend's (the stand-in's
    binding computes with it), so the values are checked too, not only the devices."""
    cam = Camera.look_at([0.1, -0.2, -1.0], [0, 0, 3], [0, -1, 0], 40.0, 42.0, 24, 18)
    sh = mode == "softmax_gs"
    want = _splats(60, CPU, sh=sh)
    ref = _render(want, cam, mode, backend="cpu", sh=sh)
    (ref.rgb.mean() + ref.depth.mean()).backward()
    with simulated_gpu(monkeypatch):
        s = _splats(60, OTHER, sh=sh)
        out = _render(s, cam, mode, sh=sh)
        (out.rgb.mean() + out.depth.mean()).backward()
        assert out.rgb.device == OTHER and s["means3d"].grad.device == OTHER
        torch.testing.assert_close(out.rgb.cpu(), ref.rgb, rtol=1e-5, atol=1e-6)
        for k, v in s.items():
            if want[k].grad is not None:
                torch.testing.assert_close(v.grad.cpu(), want[k].grad, rtol=1e-4, atol=1e-6, msg=k)


def test_the_reference_backend_renders_device_splats_through_a_host_camera(monkeypatch):
    cam = Camera.look_at([0.0, 0.0, -1.0], [0, 0, 3], [0, -1, 0], 12.0, 12.0, 8, 6)
    with simulated_gpu(monkeypatch):
        s = _splats(6, OTHER)
        out = _render(s, cam, "softmax_gs", backend="reference")
        out.rgb.sum().backward()
        assert out.rgb.device == OTHER and s["quats"].grad.device == OTHER


@pytest.mark.parametrize("backend", ["reference", "auto"])
def test_a_host_background_is_taken_with_device_splats_also_when_nothing_is_in_view(monkeypatch, backend):
    """The compiled backends move the background to the splats' device; the reference, which also
    renders the compiled backends' views with nothing in them (kernel_args.no_splats), did not."""
    cam = Camera.look_at([0.0, 0.0, -1.0], [0, 0, 3], [0, -1, 0], 12.0, 12.0, 8, 6)
    bg = torch.tensor([0.1, 0.2, 0.3])      # on the host
    with simulated_gpu(monkeypatch):
        for behind in (False, True):
            s = _splats(6, OTHER)
            if behind:
                with torch.no_grad():
                    s["means3d"][:, 2] = -5.0
            out = rasterize(s["means3d"], s["quats"], s["scales"], s["opacities"], s["colors"], cam, mode="3dgs",
                            background=bg, backend=backend)
            assert out.rgb.device == OTHER
            if behind:
                torch.testing.assert_close(out.rgb.cpu(), bg.expand(6, 8, 3), rtol=0, atol=0)


@pytest.mark.parametrize("glue", ["verified", "lean"])
@pytest.mark.parametrize("method", ["3dgs", "softmax_gs"])
def test_training_steps_on_another_device_than_the_scene(monkeypatch, method, glue):
    """A fit that clones, splits, prunes and resets, trained on the other device; the scene (images,
    cameras) stays on the host, as a loaded scene does on a GPU run. With the lean glue the
    densification reads the dense projection (every Gaussian's row, radius 0 where culled)."""
    monkeypatch.setenv("SMGS_CUDA_GLUE", glue)
    scene = pattern_scene("circle4", 12)
    with simulated_gpu(monkeypatch):
        m = create_method(method, scene, fit_config(method), device=OTHER)
        for s in range(8):
            m.train_step(s)
        out = m.render(scene.test[0].camera)
    assert out.rgb.device == OTHER and m.num_gaussians() != 4


def test_a_protocol_cell_trains_and_evaluates_on_another_device_than_its_scene(tmp_path, monkeypatch):
    """The runner's whole cell on the other device: training with a checkpoint, intermediate and
    final metrics (PSNR/SSIM/LPIPS/FLIP), render FPS, peak memory and the view-consistency video,
    on a small procedural scene (SfM init, SH, background, trajectory) held on the host."""
    import protocols.train_loop as tl
    from hydra import compose, initialize_config_dir

    from protocols.cell import run_cell
    from protocols.run import CONFIG_DIR, plan
    from smgs.data.procedural import make_procedural_scene

    ov = ["+experiment=smoke", "grid.methods=[softmax_gs]", "protocol.steps=4", "report=false",
          "eval.fps_repeats=1", "device=cpu", f"out_dir={tmp_path}", "checkpoint_every=2", "eval.consistency=true",
          "eval.consistency_max_width=16"]
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        payload = plan(compose(config_name="config", overrides=ov), ov)[1][0]
    scene = make_procedural_scene(n_views=4, size=(24, 16), n_points=200, n_trajectory=10, supersample=1)
    monkeypatch.setattr(tl, "load_scene_for", lambda cfg: scene)
    payload["config"]["device"] = str(OTHER)
    with simulated_gpu(monkeypatch):
        s = run_cell(payload)
    log = (tmp_path / payload["key"] / "log.txt").read_text()
    assert s["status"] == "ok", log[-3000:]
    assert "MixedDevices" not in log


def test_the_lean_glue_trains_what_the_verified_glue_trains(monkeypatch):
    """Eight steps of a densifying fit on the other device with each glue: the same Gaussians, to
    the bit (the dense projection's culled rows reach no pixel and add nothing to the densifier's
    statistics)."""
    scene = pattern_scene("circle4", 12)
    params = {}
    for glue in ("verified", "lean"):
        monkeypatch.setenv("SMGS_CUDA_GLUE", glue)
        with simulated_gpu(monkeypatch):
            m = create_method("softmax_gs", scene, fit_config("softmax_gs"), device=OTHER)
            for s in range(8):
                m.train_step(s)
            params[glue] = {k: v.detach().cpu() for k, v in m.trainer.gaussians.params.items()}
    assert params["lean"].keys() == params["verified"].keys()
    for k, v in params["verified"].items():
        assert torch.equal(params["lean"][k], v), k
