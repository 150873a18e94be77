"""Bad inputs to the renderer get the same clear error on every backend (smgs.raster.checks)."""

import math

import pytest
import torch

from smgs.camera import Camera
from smgs.raster import rasterize, rasterize_splats
from smgs.raster.stability import base_scene

BACKENDS = ["reference", "cpu", pytest.param("cuda", marks=pytest.mark.gpu)]


def _splats(backend):
    dev = "cuda" if backend == "cuda" else "cpu"
    return {k: v.to(dev, torch.float32) for k, v in base_scene(torch.float32).items()}


def _render(s, backend, width=8, height=8, mode="softmax_gs"):
    return rasterize_splats(s["means2d"], s["conics"], s["opacities"], s["colors"], s["depths"], s["alpha"],
                            s["beta"], s["gamma"], width, height, mode=mode, backend=backend)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("name", ["means2d", "conics", "opacities", "colors", "depths", "alpha", "beta", "gamma"])
@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_inputs_are_refused_naming_the_tensor(backend, name, bad):
    s = _splats(backend)
    if name == "gamma" and bad == math.inf:
        s[name].fill_(bad)  # a hard depth decay: valid, rendered finite
        assert torch.isfinite(_render(s, backend).rgb).all()
        return
    s[name].view(-1)[1] = bad
    with pytest.raises(ValueError, match=rf"{name} has 1 NaN or -?inf value"):
        _render(s, backend)


@pytest.mark.parametrize("backend", BACKENDS)
def test_an_unused_parameter_is_not_checked(backend):
    s = _splats(backend)
    s["alpha"].fill_(math.nan)  # 3dgs uses neither alpha nor beta/gamma
    s["beta"].fill_(math.nan)
    assert torch.isfinite(_render(s, backend, mode="3dgs").rgb).all()


@pytest.mark.parametrize("backend", BACKENDS)
def test_integer_tensors_and_mixed_dtypes_are_refused(backend):
    s = _splats(backend)
    s["means2d"] = s["means2d"].long()
    with pytest.raises(TypeError, match=r"means2d has dtype torch.int64.*float32 or float64"):
        _render(s, backend)
    s = _splats(backend)
    s["colors"] = s["colors"].double()
    with pytest.raises(TypeError, match=r"colors is torch.float64 but means2d is torch.float32"):
        _render(s, backend)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("width, height, err, match", [
    (8.0, 8, TypeError, r"width must be an integer number of pixels, got float 8.0"),
    (8, True, TypeError, r"height must be an integer"),
    (0, 8, ValueError, r"width=0 is outside 1..16384"),
    (20000, 20000, ValueError, r"width=20000 is outside"),
])
def test_image_sizes_are_checked_before_allocating(backend, width, height, err, match):
    with pytest.raises(err, match=match):
        _render(_splats(backend), backend, width, height)


def _camera(**over):
    K = torch.tensor([[10.0, 0, 8], [0, 10.0, 8], [0, 0, 1]])
    return Camera(K=over.get("K", K), viewmat=over.get("viewmat", torch.eye(4)), width=16, height=16)


def _gaussians():
    g = torch.Generator().manual_seed(0)
    n = 5
    means = torch.rand(n, 3, generator=g) - 0.5
    means[:, 2] += 3
    return means, torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1), torch.full((n, 3), 0.1), torch.full((n,), 0.8), \
        torch.rand(n, 3, generator=g)


@pytest.mark.parametrize("backend", ["reference", "cpu"])
def test_negative_scales_and_a_nan_camera_are_refused(backend):
    means, quats, scales, opac, cols = _gaussians()
    assert rasterize(means, quats, scales, opac, cols, _camera(), mode="3dgs", backend=backend).rgb.abs().sum() > 0
    scales[2, 1] = -0.1
    with pytest.raises(ValueError, match="scales has 1 negative value"):
        rasterize(means, quats, scales, opac, cols, _camera(), mode="3dgs", backend=backend)
    scales[2, 1] = 0.1
    vm = torch.eye(4)
    vm[0, 3] = math.nan
    with pytest.raises(ValueError, match=r"camera.viewmat has 1 NaN or inf"):
        rasterize(means, quats, scales, opac, cols, _camera(viewmat=vm), mode="3dgs", backend=backend)
    means[0, 0] = math.nan
    with pytest.raises(ValueError, match=r"means3d has 1 NaN or inf"):
        rasterize(means, quats, scales, opac, cols, _camera(), mode="3dgs", backend=backend)


def _outcome(f):
    try:
        f()
    except (ValueError, TypeError) as exc:
        return type(exc).__name__, str(exc)
    return None


def _bad_tensors():
    """Tensors the checks see in a training step, with bad values where each path could differ: NaN,
    ±inf, −0 and negatives, at the ends of vectorised runs, in strided views (the trainer's
    ``sh_rest[:, :k]``, whose rows are contiguous, and a transpose, whose rows are not)."""
    g = torch.Generator().manual_seed(4)
    rest = torch.randn(1001, 15, 3, generator=g)
    rest[7, 2, 1], rest[1000, 14, 2], rest[500, 5, 0] = math.nan, math.inf, -0.0   # [500, 5] is past k = 4
    opac = torch.rand(1000, generator=g)
    opac[-1] = -math.inf
    gamma = torch.rand(333, generator=g)
    gamma[0], gamma[17] = math.inf, math.inf
    scales = torch.rand(1000, 3, generator=g)
    scales[999, 2], scales[0, 0], scales[5, 1] = -1e-30, -0.0, -2.0
    return [("sh_rest", rest[:, :4]), ("sh_rest", rest[:, 5:]), ("rest", rest), ("opacities", opac),
            ("opacities", opac[:-1]), ("gamma", gamma), ("means2d", torch.randn(64, 2, generator=g).t()),
            ("scales", scales), ("scales", scales.abs()), ("empty", torch.empty(0, 3))]


@pytest.mark.usefixtures("cpu_isa")
def test_the_compiled_checks_decide_and_word_as_pytorch(monkeypatch):
    """Float32 CPU tensors are counted in one compiled pass (checks._compiled_counts, once the compiled
    projection is loaded) instead of PyTorch sums: the same inputs refused with the same words, the
    exact counts (every SIMD path)."""
    from smgs.raster import checks, projection

    assert projection.fused_available()
    tensors = _bad_tensors()
    compiled = checks._compiled_counts(tensors, ("gamma",))
    want = [(int((t.isnan() | (t == -math.inf)).sum()) if n == "gamma" else int((~t.isfinite()).sum()),
             int((t < 0).sum())) for n, t in tensors]
    assert compiled == want and want[0][0] == 1 and want[1][0] == 1 and want[5] == (0, 0)
    assert checks.nonfinite_counts([t for _, t in tensors]) == [int((~t.isfinite()).sum()) for _, t in tensors]
    calls = [lambda n=n, t=t: checks.finite([(n, t)], pos_inf_ok=("gamma",)) for n, t in tensors]
    calls += [lambda n=n, t=t: checks.non_negative(n, t) for n, t in tensors if n == "scales"]
    calls.append(lambda: checks.finite([(n, t) for n, t in tensors[3:]], pos_inf_ok=("gamma",)))
    with_kernel = [_outcome(f) for f in calls]
    monkeypatch.setattr(checks, "_compiled_counts", lambda *a: None)   # the PyTorch path
    assert with_kernel == [_outcome(f) for f in calls]
    assert sum(o is not None for o in with_kernel) == 6, with_kernel
