"""Pure-PyTorch compositing of projected splats: the oracle every other backend is tested against.

Dense (every splat is tested at every pixel), differentiable through autograd, any dtype (float64
for gradcheck and the stiff-case battery) and any device. Slow by design: use it on small scenes.

The per-pixel loop is Algorithm 1 of the Softmax-GS supplementary with these changes, all
algebraically equal to the paper's solved system and written so that no step can produce 0/0,
inf·0 or a catastrophic cancellation (each is exercised by tests/test_raster_stiff.py):

* the transmittance T and the absorbance A = 1 - T are both carried, A as A + a·T, so tiny
  opacities are not lost in 1 - T; the softmax step sets them to the vanilla product directly,
  which is what eqs. (14) and (16) maintain;
* the running depth / exponent means are updated incrementally, d += (d_k - d)·w, so a mean of
  equal depths stays bit-exact (s = 1 exactly at any γ);
* the two softmax weights are two sigmoids, never 1 - w (which rounds to 0 at large β·Δp);
* eq. (15) solved: ã_cur = â_cur(1-T)/(â_cur + â_past·T) with the un-updated â_past (default), or
  as printed in line 14 of Algorithm 1 (``eq15="printed"``);
* the root of eq. (16) as m = 2C/(A + √D), D = (ā_cur - ā_past)² + 4·ā_cur·ā_past·T_orig (a sum
  of non-negative terms), and m = 1 exactly where it is 1 by construction (s = 0, or s = 1 with the
  solved eq. 15);
* the past colour is rescaled by r = ā_past/a_past written without dividing by a_past:
  r = m·(s·w_past·(1-T_orig)/(â_past + â_cur) + 1 - s), and line 21 as T_past = T + a_past·(1 - r),
  which is T exactly where the softmax changes nothing (s = 0);
* -p = ½dᵀQd in the LDLᵀ form of the conic, factored once per splat in float64 (quadratic_form);
* (-p)^α uses q = max(-p, 0) and defines q^α and its gradients as 0 at q = 0;
* γ·|Δd| is 0 when Δd = 0 (γ may be inf), and capped where s underflows to 0 anyway.

The depth channel is composited as one more colour channel (so it is rescaled with the colour,
as Algorithm 1 does for c_past) and divided by alpha at the end.

The softmax head (docs/kmax-scope.md): in ``pixel`` scope a pixel's first k_max composited splats;
in ``patch`` scope the splats at positions < k_max of its tile's depth-sorted list, which this dense
renderer takes from an emulation of the compiled backends' binning (``smgs.raster.tiles``). The
running means are updated by head steps only (a tail step never precedes a head step in the global
order, so this changes nothing there; in a per-pixel order under patch scope it can).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from smgs.raster import constants as K
from smgs.raster.tiles import list_positions
from smgs.raster.composite_inputs import CompositeSettings, Splats2D
from smgs.raster.types import RenderOutput, RenderStats


def _sorted_order(depths: torch.Tensor) -> torch.Tensor:
    """Depth order, ties broken by index (a stable sort keeps index order among equals)."""
    return torch.sort(depths.detach(), stable=True).indices


def _gef_power(q: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """q^α with q >= 0, and q^α := 0 with zero gradients at q = 0 (the gradient of q^α at 0 is
    infinite for α < 1 and ln(0)·0 for dα)."""
    pos = q > 0
    q_safe = torch.where(pos, q, torch.ones_like(q))
    return torch.where(pos, q_safe ** alpha, torch.zeros_like(q))


def conic_factor(conic: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(½a, b/a, ½(c - b²/a)) of one conic (a, b, c) [3], or of a conic per pixel [P, 3], formed in
    float64 (the products of float32 inputs are exact there) and rounded to the conic's dtype;
    (0, b, ½c) where a = 0. The compiled backends store the same factor (splat_factor in
    splat_math.h). No gradient flows through it."""
    a, b, c = conic.detach().double().unbind(-1)
    if conic.dim() == 1:
        if a == 0:
            return tuple(v.to(conic.dtype) for v in (a, b, 0.5 * c))
        return tuple(v.to(conic.dtype) for v in (0.5 * a, b / a, 0.5 * ((a * c - b * b) / a)))
    zero = a == 0
    a1 = torch.where(zero, torch.ones_like(a), a)   # both branches finite
    return tuple(v.to(conic.dtype) for v in (torch.where(zero, a, 0.5 * a), torch.where(zero, b, b / a1),
                                             0.5 * torch.where(zero, c, (a * c - b * b) / a1)))


