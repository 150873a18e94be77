"""What the compiled backends (cpu, cuda) share around their kernels: the inputs in the kernels'
form, the gradients handed back and the output built.
The inputs were checked by ``smgs.raster.api.rasterize_splats`` before they arrive here."""

from __future__ import annotations

import torch

from smgs.raster.composite_inputs import CompositeSettings, Splats2D
from smgs.raster.types import RenderOutput, RenderStats

# Position of each tensor input of the compiled autograd Functions (ctx.needs_input_grad order).
INPUTS = ("means2d", "conics", "opacities", "colors", "depths", "alpha", "beta", "gamma", "background",
          "reg_values")


def kernel_inputs(sp: Splats2D, st: CompositeSettings) -> tuple[torch.Tensor | None, ...]:
    """The ten tensor inputs (``INPUTS``) as the kernels read them: contiguous float32, None where the
    mode ignores them, the background flat."""
    f32 = lambda t: None if t is None else t.to(torch.float32).contiguous()  # noqa: E731
    bg = None if sp.background is None else sp.background.to(device=sp.means2d.device,
                                                              dtype=torch.float32).reshape(-1)
    return (sp.means2d.contiguous(), sp.conics.contiguous(), sp.opacities.contiguous(), sp.colors.contiguous(),
            sp.depths.contiguous(), f32(sp.alpha) if st.use_gef else None, f32(sp.beta) if st.use_softmax else None,
            f32(sp.gamma) if st.use_softmax else None, None if bg is None else bg.contiguous(), f32(sp.reg_values))


def output_grads(ctx, g_rgb, g_alpha, g_depth, g_reg, alpha_out: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """The image gradients as the CPU kernel reads them: contiguous float32; an empty ``g_alpha`` /
    ``g_depth`` where the loss did not use that output (a Function with ``set_materialize_grads(False)``
    gets None there, and the kernel reads an empty one as zero: a training loss of the colours alone
    makes no [H, W] zeros for them, nor for the counters and the final transmittance), zeros where
    it did not use the colours, and an empty ``g_reg`` where nothing was regularised."""
    h, w = alpha_out.shape
    none = alpha_out.new_empty(0)
    g_rgb = alpha_out.new_zeros(h, w, ctx.n_channels) if g_rgb is None else g_rgb.contiguous().float()
    g_alpha = none if g_alpha is None else g_alpha.contiguous().float()
    g_depth = none if g_depth is None else g_depth.contiguous().float()
    if not ctx.n_reg:
        g_reg = none
    else:
        g_reg = alpha_out.new_zeros(h, w, 1 + 2 * ctx.n_reg) if g_reg is None else g_reg.contiguous().float()
    return g_rgb, g_alpha, g_depth, g_reg


def kernel_grads(ctx, grads, g_rgb: torch.Tensor, t_final: torch.Tensor, n_settings: int = 1) -> tuple:
    """The backward's return: the kernel's nine gradients (means2d ... gamma, reg_values) with the
    background's added, None for every input that needs none, then None for the settings."""
    gm, gc, go, gcol, gd, gal, gbe, gga, grv = grads
    g_bg = (g_rgb * t_final[..., None]).sum((0, 1)) if ctx.needs_input_grad[8] else None   # rgb += T·bg
    out = (gm, gc, go, gcol, gd, gal, gbe, gga, g_bg, grv)
    return tuple(g if need else None for g, need in zip(out, ctx.needs_input_grad)) + (None,) * n_settings


def kernel_output(st: CompositeSettings, rgb: torch.Tensor, alpha: torch.Tensor, depth: torch.Tensor,
                  reg: torch.Tensor | None, n_contrib: torch.Tensor, pairs: torch.Tensor,
                  leaders: torch.Tensor | None = None, list_end: torch.Tensor | None = None) -> RenderOutput:
    """The RenderOutput of a kernel's outputs (``reg`` None where no values were regularised,
    ``leaders`` None where the map was not asked for; ``list_end`` is kept in patch scope only)."""
    stats = RenderStats(n_contrib=n_contrib, pairs_evaluated=pairs,   # converted when read (RenderStats)
                        k_max=st.k_max if st.use_softmax else 2**31 - 1, scope=st.scope,
                        list_end=list_end if st.patch else None)
    return RenderOutput(rgb=rgb, alpha=alpha, depth=depth, stats=stats, reg=reg,
                        leaders=None if leaders is None else leaders.long())


def no_splats(sp: Splats2D, st: CompositeSettings) -> RenderOutput:
    """A render of zero splats (none in view): the background, zero alpha and depth, and zero
    gradients for every input. The compiled kernels read the regulariser's channel count from a
    non-empty ``reg_values`` only, so with none they returned ``reg`` [H, W, 0] and the ray
    variance failed on it; the reference has no per-splat work to do here and gives the
    documented shapes ([H, W, 1 + 2R]) with its outputs still in the autograd graph."""
    from smgs.raster.reference import rasterize_splats_reference

    return rasterize_splats_reference(sp, st)
