"""Training loss: (1 − λ)·L1 + λ·(1 − SSIM) and the per-ray variance regulariser of β and γ.

SSIM here is the 3DGS SSIM of ``smgs.metrics.ssim`` (same window, constants and formula, imported
from there) computed faster for training: the separable window is applied as two banded matrix
products (the 11×11 depthwise conv2d costs ~5-10 ms forward+backward at 128² on one core; the band
products ~0.5 ms per blur of 9 channels), the backward is analytic (the window is symmetric, so
the blur is its own adjoint), and the target's statistics are computed once per image. Tests
check it against ``smgs.metrics.ssim`` in value and gradient. On float32 CPU tensors the trainer
uses the compiled pass of ``smgs.train.image_loss`` instead (same definition, one pass, ~3.5×
faster at 128²); this module is its fallback on other devices and dtypes.
"""

from __future__ import annotations


import torch
import torch.nn.functional as F

from smgs.metrics.ssim import WINDOW, gaussian_kernel_1d, ssim_from_stats


def _band(n: int, dtype: torch.dtype, device) -> torch.Tensor:
    """[n, n] matrix M with (M @ x)[i] = Σ_k g[k]·x[i + k − r] (zero padding): the 1D window.
    Symmetric, since the window is."""
    r = WINDOW // 2
    g = gaussian_kernel_1d(device=device)
    i = torch.arange(n, device=device)
    off = i[None, :] - i[:, None] + r                     # j − i + r
    ok = (off >= 0) & (off < WINDOW)
    return (g[off.clamp(0, WINDOW - 1)] * ok).to(dtype)


def _blur(s: torch.Tensor, bv: torch.Tensor, bh: torch.Tensor) -> torch.Tensor:
    """Separable window over the rows and columns of every channel of s [K, H, W]: Bv·s_k·Bhᵀ."""
    k, h, w = s.shape
    return bv @ (s.reshape(k * h, w) @ bh.T).reshape(k, h, w)


class _SSIM(torch.autograd.Function):
    """Mean SSIM of x [C, H, W] against a fixed target, with an analytic backward: the map is
    A1·A2/(B1·B2) (``ssim_from_stats``); its derivatives w.r.t. the blurred statistics (μx, E[x²],
    E[xy]) go back through the blur (its own adjoint: symmetric bands) to x. Far fewer tensor ops
    than autograd's graph."""

    @staticmethod
    def forward(ctx, x, y, mu2, s2, bv, bh):  # type: ignore[override]
        c = x.shape[0]
        st = _blur(torch.cat([x, x * x, x * y], 0), bv, bh)
        mu1, e11, e12 = st[:c], st[c:2 * c], st[2 * c:]
        a1, a2, b1, b2 = ssim_from_stats(mu1, mu2, e11 - mu1 * mu1, s2, e12 - mu1 * mu2)
        den = b1 * b2
        m = a1 * a2 / den
        ctx.save_for_backward(x, y, mu1, mu2, a1, a2, b1, b2, den, m, bv, bh)
        return m.mean()

    @staticmethod
    def backward(ctx, g):  # type: ignore[override]
        x, y, mu1, mu2, a1, a2, b1, b2, den, m, bv, bh = ctx.saved_tensors
        c = x.shape[0]
        gs = g / m.numel()
        q = gs / den
        d_a1 = a2 * q
        d_a2 = a1 * q
        gm = m * gs
        d_b1 = gm / b1
        d_b2 = gm / b2                    # dL/dB = −d_b
        # μx enters A1 = 2μxμy + C1 and B1 = μx² + ...; and A2 = 2(E[xy] − μxμy) + C2,
        # B2 = E[x²] − μx² + ...: dL/dE[x²] = −d_b2, dL/dE[xy] = 2·d_a2
        d = torch.empty((3 * c,) + x.shape[1:], dtype=x.dtype, device=x.device)
        torch.mul(((d_a1 - d_a2) * mu2).sub_((d_b1 - d_b2).mul_(mu1)), 2, out=d[:c])
        torch.neg(d_b2, out=d[c:2 * c])
        torch.mul(d_a2, 2, out=d[2 * c:])
        d = _blur(d, bv, bh)
        dx = torch.addcmul(d[:c], x, d[c:2 * c], value=2).addcmul_(y, d[2 * c:])
        return dx, None, None, None, None, None


