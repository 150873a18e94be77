"""Training loss: (1 − λ)·L1 + λ·(1 − SSIM) and the per-ray variance regulariser of β and γ.

SSIM here is the 3DGS SSIM of ``smgs.metrics.ssim`` (11×11 Gaussian window, σ 1.5, zero
padding, mean of the map) computed faster for training: the separable window is applied as two
banded matrix products (the 11×11 depthwise conv2d costs ~5 ms forward+backward at 128² on one
core, more than everything else in a 4-Gaussian step), the blur's backward is the same banded
products transposed, and the target's statistics are computed once per image. Tests check it
against ``smgs.metrics.ssim`` in value and gradient.
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


class _Blur(torch.autograd.Function):
    """x [C,H,W] ↦ Bv·x·Bhᵀ; its adjoint is Bvᵀ·g·Bh (linear, so no inputs are saved)."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, bv: torch.Tensor, bh: torch.Tensor) -> torch.Tensor:  # type: ignore[override]
        ctx.save_for_backward(bv, bh)
        return bv @ x @ bh.T

    @staticmethod
    def backward(ctx, g: torch.Tensor):  # type: ignore[override]
        bv, bh = ctx.saved_tensors
        return bv.T @ g @ bh, None, None


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
        yc = y.detach().permute(2, 0, 1).contiguous()
        mu2 = bv @ yc @ bh.T
        s2 = bv @ (yc * yc) @ bh.T - mu2 * mu2
        if len(self._targets) >= self.max_cached:
            self._targets.clear()
        self._targets[key] = (y, yc, mu2, s2)
        return yc, mu2, s2

    def __call__(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """Mean SSIM of images [H, W, C] (x differentiable, y a fixed target)."""
        h, w, c = x.shape
        bv, bh = self._bands_for(h, w, x.dtype, x.device)
        yc, mu2, s2 = self._target_stats(y, bv, bh)
        xc = x.permute(2, 0, 1)
        st = _Blur.apply(torch.cat([xc, xc * xc, xc * yc], 0), bv, bh)
        mu1, e11, e12 = st[:c], st[c:2 * c], st[2 * c:]
        mu1_sq = mu1 * mu1
        mu12 = mu1 * mu2
        s1 = e11 - mu1_sq
        s12 = e12 - mu12
        m = ((2 * mu12 + C1) * (2 * s12 + C2)) / ((mu1_sq + mu2 * mu2 + C1) * (s1 + s2 + C2))
        return m.mean()


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
