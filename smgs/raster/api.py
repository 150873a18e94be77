"""Public entry points of the renderer and the choice of backend."""

from __future__ import annotations

import dataclasses
import importlib
from typing import Callable

import torch

from smgs.camera import Camera
from smgs.raster import checks
from smgs.raster import constants as K
from smgs.raster.composite_inputs import CompositeSettings, Splats2D, composite_settings
from smgs.raster.cuda_v2 import kernel_choice
from smgs.raster.device_glue import lean, to_device
from smgs.raster.projection import ShColours, host_view, project_gaussians
from smgs.raster.ray_depth import check_sort, ray_depth
from smgs.raster.sh import num_sh_bases
from smgs.raster.types import Eq15, KMaxScope, RayDepth, RenderOutput, RenderStats

# name -> "module:function"; every backend is fn(Splats2D, CompositeSettings) -> RenderOutput
# (smgs.raster.composite_inputs). Imported lazily so that listing backends never compiles or loads
# a kernel.
_BACKENDS: dict[str, str] = {
    "reference": "smgs.raster.reference:rasterize_splats_reference",
    "cpu": "smgs.raster.cpu:rasterize_splats_cpu",
    "cuda": "smgs.raster.cuda:rasterize_splats_cuda",
}


def _load_backend(name: str) -> Callable[..., RenderOutput]:
    if name not in _BACKENDS:
        raise ValueError(f"unknown renderer backend {name!r}; expected 'auto' or one of {', '.join(_BACKENDS)}")
    module, _, fn = _BACKENDS[name].partition(":")
    return getattr(importlib.import_module(module), fn)


def backend_available(name: str, device: torch.device | str,
                      dtype: torch.dtype = torch.float32) -> bool:
    """Whether ``name`` can render tensors of this device and dtype here. A compiled backend whose
    toolchain is present but whose build fails raises ``smgs.raster.jit.BuildError`` (the cause and
    the fix) rather than answering False."""
    device = torch.device(device)
    if name == "reference":
        return True
    if name == "cpu":
        if device.type != "cpu" or dtype != torch.float32:
            return False
        try:
            from smgs.raster import cpu
        except ImportError:
            return False
        return cpu.is_available()
    if name == "cuda":
        if device.type != "cuda" or dtype != torch.float32:
            return False
        from smgs.raster import cuda   # importing never touches CUDA

        return cuda.is_available()
    return False


def resolve_backend(backend: str, device: torch.device | str, dtype: torch.dtype) -> str:
    """'auto' picks the fastest backend available for the tensors' device and dtype; it falls back
    to the reference only where a compiled backend lacks its toolchain or is switched off, never
    past a failed build (``BuildError``)."""
    if backend != "auto":
        if backend not in _BACKENDS:
            _load_backend(backend)  # raises the error that lists the backends
        if not backend_available(backend, device, dtype):
            raise RuntimeError(f"renderer backend {backend!r} cannot render {dtype} tensors on "
                               f"{torch.device(device)}; use backend='auto' or 'reference'")
        return backend
    for name in ("cuda", "cpu"):
        if backend_available(name, device, dtype):
            return name
    return "reference"


BACKEND_NAMES: tuple[str, ...] = tuple(_BACKENDS)


def _mode_inputs(st: CompositeSettings, n: int, alpha, beta, gamma) -> list[tuple[str, torch.Tensor]]:
    """The per-splat parameters the mode uses (α with GEF, β and γ with softmax), each [N]."""
    needed = ([("alpha", alpha)] if st.use_gef else []) + ([("beta", beta), ("gamma", gamma)] if st.use_softmax else [])
    for name, t in needed:
        if t is None:
            raise ValueError(f"mode {st.mode!r} needs {name} [N]; got None")
        if t.shape != (n,):
            raise ValueError(f"{name} must be [N], got {tuple(t.shape)}")
    return needed


