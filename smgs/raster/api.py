"""Public entry points of the renderer: choosing a backend and its variant (``smgs.raster.backends``,
the one registry) and calling it."""

from __future__ import annotations

import dataclasses
from typing import Callable

import torch

from smgs.camera import Camera
from smgs.plugins import load_target
from smgs.raster import checks
from smgs.raster import constants as K
from smgs.raster.backends import BACKEND_NAMES, BACKENDS, Renderer, Variant, as_renderer, variant
from smgs.raster.composite_inputs import CompositeSettings, Splats2D, composite_settings
from smgs.raster.device_glue import to_device
from smgs.raster.projection import ShColours, host_view, project_gaussians
from smgs.raster.ray_depth import check_sort, ray_depth
from smgs.raster.sh import num_sh_bases
from smgs.raster.types import Eq15, KMaxScope, RayDepth, RenderOutput, RenderStats

__all__ = ["rasterize", "rasterize_splats", "backend_available", "resolve_backend", "BACKEND_NAMES", "Renderer"]


def backend_available(name: str, device: torch.device | str,
                      dtype: torch.dtype = torch.float32) -> bool:
    """Whether ``name`` can render tensors of this device and dtype here. A compiled backend whose
    toolchain is present but whose build fails raises ``smgs.raster.jit.BuildError`` (the cause and
    the fix) rather than answering False."""
    spec = BACKENDS.get(name)
    device = torch.device(device)
    if spec is None or (spec.device is not None and device.type != spec.device) \
            or (spec.float32_only and dtype != torch.float32):
        return False
    if spec.available is None:
        return True
    try:
        is_available = load_target(spec.available, "renderer backend")
    except ImportError:
        return False
    return bool(is_available())


def resolve_backend(backend: str, device: torch.device | str, dtype: torch.dtype) -> str:
    """'auto' picks the fastest backend available for the tensors' device and dtype; it falls back
    to the reference only where a compiled backend lacks its toolchain or is switched off, never
    past a failed build (``BuildError``)."""
    if backend != "auto":
        if backend not in BACKENDS:
            raise ValueError(f"unknown renderer backend {backend!r}; expected 'auto' or one of {', '.join(BACKENDS)}")
        if not backend_available(backend, device, dtype):
            raise RuntimeError(f"renderer backend {backend!r} cannot render {dtype} tensors on "
                               f"{torch.device(device)}; use backend='auto' or 'reference'")
        return backend
    for name in ("cuda", "cpu"):
        if backend_available(name, device, dtype):
            return name
    return "reference"


def render_variant(backend: str | Renderer, device: torch.device | str, dtype: torch.dtype = torch.float32) -> Variant:
    """The backend and variant a render of these tensors takes (``backends.variant`` of the backend
    ``resolve_backend`` picks): what a result records."""
    choice = as_renderer(backend)
    return variant(choice, resolve_backend(choice.backend, device, dtype))