class SSIMLoss:
    """SSIM(render, target) with the target's blurred statistics cached per target tensor
    (keyed by ``id``; pass the same target tensor each time a view repeats)."""

    def __init__(self, max_cached: int = 512) -> None:
        self._bands: dict[tuple, tuple[torch.Tensor, torch.Tensor]] = {}
        self._targets: dict[int, tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]] = {}
        self.max_cached = max_cached

    def _bands_for(self, h: int, w: int, dtype, device) -> tuple[torch.Tensor, torch.Tensor]:
        key = (h, w, dtype, str(device))
        if key not in self._bands:
            self._bands[key] = (_band(h, dtype, device), _band(w, dtype, device))
        return self._bands[key]

    def _target_stats(self, y: torch.Tensor, bv: torch.Tensor, bh: torch.Tensor):
        key = id(y)
        hit = self._targets.get(key)
        if hit is not None and hit[0] is y:
            return hit[1:]
        yd = y.detach().permute(2, 0, 1).contiguous()
        c = yd.shape[0]
        st = _blur(torch.cat([yd, yd * yd], 0), bv, bh)
        mu2 = st[:c]
        s2 = st[c:] - mu2 * mu2
        if len(self._targets) >= self.max_cached:
            self._targets.clear()
        self._targets[key] = (y, yd, mu2, s2)
        return yd, mu2, s2

    def __call__(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """Mean SSIM of images [H, W, C] (x differentiable, y a fixed target)."""
        h, w, _ = x.shape
        bv, bh = self._bands_for(h, w, x.dtype, x.device)
        yd, mu2, s2 = self._target_stats(y, bv, bh)
        return _SSIM.apply(x.permute(2, 0, 1), yd, mu2, s2, bv, bh)


class _RayVariance(torch.autograd.Function):
    """Var_r = mean over covered pixels of max(S2/S0 − (S1/S0)², 0), on the channel-major copy of
    the sums (contiguous rows: the [H·W, 5] layout makes every op a slow size-2 broadcast), with
    the analytic backward: ∂/∂S2 = 1/S0, ∂/∂S1 = −2·μ/S0, ∂/∂S0 = −(Var − μ²)/S0 (μ = S1/S0),
    passed where Var ≥ 0 (torch.clamp's mask)."""

    @staticmethod
    def forward(ctx, reg, r: int):  # type: ignore[override]
        s = reg.reshape(-1, 1 + 2 * r).T.contiguous()          # [1 + 2R, P]
        hit = s[0] > 0
        inv = torch.where(hit, s[0], s.new_ones(())).reciprocal_().mul_(hit)
        mean = s[1:1 + r] * inv
        var = s[1 + r:] * inv - mean * mean
        keep = var >= 0
        n = hit.sum().clamp_min(1)
        ctx.save_for_backward(inv, mean, var, keep, n)
        ctx.shape = reg.shape
        return (var * keep).sum(1) / n

    @staticmethod
    def backward(ctx, g):  # type: ignore[override]
        inv, mean, var, keep, n = ctx.saved_tensors
        gv = (g / n)[:, None] * keep * inv                      # dL/dS2 [R, P] (0 where uncovered)
        d = torch.cat([-(gv * (var - mean * mean)).sum(0, keepdim=True), -2 * gv * mean, gv], 0)
        return d.T.reshape(ctx.shape), None


def ray_variance(reg: torch.Tensor) -> torch.Tensor:
    """Per-ray weighted variances from the renderer's ``reg`` sums [H, W, 1 + 2R]
    (Σw, Σw·v_r, Σw·v_r²): Var_r = Σw v²/Σw − (Σw v/Σw)² per pixel (clamped at 0), averaged over
    the pixels with Σw > 0. Returns [R] (zeros if no pixel is covered)."""
    return _RayVariance.apply(reg, (reg.shape[-1] - 1) // 2)


def l1(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    return F.l1_loss(x, y)