def _check_inputs(sp: Splats2D, st: CompositeSettings, chk: checks.InputChecks | None = None) -> None:
    """Shapes, dtypes and finiteness (``smgs.raster.checks`` has the policy), before any backend
    (the finiteness through ``chk`` where given, which may decide it after the render)."""
    means2d, conics, opacities, colors, depths, alpha, beta, gamma = sp.per_splat()
    background, reg_values = sp.background, sp.reg_values
    named = [("means2d", means2d), ("conics", conics), ("opacities", opacities), ("colors", colors),
             ("depths", depths), ("alpha", alpha), ("beta", beta), ("gamma", gamma)]
    checks.float_dtypes(named)
    n = means2d.shape[0]
    if means2d.shape != (n, 2):
        raise ValueError(f"means2d must be [N,2], got {tuple(means2d.shape)}")
    if conics.shape != (n, 3):
        raise ValueError(f"conics must be [N,3], got {tuple(conics.shape)}")
    if opacities.shape != (n,) or depths.shape != (n,):
        raise ValueError("opacities and depths must be [N]")
    if colors.dim() != 2 or colors.shape[0] != n or colors.shape[1] < 1:
        raise ValueError(f"colors must be [N,C] with C >= 1, got {tuple(colors.shape)}")
    _mode_inputs(st, n, alpha, beta, gamma)
    if background is not None and background.numel() != colors.shape[1]:
        raise ValueError(f"background must have {colors.shape[1]} channels (one per colour), "
                         f"got {background.numel()}")
    dev = means2d.device
    for name, t in named[1:] + [("reg_values", reg_values)]:   # the background is moved where needed
        if t is not None and t.device != dev:
            raise TypeError(f"{name} is on {t.device} but means2d is on {dev}; give every input one device")
    used = {"alpha": st.use_gef, "beta": st.use_softmax, "gamma": st.use_softmax}
    (chk or checks.InputChecks()).finite([(k, t) for k, t in named if used.get(k, True)]
                                         + [("background", background), ("reg_values", reg_values)],
                                         pos_inf_ok=("gamma",))


def _per_pixel_backend(device: torch.device, dtype: torch.dtype, reg_values: torch.Tensor | None) -> str:
    """``auto`` for sort="per_pixel": the CPU re-sorting window wherever it applies (no regulariser
    sums; on another device's tensors through host copies, ``"host"``), else the reference's exact
    order (which on a real scene needs far more memory than a GPU has)."""
    if reg_values is None and dtype == torch.float32 and backend_available("cpu", "cpu"):
        return "cpu" if device.type == "cpu" else "host"
    return "reference"


def _on_host(splats: Splats2D, st: CompositeSettings) -> RenderOutput:
    """The compositing on host copies of the splats through the cpu backend (the reference where
    that does not apply), the outputs moved back to the inputs' device: for what the CUDA backend
    has no kernel for. The copies are differentiable, so gradients flow back to the device."""
    device = splats.means2d.device
    host = splats.mapped(lambda t: t.cpu())
    on_cpu = host.reg_values is None and backend_available("cpu", "cpu", host.means2d.dtype)
    out = _composite(host, st, "cpu" if on_cpu else "reference", "default", checks.InputChecks())
    if device.type == "cpu":
        return out
    move = lambda t: None if t is None else t.to(device)  # noqa: E731
    return RenderOutput(rgb=move(out.rgb), alpha=move(out.alpha), depth=move(out.depth),
                        stats=RenderStats(move(out.stats.n_contrib), out.stats.pairs_evaluated, out.stats.k_max,
                                          out.stats.scope, move(out.stats.list_end)),
                        reg=move(out.reg), leaders=move(out.leaders))