def _lean(choice: Renderer, device: torch.device, dtype: torch.dtype) -> bool:
    """Whether the render takes the lean glue (``device_glue``): never on the CPU; elsewhere where the
    backend it resolves to has that glue (one that cannot render here says so when it composites)."""
    if device.type == "cpu":
        return False
    try:
        return render_variant(choice, device, dtype).lean(device)
    except (RuntimeError, ValueError):
        return False


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
    out = _composite(host, st, Renderer("cpu" if on_cpu else "reference"), checks.InputChecks())
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
    backend: str | Renderer = "auto",
    eq15: Eq15 = "solved",
    reg_values: torch.Tensor | None = None,
    reg_depth_scale: float = 1.0,
    t_min: float = K.T_MIN,
    ray_depth: RayDepth | None = None,
    leaders: bool = False,
    k_max_scope: KMaxScope = K.DEFAULT_K_MAX_SCOPE,
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
    ``backend``: a backend's name (``auto``, ``reference``, ``cpu``, ``cuda``), or a
    ``smgs.raster.Renderer`` that also names its variants (``smgs.raster.backends``): e.g.
    ``Renderer("cuda", kernels="v2")``, the opt-in CUDA kernels (docs/cuda.md), with which
    ``ray_depth`` and ``leaders`` on CUDA tensors run on the GPU (the CPU window's twin, windows up to
    32 splats, no ``reg_values``) instead of on host copies; a variant left unset is its environment
    variable's (``SMGS_CUDA_KERNELS``, ``SMGS_CUDA_GLUE``), else the default.
    """
    choice = as_renderer(backend)
    st = composite_settings(width, height, mode, k_max, eq15, reg_depth_scale, t_min, k_max_scope, leaders)
    splats = Splats2D(means2d, conics, opacities, colors, depths, alpha, beta, gamma, background, reg_values,
                      ray_depth)
    lean = _lean(choice, means2d.device, means2d.dtype)
    return _composite(splats, st, choice, checks.InputChecks(defer=lean))


def _composite(splats: Splats2D, st: CompositeSettings, choice: Renderer, chk: checks.InputChecks) -> RenderOutput:
    """``rasterize_splats`` with its settings made and its input checks in ``chk`` (``rasterize``
    adds the 3D inputs'): decided before the backend runs, or, deferred (the lean GPU glue), read
    right after it."""
    _check_inputs(splats, st, chk)
    if chk.defer:   # the lean glue: nothing of a bad input renders before the refusal (checks.InputChecks)
        splats = dataclasses.replace(splats, opacities=chk.gate(splats.opacities))
    return _settled(chk, _compositor(splats, st, choice), splats, st)


def _compositor(splats: Splats2D, st: CompositeSettings, choice: Renderer) -> Callable[..., RenderOutput]:
    """The function that composites ``splats`` as ``choice`` asks: the global order through the
    variant's compositing kernels; a per-pixel order or the leading-splat map through its pixel
    kernels where it has them, else (``auto``'s per-pixel order) the CPU window or the reference,
    else host copies (``_on_host``)."""
    means2d, ray_depth, reg = splats.means2d, splats.ray_depth, splats.reg_values
    if ray_depth is not None:
        if ray_depth.coefs.shape != (splats.n, 9):
            raise ValueError(f"ray_depth.coefs must be [N,9] for the N={splats.n} splats, "
                             f"got {tuple(ray_depth.coefs.shape)}")
        if choice.backend != "auto":
            _check_pixel_kernels(variant(choice, choice.backend), reg)
    name = resolve_backend(choice.backend, means2d.device, means2d.dtype)
    v = variant(choice, name)
    kernels = v.kernel_set
    if ray_depth is None and not st.leaders:
        return load_target(kernels.composite, "renderer kernels")
    if kernels.pixel is not None and (reg is None or kernels.pixel_reg):
        return load_target(kernels.pixel, "renderer kernels")
    if ray_depth is not None and choice.backend == "auto":   # the CPU window (on host copies), or the reference
        fallback = _per_pixel_backend(means2d.device, means2d.dtype, reg)
        if fallback != "host":
            return load_target(BACKENDS[fallback].kernels["default"].pixel, "renderer kernels")
    elif v.spec.device == "cpu" and kernels.pixel is not None:   # it names reg_values itself
        return load_target(kernels.pixel, "renderer kernels")
    return _on_host


def _check_pixel_kernels(v: Variant, reg_values: torch.Tensor | None) -> None:
    """Refuse a per-pixel order that the backend asked for by name cannot render, naming the way out."""
    kernels = v.kernel_set
    if kernels.pixel is None:
        others = [k for k, ks in v.spec.kernels.items() if ks.pixel is not None]
        way = f"the kernels {', '.join(others)} (backend=Renderer({v.backend!r}, kernels={others[0]!r}), " \
              "docs/cuda.md), " if others else ""
        raise ValueError(f"sort='per_pixel' has no {v.backend.upper()} kernel among the {v.kernels} ones; use {way}"
                         "backend='reference' or 'auto'")
    if reg_values is not None and not kernels.pixel_reg and v.spec.device != "cpu":
        raise ValueError(f"sort='per_pixel' on the {v.backend.upper()} kernels takes no reg_values (the per-pixel "
                         "order has no regulariser sums); drop reg_values, or use backend='reference'")


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
    backend: str | Renderer = "auto",
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
    ``"patch"`` (``rasterize_splats``; docs/kmax-scope.md). ``backend`` (as ``rasterize_splats``): a
    variant whose kernels render 3D Gaussians themselves (``Kernels.fused``: the opt-in CUDA kernels,
    ``Renderer("cuda", kernels="v2")``) does so for a float32 render in the global order, projecting
    (and evaluating SH) in one fused kernel without compaction, so the extras' ``ids`` are every
    Gaussian and ``radii`` (0, 0) marks the culled ones (docs/cuda.md); every other render projects
    here, then composites through ``rasterize_splats``' choice.
    """
    check_sort(sort)
    choice = as_renderer(backend)
    _check_3d(means3d, quats, scales, opacities, colors_or_sh, sh_rest)
    device = means3d.device
    v = _fused_variant(choice, device, means3d.dtype, sort, leaders)
    st = composite_settings(camera.width, camera.height, mode, k_max, eq15, reg_depth_scale, t_min, k_max_scope,
                            leaders)
    sh_degree = _sh_degree(sh_degree, colors_or_sh, sh_rest)
    if sh_rest is not None and sh_rest.device != device:
        raise TypeError(f"sh_rest is on {sh_rest.device} but means3d is on {device}; give every input one device")
    lean = _lean(choice, device, means3d.dtype)
    # a fused render hands the per-Gaussian inputs to its compositing without rasterize_splats' checks:
    # they are checked here, in the same finiteness pass (one synchronisation, or none with the lean
    # glue: read after the render, or made by the fused kernel itself)
    more = _check_fused_inputs(means3d, opacities, colors_or_sh, alpha, beta, gamma, background, reg_values,
                               st) if v is not None else []
    chk = _checks_3d(camera, means3d, quats, scales, colors_or_sh, sh_rest, sh_degree, more,
                     in_kernel=v is not None and lean, defer=lean)
    sh = None if sh_degree is None else ShColours(colors_or_sh, sh_rest, sh_degree, clamp_sh_colors)
    if v is not None:
        coefs = colors_or_sh if sh is None or sh_rest is None else sh.coefficients()
        return _settled(chk, load_target(v.kernel_set.fused, "renderer kernels"), means3d, quats, scales, opacities,
                        coefs, camera, alpha, beta, gamma, background, reg_values, st, sh_degree, near_plane, eps2d,
                        clamp_sh_colors, input_checks=chk)
    gaussians = (means3d, quats, scales, opacities, colors_or_sh, alpha, beta, gamma, reg_values)
    return _project_and_composite(gaussians, camera, st, choice, chk, sh, sort, background, near_plane, eps2d,
                                  dense=lean and sort == "global" and not leaders)


def _check_3d(means3d, quats, scales, opacities, colors_or_sh, sh_rest) -> None:
    """The 3D inputs' shapes and dtypes."""
    n = means3d.shape[0]
    for name, t, shape in (("means3d", means3d, (n, 3)), ("quats", quats, (n, 4)), ("scales", scales, (n, 3)),
                           ("opacities", opacities, (n,))):
        if t.shape != shape:
            raise ValueError(f"{name} must be {list(shape)}, got {tuple(t.shape)}")
    checks.float_dtypes([("means3d", means3d), ("quats", quats), ("scales", scales), ("opacities", opacities),
                         ("colors_or_sh", colors_or_sh), *([("sh_rest", sh_rest)] if sh_rest is not None else [])])


def _fused_variant(choice: Renderer, device: torch.device, dtype: torch.dtype, sort: str,
                   leaders: bool) -> Variant | None:
    """The variant that renders these 3D Gaussians itself (``Kernels.fused``), None where the render
    projects here (the CPU, a per-pixel order, the leading-splat map, a variant without one)."""
    if device.type == "cpu" or sort != "global" or leaders:
        return None
    if choice.backend != "auto" and not any(k.fused for k in BACKENDS[choice.backend].kernels.values()):
        return None   # (resolved where it composites: a backend that cannot render here says so there)
    v = render_variant(choice, device, dtype)
    return v if v.kernel_set.fused is not None else None


def _checks_3d(camera: Camera, means3d, quats, scales, colors_or_sh, sh_rest, sh_degree, more, in_kernel: bool,
               defer: bool) -> checks.InputChecks:
    """The camera's and the 3D inputs' finiteness (and non-negative scales), decided now or deferred
    (the lean glue), or left to the fused kernel's own checks (``in_kernel``)."""
    chk = checks.InputChecks(defer=defer)
    cam_named = [("camera.K", camera.K), ("camera.viewmat", camera.viewmat)]
    if all(t.device.type == "cpu" for _, t in cam_named):   # the trainer's: decided once per camera (Camera.memo)
        camera.memo(("finite",), lambda: checks.finite(cam_named))
    else:
        chk.finite(cam_named)
    named = [("means3d", means3d), ("quats", quats), ("scales", scales), ("colors_or_sh", colors_or_sh),
             *_used_rest(sh_rest, sh_degree), *more]
    if in_kernel:   # the fused projection checks them itself: a flag it raises, read after the render
        chk.in_kernel(named, pos_inf_ok=("gamma",), non_negative_name="scales")
    else:
        chk.finite(named, pos_inf_ok=("gamma",), non_negative_name="scales")
    return chk


def _project_and_composite(gaussians: tuple, camera: Camera, st: CompositeSettings, choice: Renderer,
                           chk: checks.InputChecks, sh: ShColours | None, sort: str, background, near_plane: float,
                           eps2d: float, dense: bool) -> RenderOutput:
    """``rasterize``'s projection here, then the compositing of ``rasterize_splats``' choice.
    ``dense`` (the lean glue): no compaction, a culled Gaussian keeps its row and renders at
    opacity 0, so nothing waits for the count of survivors."""
    means3d, quats, scales, opacities, colors_or_sh, alpha, beta, gamma, reg_values = gaussians
    device = means3d.device
    # The camera packed on the host (with the centre where SH needs it) and copied over once per
    # camera (kept on it until it changes: Camera.memo).
    center = sh is not None
    view = camera.memo(("view", means3d.dtype, center, device),
                       lambda: to_device(host_view(camera, means3d.dtype, center=center), device))
    # The reference backend is the oracle: pure PyTorch throughout, so its projection is too. The
    # colours from SH are made with the projection (in its compiled pass where that runs).
    proj = project_gaussians(means3d, quats, scales, camera, near_plane=near_plane, eps2d=eps2d,
                             fused=False if choice.backend == "reference" else None, view=view, dense=dense, sh=sh)
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
    out = _composite(splats, st, choice, chk)
    if out.leaders is not None and ids.numel():   # projected index -> the caller's index (none: all -1)
        out.leaders = torch.where(out.leaders >= 0, ids[out.leaders.clamp_min(0)], out.leaders)
    out.extras.update(ids=ids, means2d=means2d, radii=proj.radii)
    return out