def quadratic_form(dx: torch.Tensor, dy: torch.Tensor, conic: torch.Tensor) -> torch.Tensor:
    """q = -p = ½(a·dx² + 2b·dx·dy + c·dy²), unclamped, in the LDLᵀ form ½a·w² + ½s·dy² with
    w = dx + (b/a)·dy: summed as written, the terms of an elongated splat cancel (an absolute error
    up to ~0.1 in float32 at condition number 1e8); here both terms are >= 0 for a positive-definite
    conic. The conic's gradient is the closed form (½dx², dx·dy, ½dy²), attached by a term that is
    exactly zero in value, so autograd never differentiates the division by a. ``conic`` is one
    conic [3] or one per pixel [P, 3] (per-pixel order)."""
    ha, r, hs = conic_factor(conic)
    if conic.dim() == 1 and ha != 0:
        w = dx + r * dy
        q = ha * (w * w) + hs * (dy * dy)
    elif conic.dim() == 1:
        q = r * (dx * dy) + hs * (dy * dy)
    else:
        w = dx + r * dy
        q = torch.where(ha != 0, ha * (w * w), r * (dx * dy)) + hs * (dy * dy)
    if conic.requires_grad:
        dxd, dyd = dx.detach(), dy.detach()
        g = 0.5 * (conic[..., 0] * dxd * dxd + conic[..., 2] * dyd * dyd) + conic[..., 1] * dxd * dyd
        q = q + (g - g.detach())
    return q


def peak_depth(coefs: torch.Tensor, u: torch.Tensor, v: torch.Tensor, fallback: torch.Tensor) -> torch.Tensor:
    """Camera-space depth where each splat's 3D response peaks along the ray d = (u, v, 1):
    t* = b·d / dᵀQd (``smgs.raster.ray_depth``; the twin of peak_depth in splat_math.h, which the
    CPU backend's re-sorting window uses). coefs
    [N, 9], u and v [P], fallback [N] (the centre depths, used where dᵀQd vanishes); returns [P, N]."""
    qxx, qxy, qxz, qyy, qyz, qzz, bx, by, bz = coefs.double().unbind(-1)
    u, v = u.double()[:, None], v.double()[:, None]
    num = bx * u + by * v + bz
    den = qxx * u * u + qyy * v * v + qzz + 2 * (qxy * u * v + qxz * u + qyz * v)
    ok = den > 1e-12 * (u * u + v * v + 1)
    return torch.where(ok, num / torch.where(ok, den, torch.ones_like(den)), fallback.detach().double())


def softmax_step(T, A, C, d_past, p_past, a, p, d, c, beta, gamma, eq15: str):
    """One softmax-competition step of Algorithm 1 (lines 7-27) for a batch of pixels.

    Inputs must be valid (A > 0, a > 0); the caller masks other pixels. Returns the new
    (T, A, C, d_past, p_past). T and A come out as the vanilla product (eqs. 14 and 16).
    """
    T0 = T * (1 - a)                      # line 7, the original transmittance
    U = A + a * T                         # 1 - T0 without cancellation
    x = beta * (p - p_past)               # line 9: w_cur = 1/(1 + exp(β(p_past - p_cur)))
    w_cur = torch.sigmoid(x)
    w_past = torch.sigmoid(-x)            # line 11, not 1 - w_cur
    h_cur = w_cur * a                     # line 10, â_cur
    h_past = w_past * A                   # line 12, â_past
    S = h_past + h_cur
    t_past = h_past * U / S               # eq. (15), ã_past
    # solved: the un-updated â_past; printed (line 14): the updated ã_past
    E = h_cur + (h_past if eq15 == "solved" else t_past) * T0
    # E leaves the float32 normal range only where T0 and w_cur both did (deep behind saturated
    # splats, β·Δp large): ã_past = U ≈ 1 already closes the pixel, and ã_cur := 0 (the limit
    # w_cur -> 0), not 0/0. The same threshold in every backend and dtype (constants.TINY).
    live = E >= K.TINY
    t_cur = torch.where(live, h_cur * U / torch.where(live, E, torch.ones_like(E)), torch.zeros_like(E))
    dd = d - d_past
    # line 15, s = exp(-γ|Δd|), with γ|Δd| := 0 at Δd = 0 (γ may be inf) and := G_MAX where s
    # underflows to 0; γ is zeroed in the unused branch so no inf·0 reaches the gradients.
    flat = (dd == 0) | ((gamma * dd.abs()).detach() > K.DECAY_ARG_MAX)
    g_live = torch.where(flat, torch.zeros_like(dd), gamma) * dd.abs()
    g = torch.where(flat, torch.where(dd == 0, 0.0, K.DECAY_ARG_MAX) * torch.ones_like(dd), g_live)
    s = torch.exp(-g)
    b_past = s * t_past + (1 - s) * A     # line 16
    b_cur = s * t_cur + (1 - s) * a       # line 17
    # line 18, the smaller root of (1 - m·ā_past)(1 - m·ā_cur) = T0, in the cancellation-free form
    D = (b_cur - b_past) ** 2 + 4 * b_cur * b_past * T0
    m = 2 * U / (b_past + b_cur + torch.sqrt(D))
    exact = (s == 0) | ((s == 1) & (eq15 == "solved"))
    m = torch.where(exact, torch.ones_like(m), m)
    a_cur = m * b_cur                     # line 20
    r = m * (s * w_past * U / S + (1 - s))  # ā_past / a_past for line 22
    T_past = T + A * (1 - r)              # lines 19, 21: 1 - m·ā_past, exactly T where r = 1
    wk = (a_cur * T_past / U)             # share of the current splat in the new means (25-26)
    C = C * r[:, None] + c * (a_cur * T_past)[:, None]   # lines 22, 24
    d_past = d_past + (d - d_past) * wk
    p_past = p_past + (p - p_past) * wk
    return T0, U, C, d_past, p_past