def rasterize_splats(
    means2d: torch.Tensor,
    conics: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    depths: torch.Tensor,
    alpha: torch.Tensor | None,
    beta: torch.Tensor | None,
    gamma: torch.Tensor | None,
    width: int,
    height: int,
    mode: str = "softmax_gs",
    k_max: int = K.DEFAULT_K_MAX,
    background: torch.Tensor | None = None,
    backend: str = "auto",
    eq15: Eq15 = "solved",
    reg_values: torch.Tensor | None = None,
    reg_depth_scale: float = 1.0,
    t_min: float = K.T_MIN,
    ray_depth: RayDepth | None = None,
    leaders: bool = False,
    k_max_scope: KMaxScope = K.DEFAULT_K_MAX_SCOPE,
    cuda_kernels: str | None = None,
) -> RenderOutput:
    """Composite already-projected 2D splats front to back (Algorithm 1 of Softmax-GS).

    means2d [N,2] in pixels (pixel (i, j) has its centre at (i+0.5, j+0.5)); conics [N,3] = (a, b, c)
    of the inverse 2D covariance, used as given; opacities [N] in [0, 1]; colors [N,C]; depths [N];
    alpha (GEF sharpness), beta (softmax strength), gamma (depth decay) [N] or None where the mode
    ignores them. ``eq15`` selects the solved (default) or printed form of eq. (15).
    ``reg_values [N,R]`` (optional) adds per-pixel sums for the variance regulariser over the
    first k_max splats of each pixel, weighted by 1/(1 + (d - d_front)/reg_depth_scale)
    (the weights carry no gradient). ``t_min``: a splat whose vanilla update would bring the
    transmittance below it is not composited and the pixel stops (default 1e-4, the 3DGS rule;
    0 never stops). ``ray_depth`` (from ``smgs.raster.ray_depth.ray_depth``): each pixel orders its
    splats by the depth along its ray where the 3D response peaks, instead of all by ``depths``:
    exactly on the reference backend, through a re-sorting window of ``constants.SORT_WINDOW``
    splats on the cpu backend (no ``reg_values``; ``auto`` picks it wherever it applies, on CUDA
    tensors through differentiable host copies), not on the default cuda kernels (the opt-in v2 ones
    below). ``leaders``: the output's ``leaders``
    map too (``RenderOutput``; for the view-consistency metric): the cpu backend renders it through
    its per-pixel kernel (no ``reg_values``); the default cuda kernels have none, so there the splats
    are composited on host copies (cpu, else reference) and the outputs moved back. ``k_max_scope``:
    what the softmax head is (docs/kmax-scope.md): ``"pixel"``, each pixel's first k_max composited
    splats; ``"patch"``, the splats at positions < k_max of its 16x16 tile's depth-sorted list.
    ``cuda_kernels``: which CUDA kernels composite where the cuda backend does (``"default"``, or the
    opt-in ``"v2"``, docs/cuda.md); None reads ``$SMGS_CUDA_KERNELS`` (default ``"default"``). With
    ``"v2"``, ``ray_depth`` and ``leaders`` on CUDA tensors run on the GPU (the CPU window's twin,
    windows up to 32 splats, no ``reg_values``) instead of on host copies.
    """
    kernels = kernel_choice(cuda_kernels)
    st = composite_settings(width, height, mode, k_max, eq15, reg_depth_scale, t_min, k_max_scope, leaders)
    splats = Splats2D(means2d, conics, opacities, colors, depths, alpha, beta, gamma, background, reg_values,
                      ray_depth)
    return _composite(splats, st, backend, kernels, checks.InputChecks(defer=lean(means2d.device)))


def _composite(splats: Splats2D, st: CompositeSettings, backend: str, kernels: str,
               chk: checks.InputChecks) -> RenderOutput:
    """``rasterize_splats`` with its settings made and its input checks in ``chk`` (``rasterize``
    adds the 3D inputs'): decided before the backend runs, or, deferred (the lean GPU glue), read
    right after it."""
    _check_inputs(splats, st, chk)
    if chk.defer:   # the lean glue: nothing of a bad input renders before the refusal (checks.InputChecks)
        splats = dataclasses.replace(splats, opacities=chk.gate(splats.opacities))
    means2d, ray_depth = splats.means2d, splats.ray_depth
    if ray_depth is not None:
        if ray_depth.coefs.shape != (splats.n, 9):
            raise ValueError(f"ray_depth.coefs must be [N,9] for the N={splats.n} splats, "
                             f"got {tuple(ray_depth.coefs.shape)}")
        if backend == "cuda" and kernels != "v2":
            raise ValueError("sort='per_pixel' has no CUDA kernel among the default ones; use the opt-in kernels "
                             "(cuda_kernels='v2', docs/cuda.md), backend='reference' or 'auto'")
        if backend == "cuda" and splats.reg_values is not None:
            raise ValueError("sort='per_pixel' on the CUDA kernels takes no reg_values (the per-pixel order has no "
                             "regulariser sums); drop reg_values, or use backend='reference'")
    # the opt-in kernels order each pixel (and give the leading-splat map) on the GPU itself
    pixel_on_gpu = (kernels == "v2" and (ray_depth is not None or st.leaders) and splats.reg_values is None
                    and backend in ("auto", "cuda")
                    and resolve_backend(backend, means2d.device, means2d.dtype) == "cuda")
    if ray_depth is not None and backend == "auto" and not pixel_on_gpu:   # cpu, reference, or "host"
        name = _per_pixel_backend(means2d.device, means2d.dtype, splats.reg_values)
    else:
        name = resolve_backend(backend, means2d.device, means2d.dtype)
    if name == "host" or (st.leaders and name == "cuda" and not pixel_on_gpu):
        fn = _on_host
    else:
        fn = _load_backend(name)
    if pixel_on_gpu:
        from smgs.raster.cuda_v2 import rasterize_splats_pixel_cuda as fn
    elif name == "cuda" and kernels == "v2" and ray_depth is None and not st.leaders:
        from smgs.raster.cuda_v2 import rasterize_splats_cuda_v2 as fn
    return _settled(chk, fn, splats, st)


