"""Training loss: (1 − λ)·L1 + λ·(1 − SSIM) and the per-ray variance regulariser of β and γ.

SSIM here is the 3DGS SSIM of ``smgs.metrics.ssim`` (11×11 Gaussian window, σ 1.5, zero
padding, mean of the map) computed faster for training: the separable window is applied as two
banded matrix products (the 11×11 depthwise conv2d costs ~5-10 ms forward+backward at 128² on one
core, more than everything else in a 4-Gaussian step), the backward is analytic (the blur's
adjoint is the transposed band products), and the target's statistics are computed once per
image. Tests check it against ``smgs.metrics.ssim`` in value and gradient.
"""

from __future__ import annotations

import math

import torch

from smgs.metrics.ssim import C1, C2, SIGMA, WINDOW


def _band(n: int, dtype: torch.dtype, device) -> torch.Tensor:
    """[n, n] matrix M with (M @ x)[i] = Σ_k g[k]·x[i + k − r] (zero padding): the 1D window."""
    r = WINDOW // 2
    x = torch.arange(WINDOW, dtype=torch.float64) - r
    g = torch.exp(-x * x / (2 * SIGMA * SIGMA))
    g = g / g.sum()
    i = torch.arange(n)
    off = i[None, :] - i[:, None] + r                     # j − i + r
    ok = (off >= 0) & (off < WINDOW)
    return torch.where(ok, g[off.clamp(0, WINDOW - 1)], torch.zeros(())).to(dtype=dtype, device=device)


def _blur(s: torch.Tensor, bv: torch.Tensor, bh: torch.Tensor) -> torch.Tensor:
    """Separable window over the rows and columns of every channel of s [K, H, W]: Bv·s_k·Bhᵀ."""
    k, h, w = s.shape
    return bv @ (s.reshape(k * h, w) @ bh.T).reshape(k, h, w)


class _SSIM(torch.autograd.Function):
    """Mean SSIM of x [C, H, W] against a fixed target, with an analytic backward: the map is
    A1·A2/(B1·B2) with A1 = 2μxμy + C1, A2 = 2σxy + C2, B1 = μx² + μy² + C1, B2 = σx² + σy² + C2;
    its derivatives w.r.t. the blurred statistics (μx, E[x²], E[xy]) go back through the adjoint
    blur (the transposed band matrices) to x. Far fewer kernel launches than autograd's graph."""

    @staticmethod
    def forward(ctx, x, y, mu2, s2, bv, bh):  # type: ignore[override]
        c = x.shape[0]
        st = _blur(torch.cat([x, x * x, x * y], 0), bv, bh)
        mu1, e11, e12 = st[:c], st[c:2 * c], st[2 * c:]
        mu12 = mu1 * mu2
        mu1_sq = mu1 * mu1
        a1 = 2 * mu12 + C1
        a2 = 2 * (e12 - mu12) + C2
        b1 = mu1_sq + mu2 * mu2 + C1
        b2 = (e11 - mu1_sq) + s2 + C2
        den = b1 * b2
        m = a1 * a2 / den
        ctx.save_for_backward(x, y, mu1, mu2, a1, a2, b1, b2, den, m, bv, bh)
        return m.mean()

    @staticmethod
    def backward(ctx, g):  # type: ignore[override]
        x, y, mu1, mu2, a1, a2, b1, b2, den, m, bv, bh = ctx.saved_tensors
        g = g / m.numel()
        d_a1 = g * a2 / den
        d_a2 = g * a1 / den
        d_b1 = -g * m / b1
        d_b2 = -g * m / b2
        # μx enters a1 and b1 directly, and a2 = 2(E[xy] − μxμy) + C2, b2 = E[x²] − μx² + ...
        d_mu1 = 2 * ((d_a1 - d_a2) * mu2 + (d_b1 - d_b2) * mu1)
        d = _blur(torch.cat([d_mu1, d_b2, 2 * d_a2], 0), bv.T, bh.T)
        c = x.shape[0]
        dx = d[:c] + 2 * x * d[c:2 * c] + y * d[2 * c:]
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


def ray_variance(reg: torch.Tensor) -> torch.Tensor:
    """Per-ray weighted variances from the renderer's ``reg`` sums [H, W, 1 + 2R]
    (Σw, Σw·v_r, Σw·v_r²): Var_r = Σw v²/Σw − (Σw v/Σw)² per pixel, averaged over the pixels
    with Σw > 0. Returns [R] (zeros if no pixel is covered)."""
    r = (reg.shape[-1] - 1) // 2
    flat = reg.reshape(-1, reg.shape[-1])
    sw = flat[:, 0]
    hit = sw > 0
    if not bool(hit.any()):
        return flat.new_zeros(r)
    f = flat[hit]
    sw = f[:, :1]
    mean = f[:, 1:1 + r] / sw
    var = f[:, 1 + r:] / sw - mean * mean
    return var.clamp_min(0.0).mean(0)


def l1(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    return (x - y).abs().mean()


def psnr(x: torch.Tensor, y: torch.Tensor) -> float:
    """PSNR in dB of images in [0, 1] (x clamped to [0, 1] first); inf when equal."""
    mse = float(((x.detach().clamp(0, 1) - y) ** 2).mean())
    return math.inf if mse == 0 else -10.0 * math.log10(mse)