def vanilla_step(T, A, C, d_past, p_past, a, p, d, c, track_means: bool):
    """Front-to-back compositing of one splat (3DGS); the running means only where softmax needs
    them later."""
    aT = a * T
    U = A + aT
    C = C + c * aT[:, None]
    if track_means:
        wk = aT / U
        d_past = d_past + (d - d_past) * wk
        p_past = p_past + (p - p_past) * wk
    return T * (1 - a), U, C, d_past, p_past


@dataclass
class _Splat:
    """One compositing step's splat: scalars (global order) or one value per pixel [P] (per-pixel
    order, rows gathered by each pixel's own index). ``col`` [1 or P, C+1] has the depth last."""

    mx: torch.Tensor
    my: torch.Tensor
    conic: torch.Tensor
    o: torch.Tensor
    col: torch.Tensor
    d: torch.Tensor
    al: torch.Tensor | None
    be: torch.Tensor | None
    ga: torch.Tensor | None
    rv: torch.Tensor | None


def _splat(k, means2d, conics, opacities, colors, depths, alpha, beta, gamma, reg_values) -> _Splat:
    """The splat of index ``k``: an int, or a LongTensor [P] of one index per pixel."""
    pick = lambda t: None if t is None else t[k]  # noqa: E731
    col = torch.cat([colors[k], depths[k].unsqueeze(-1)], -1).reshape(-1, colors.shape[1] + 1)
    rv = None if reg_values is None else reg_values[k].reshape(-1, reg_values.shape[1])
    return _Splat(means2d[k, 0], means2d[k, 1], conics[k], opacities[k], col, depths[k], pick(alpha), pick(beta),
                  pick(gamma), rv)