def _settled(chk: checks.InputChecks, fn: Callable[..., RenderOutput], *args, **kwargs) -> RenderOutput:
    """``fn(*args, **kwargs)`` with ``chk`` settled after it (deferred checks are read with the
    backend's own wait), also when it raised: a bad input is named rather than what it made the
    backend raise."""
    chk.start()
    try:
        out = fn(*args, **kwargs)
    except Exception:
        chk.settle()
        raise
    chk.settle()
    return out


def _check_fused_inputs(means3d, opacities, colors_or_sh, alpha, beta, gamma, background, reg_values,
                        st: CompositeSettings) -> list[tuple[str, torch.Tensor | None]]:
    """What ``rasterize_splats`` checks of the inputs that the fused path hands to the compositing
    without going through it (the 2D splats are the kernel's own); returns those whose finiteness
    the caller checks (γ may be +inf)."""
    needed = _mode_inputs(st, means3d.shape[0], alpha, beta, gamma)
    checks.float_dtypes([("means3d", means3d), *needed])
    nch = colors_or_sh.shape[-1]
    if background is not None and background.numel() != nch:
        raise ValueError(f"background must have {nch} channels (one per colour), got {background.numel()}")
    for name, t in [("opacities", opacities), ("colors_or_sh", colors_or_sh), *needed, ("reg_values", reg_values)]:
        if t is not None and t.device != means3d.device:
            raise TypeError(f"{name} is on {t.device} but means3d is on {means3d.device}; give every input one device")
    return [("opacities", opacities), *needed, ("background", background), ("reg_values", reg_values)]


def _sh_degree(sh_degree: int | None, colors_or_sh: torch.Tensor, sh_rest: torch.Tensor | None = None) -> int | None:
    """``sh_degree`` after rasterize's shape rule for ``colors_or_sh`` (and ``sh_rest``)."""
    if sh_degree is None and colors_or_sh.dim() != 2:
        raise ValueError("colors_or_sh without sh_degree must be [N,C] colours")
    if sh_degree is not None and colors_or_sh.dim() != 3:
        raise ValueError("colors_or_sh with sh_degree must be [N,K,C] SH coefficients")
    if sh_degree is not None and not 0 <= sh_degree <= 3:
        raise ValueError(f"sh_degree must be 0..3, got {sh_degree}")
    if sh_rest is None:
        if sh_degree is not None and colors_or_sh.shape[1] < num_sh_bases(sh_degree):
            raise ValueError(f"sh_degree {sh_degree} needs {num_sh_bases(sh_degree)} SH coefficients, "
                             f"colors_or_sh has {colors_or_sh.shape[1]}")
        return sh_degree
    if sh_degree is None:
        raise ValueError("sh_rest (the SH coefficients after the first) needs sh_degree")
    n, _, c = colors_or_sh.shape
    if colors_or_sh.shape[1] != 1 or sh_rest.dim() != 3 or sh_rest.shape[0] != n or sh_rest.shape[2] != c:
        raise ValueError(f"with sh_rest, colors_or_sh must be [N,1,C] (the first SH coefficient) and sh_rest "
                         f"[N,K-1,C]; got {tuple(colors_or_sh.shape)} and {tuple(sh_rest.shape)}")
    if 1 + sh_rest.shape[1] < num_sh_bases(sh_degree):
        raise ValueError(f"sh_degree {sh_degree} needs {num_sh_bases(sh_degree)} SH coefficients, "
                         f"colors_or_sh and sh_rest have {1 + sh_rest.shape[1]}")
    return sh_degree


def _used_rest(sh_rest: torch.Tensor | None, sh_degree: int | None) -> list[tuple[str, torch.Tensor]]:
    """The coefficients of ``sh_rest`` the degree reads (a view), named for the input checks."""
    if sh_rest is None or sh_degree is None:
        return []
    return [("sh_rest", sh_rest[:, :num_sh_bases(sh_degree) - 1])]


def rasterize(
    means3d: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    colors_or_sh: torch.Tensor,
    camera: Camera,
    alpha: torch.Tensor | None = None,
    beta: torch.Tensor | None = None,
    gamma: torch.Tensor | None = None,
    mode: str = "softmax_gs",
    k_max: int = K.DEFAULT_K_MAX,
    sh_degree: int | None = None,
    background: torch.Tensor | None = None,
    backend: str = "auto",
    eq15: Eq15 = "solved",
    reg_values: torch.Tensor | None = None,
    reg_depth_scale: float = 1.0,
    near_plane: float = K.NEAR_PLANE,
    eps2d: float = K.EPS2D,
    clamp_sh_colors: bool = True,
    t_min: float = K.T_MIN,
    sort: str = "global",
    leaders: bool = False,
    k_max_scope: KMaxScope = K.DEFAULT_K_MAX_SCOPE,
    cuda_kernels: str | None = None,
    sh_rest: torch.Tensor | None = None,
) -> RenderOutput:
    """Render 3D Gaussians (activated values) through ``camera``.

    quats are wxyz and normalised here; colors_or_sh is [N,C] colours, or [N,K,C] SH coefficients
    evaluated at ``sh_degree`` (+0.5 and clamped at 0 as 3DGS, unless ``clamp_sh_colors=False``).
    ``sh_rest``: the SH coefficients in two parts, as a trainer keeps them (3DGS's features_dc and
    features_rest), read without joining them: colors_or_sh [N,1,C] the first, sh_rest [N,K-1,C] the
    others. On float32 CPU tensors the colours are made in the compiled projection, for the
    Gaussians it keeps.
    ``extras`` of the output hold the projection (``ids``, ``means2d``, ``radii``), so a
    densification strategy can read the 2D mean gradients (call ``retain_grad`` on ``means2d``).
    ``sort``: ``"global"`` orders all splats by the view depth of their centres (3DGS);
    ``"per_pixel"`` orders each pixel's splats by the depth along its ray where the 3D Gaussian's
    response peaks (StopThePop; ``smgs.raster.ray_depth``; backends as ``rasterize_splats``). The
    order is not differentiated; the compositing and its gradients are those of the mode.
    ``leaders``: the output's ``leaders`` map too, as indices of the Gaussians given here
    (``rasterize_splats`` says how each backend renders it). ``k_max_scope``: ``"pixel"`` or
    ``"patch"`` (``rasterize_splats``; docs/kmax-scope.md). ``cuda_kernels`` (as
    ``rasterize_splats``): with ``"v2"`` a float32 CUDA render in the global order projects (and
    evaluates SH) in one fused kernel without compaction, so the extras' ``ids`` are every Gaussian
    and ``radii`` (0, 0) marks the culled ones (docs/cuda.md).
    """
    check_sort(sort)
    kernels = kernel_choice(cuda_kernels)
    n = means3d.shape[0]
    for name, t, shape in (("means3d", means3d, (n, 3)), ("quats", quats, (n, 4)), ("scales", scales, (n, 3)),
                           ("opacities", opacities, (n,))):
        if t.shape != shape:
            raise ValueError(f"{name} must be {list(shape)}, got {tuple(t.shape)}")
    checks.float_dtypes([("means3d", means3d), ("quats", quats), ("scales", scales), ("opacities", opacities),
                         ("colors_or_sh", colors_or_sh), *([("sh_rest", sh_rest)] if sh_rest is not None else [])])
    device = means3d.device
    lean_glue = lean(device)
    on_cuda = device.type != "cpu" and backend in ("auto", "cuda") \
        and resolve_backend(backend, device, means3d.dtype) == "cuda"
    fused = kernels == "v2" and sort == "global" and not leaders and on_cuda
    # the fused path hands the per-Gaussian inputs to its compositing without rasterize_splats'
    # checks: they are checked here, in the same finiteness pass (one synchronisation, or none
    # with the lean glue: read after the render)
    st = composite_settings(camera.width, camera.height, mode, k_max, eq15, reg_depth_scale, t_min, k_max_scope,
                            leaders)
    sh_degree = _sh_degree(sh_degree, colors_or_sh, sh_rest)
    if sh_rest is not None and sh_rest.device != device:
        raise TypeError(f"sh_rest is on {sh_rest.device} but means3d is on {device}; give every input one device")
    more = _check_fused_inputs(means3d, opacities, colors_or_sh, alpha, beta, gamma, background, reg_values,
                               st) if fused else []
    chk = checks.InputChecks(defer=lean_glue)
    cam_named = [("camera.K", camera.K), ("camera.viewmat", camera.viewmat)]
    if all(t.device.type == "cpu" for _, t in cam_named):   # the trainer's: decided once per camera (Camera.memo)
        camera.memo(("finite",), lambda: checks.finite(cam_named))
    else:
        chk.finite(cam_named)
    named = [("means3d", means3d), ("quats", quats), ("scales", scales), ("colors_or_sh", colors_or_sh),
             *_used_rest(sh_rest, sh_degree), *more]
    if fused and lean_glue:   # the fused projection checks them itself: a flag it raises, read after the render
        chk.in_kernel(named, pos_inf_ok=("gamma",), non_negative_name="scales")
    else:
        chk.finite(named, pos_inf_ok=("gamma",))
        chk.non_negative("scales", scales)
    sh = None if sh_degree is None else ShColours(colors_or_sh, sh_rest, sh_degree, clamp_sh_colors)
    if fused:
        from smgs.raster.cuda_v2 import rasterize_fused

        coefs = colors_or_sh if sh is None or sh_rest is None else sh.coefficients()
        return _settled(chk, rasterize_fused, means3d, quats, scales, opacities, coefs, camera, alpha, beta,
                        gamma, background, reg_values, st, sh_degree, near_plane, eps2d, clamp_sh_colors, input_checks=chk)
    # The camera packed on the host (with the centre where SH needs it) and copied over once per
    # camera (kept on it until it changes: Camera.memo).
    center = sh is not None
    view = camera.memo(("view", means3d.dtype, center, device),
                       lambda: to_device(host_view(camera, means3d.dtype, center=center), device))
    # Lean glue: no compaction (a culled Gaussian keeps its row and renders at opacity 0), so no
    # host wait; on the CUDA backend's plain path only (the host paths take compacted splats).
    dense = lean_glue and on_cuda and sort == "global" and not leaders
    # The reference backend is the oracle: pure PyTorch throughout, so its projection is too. The
    # colours from SH are made with the projection (in its compiled pass where that runs).
    proj = project_gaussians(means3d, quats, scales, camera, near_plane=near_plane, eps2d=eps2d,
                             fused=False if backend == "reference" else None, view=view, dense=dense, sh=sh)
    ids = proj.ids
    if dense:
        pick = (lambda t: t)
    elif device.type == "cpu":   # whole rows copied (t[ids] indexes element by element: ~4x slower here)
        pick = (lambda t: None if t is None else t.index_select(0, ids))
    else:
        pick = (lambda t: None if t is None else t[ids])
    colors = pick(colors_or_sh) if sh is None else proj.colors
    # a culled row of the dense projection reaches no pixel at opacity 0 (every backend skips a
    # splat under 1/255), so it renders as if absent
    opac = opacities * proj.visible if dense else pick(opacities)
    means2d = proj.means2d
    rd = ray_depth(means3d[ids], quats[ids], scales[ids], camera) if sort == "per_pixel" else None
    splats = Splats2D(means2d, proj.conics, opac, colors, proj.depths, pick(alpha), pick(beta), pick(gamma),
                      background, pick(reg_values), rd)
    out = _composite(splats, st, backend, kernels, chk)
    if out.leaders is not None and ids.numel():   # projected index -> the caller's index (none: all -1)
        out.leaders = torch.where(out.leaders >= 0, ids[out.leaders.clamp_min(0)], out.leaders)
    out.extras.update(ids=ids, means2d=means2d, radii=proj.radii)
    return out