def _pixel_order(means2d, conics, depths, ray_depth, px, py) -> torch.Tensor:
    """[P, L] splat indices per pixel, nearest peak depth first, the splats whose 3σ ellipse misses
    the pixel after all others and cut where no pixel has any left. Peak depths are compared as
    float32 (as a float32 kernel keeps them), and equal ones keep the global order (StopThePop
    re-sorts the globally sorted list): coplanar splats, whose peak depths differ only by rounding,
    are taken in the global order. Formed in chunks of pixels (at most ~2^22 pixel-splat pairs)."""
    n = means2d.shape[0]
    g = _sorted_order(depths)
    with torch.no_grad():
        ha, r, hs = (x.double()[g] for x in conic_factor(conics))                  # [N] each
        mx, my, coefs = means2d[g, 0].double(), means2d[g, 1].double(), ray_depth.coefs[g]
        fallback = depths[g]
        orders, counts = [], []
        step = max(1, (1 << 22) // max(n, 1))
        for lo in range(0, px.shape[0], step):
            cx, cy = px[lo:lo + step], py[lo:lo + step]
            t = peak_depth(coefs, (cx - ray_depth.cx) / ray_depth.fx, (cy - ray_depth.cy) / ray_depth.fy, fallback)
            dx = cx.double()[:, None] - mx
            dy = cy.double()[:, None] - my
            w = dx + r * dy
            q = torch.where(ha != 0, ha * w * w, r * dx * dy) + hs * dy * dy
            # a margin past 3σ: the float32 q of a splat just inside must never be cut
            inside = q <= -K.P_MIN * (1 + 1e-4) + 1e-6
            t = torch.where(inside, t.float(), torch.full_like(t, torch.inf, dtype=torch.float32))
            orders.append(g[torch.sort(t, dim=1, stable=True).indices])
            counts.append(inside.sum(1))
        width = int(torch.cat(counts).max()) if counts else 0
        return torch.cat([o[:, :width] for o in orders])


def _take_leader(lead: torch.Tensor, hit: torch.Tensor, k) -> torch.Tensor:
    """Record splat ``k`` (an int, or one index per pixel) as the first, else the second, leading
    splat of the pixels ``hit``; a pixel with two keeps them."""
    k = torch.as_tensor(k, device=lead.device).expand(lead.shape[0])
    first = hit & (lead[:, 0] < 0)
    second = hit & ~first & (lead[:, 1] < 0)
    return torch.stack([torch.where(first, k, lead[:, 0]), torch.where(second, k, lead[:, 1])], 1)


def rasterize_splats_reference(splats: Splats2D, st: CompositeSettings) -> RenderOutput:
    """Composite projected splats (``smgs.raster.rasterize_splats`` has the arguments). With
    ``splats.ray_depth`` each pixel takes its splats in its own exact order
    (``smgs.raster.ray_depth``), else all in the order of ``depths``. ``st.leaders``: also the
    leading-splat map (the first two composited splats with a >= constants.LEADER_ALPHA per pixel)."""
    means2d, conics, opacities, colors, depths, alpha, beta, gamma = splats.per_splat()
    background, reg_values, ray_depth = splats.background, splats.reg_values, splats.ray_depth
    use_gef, use_softmax, k_max, patch = st.use_gef, st.use_softmax, st.k_max, st.patch
    width, height = st.width, st.height
    device, dtype = means2d.device, means2d.dtype
    n_ch = colors.shape[1]
    P = width * height
    ys, xs = torch.meshgrid(torch.arange(height, device=device, dtype=dtype),
                            torch.arange(width, device=device, dtype=dtype), indexing="ij")
    px = xs.reshape(-1) + K.PIXEL_CENTER
    py = ys.reshape(-1) + K.PIXEL_CENTER

    T = torch.ones(P, device=device, dtype=dtype)
    A = torch.zeros(P, device=device, dtype=dtype)
    C = torch.zeros(P, n_ch + 1, device=device, dtype=dtype)   # colour + depth channel
    d_past = torch.zeros(P, device=device, dtype=dtype)
    p_past = torch.zeros(P, device=device, dtype=dtype)
    done = torch.zeros(P, device=device, dtype=torch.bool)
    count = torch.zeros(P, device=device, dtype=torch.long)
    n_reg = 0 if reg_values is None else reg_values.shape[1]
    reg = torch.zeros(P, 1 + 2 * n_reg, device=device, dtype=dtype) if n_reg else None
    d_front = torch.zeros(P, device=device, dtype=dtype)
    n_head = torch.zeros(P, device=device, dtype=torch.long)      # head steps taken, for d_front
    list_end = torch.zeros(P, device=device, dtype=torch.long) if patch else None
    if patch:   # [tiles, N] list positions, and each pixel's tile
        positions, pixel_tile = list_positions(means2d, conics, opacities, depths, width, height)
    track = use_softmax and k_max > 0
    lead = torch.full((P, 2), -1, device=device, dtype=torch.long) if st.leaders else None
    one = torch.ones((), device=device, dtype=dtype)
    half = 0.5 * one

    inputs = (means2d, conics, opacities, colors, depths, alpha, beta, gamma, reg_values)
    if ray_depth is None:
        steps = ((k, _splat(k, *inputs)) for k in _sorted_order(depths).tolist())
    else:
        order = _pixel_order(means2d, conics, depths, ray_depth, px, py)
        steps = ((order[:, j], _splat(order[:, j], *inputs)) for j in range(order.shape[1]))
    for k, sp in steps:
        pos = (positions[pixel_tile, k] if torch.is_tensor(k) else positions[:, k][pixel_tile]) if patch else None
        dx = px - sp.mx
        dy = py - sp.my
        q = torch.clamp(quadratic_form(dx, dy, sp.conic), min=0.0)  # -p >= 0
        e = _gef_power(q, sp.al) if use_gef else q
        kern = torch.exp(-torch.clamp(e, max=-K.EXP_ARG_MIN))
        a = torch.clamp(sp.o * kern, max=K.ALPHA_MAX)
        reach = (~done) & (q <= -K.P_MIN) & (a >= K.ALPHA_MIN)
        if not bool(reach.any()):
            continue
        stop = reach & (T * (1 - a) < st.t_min * (1 - K.T_STOP_SLACK))
        head_k = (pos < k_max) if patch else (count < k_max)   # the step's place in the softmax head
        if use_softmax:   # the stop holds for vanilla steps only: in the head a later splat can win
            stop = stop & ~head_k
        done = done | stop
        reach = reach & ~stop
        p = -q
        in_head = reach & head_k
        soft = in_head & (A > 0) if use_softmax else torch.zeros_like(reach)
        van = reach & ~soft

        new_state = [T, A, C, d_past, p_past]
        if bool(van.any()):
            # a = ½ where the step does not apply keeps U = A + a·T > 0 (no NaN gradients).
            vs = vanilla_step(T, A, C, d_past, p_past, torch.where(van, a, half), p, sp.d, sp.col, track)
            new_state = [torch.where(m[:, None] if v.dim() == 2 else m, v, o)
                         for v, o, m in zip(vs, new_state, (van, van, van, van & in_head, van & in_head))]
        if bool(soft.any()):
            # Benign values where the step does not apply, so no branch produces NaN gradients.
            A_s = torch.where(soft, A, half)
            a_s = torch.where(soft, a, half)
            T_s = torch.where(soft, T, half)
            ss = softmax_step(T_s, A_s, C, d_past, p_past, a_s, p, sp.d, sp.col, sp.be, sp.ga, st.eq15)
            new_state = [torch.where(soft[:, None] if v.dim() == 2 else soft, v, o)
                         for v, o in zip(ss, new_state)]
        T, A, C, d_past, p_past = new_state
        if lead is not None:
            lead = _take_leader(lead, reach & (a.detach() >= K.LEADER_ALPHA), k)

        if reg is not None:
            first = in_head & (n_head == 0)
            d_front = torch.where(first, sp.d.detach().expand(P), d_front)
            w = 1.0 / (1.0 + (sp.d.detach() - d_front) / st.reg_depth_scale)
            w = torch.where(in_head, w, torch.zeros_like(w))
            reg = reg + torch.cat([w[:, None], w[:, None] * sp.rv, w[:, None] * sp.rv * sp.rv], dim=1)
        count = count + reach.long()
        n_head = n_head + in_head.long()
        if list_end is not None:
            list_end = torch.where(reach, torch.maximum(list_end, pos + 1), list_end)

    stats = RenderStats(n_contrib=count.reshape(height, width), pairs_evaluated=P * means2d.shape[0],
                        k_max=k_max if use_softmax else 2**31 - 1, scope=st.scope,
                        list_end=None if list_end is None else list_end.reshape(height, width))
    used = (means2d, conics, opacities, colors, depths) + ((alpha,) if use_gef else ()) \
        + ((beta, gamma) if use_softmax else ()) + (reg_values,)
    tie = _tie(used)
    if tie is not None:
        C, A = C + tie, A + tie
        reg = None if reg is None else reg + tie
    return _output(T, A, C, background, stats, reg, lead, width, height)


def _tie(tensors) -> torch.Tensor | None:
    """An exact 0 that depends on every input needing a gradient (the sum of an empty slice of
    each), added to the outputs: a view where no splat reaches a pixel (none in view, all behind
    the camera) then back-propagates zero gradients, as the compiled backends do, instead of an
    output outside the graph whose ``backward()`` raises. None when no input needs a gradient."""
    parts = [t.reshape(-1)[:0].sum() for t in tensors if t is not None and t.requires_grad]
    return sum(parts[1:], parts[0]) if parts else None


def _output(T, A, C, background, stats: RenderStats, reg, lead, width: int, height: int) -> RenderOutput:
    """The image from the final state: colour (+ T·background), alpha, expected depth normalised by
    alpha (0 where alpha is 0), and the optional sums and leading-splat map, as [H, W, ...]."""
    n_ch = C.shape[1] - 1
    rgb = C[:, :n_ch]
    if background is not None:   # a host background with device splats (the compiled backends take it so)
        rgb = rgb + T[:, None] * background.to(device=C.device, dtype=C.dtype)[None, :]
    pos = A > 0
    depth = torch.where(pos, C[:, n_ch] / torch.where(pos, A, torch.ones_like(A)), torch.zeros_like(A))
    shape = (height, width)
    return RenderOutput(rgb=rgb.reshape(*shape, n_ch), alpha=A.reshape(shape), depth=depth.reshape(shape),
                        stats=stats, reg=None if reg is None else reg.reshape(*shape, -1),
                        leaders=None if lead is None else lead.reshape(*shape, 2))
