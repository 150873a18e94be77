"""SSIM as 3DGS computes it (``utils/loss_utils.py``): 11×11 Gaussian window, σ = 1.5,
C1 = 0.01², C2 = 0.03², zero padding, mean of the map. Differentiable (the training loss uses it)."""

from __future__ import annotations

import torch
import torch.nn.functional as F

WINDOW = 11
SIGMA = 1.5
C1 = 0.01**2
C2 = 0.03**2


def gaussian_kernel_1d(size: int = WINDOW, sigma: float = SIGMA, device=None) -> torch.Tensor:
    """The normalised 1D Gaussian [size] (float64, on ``device``) whose outer product is the window."""
    x = torch.arange(size, dtype=torch.float64, device=device) - size // 2
    g = torch.exp(-x * x / (2 * sigma * sigma))
    return g / g.sum()


def gaussian_window(size: int = WINDOW, sigma: float = SIGMA, dtype=torch.float32, device=None) -> torch.Tensor:
    g = gaussian_kernel_1d(size, sigma, device)
    return (g[:, None] * g[None, :]).to(dtype=dtype, device=device)


def ssim_from_stats(mu1: torch.Tensor, mu2: torch.Tensor, s1: torch.Tensor, s2: torch.Tensor,
                    s12: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """(A1, A2, B1, B2) of the SSIM map A1·A2 / (B1·B2) from the local means, variances and
    covariance: A1 = 2μ1μ2 + C1, A2 = 2σ12 + C2, B1 = μ1² + μ2² + C1, B2 = σ1² + σ2² + C2."""
    return 2 * (mu1 * mu2) + C1, 2 * s12 + C2, mu1 * mu1 + mu2 * mu2 + C1, s1 + s2 + C2


def ssim_map(img1: torch.Tensor, img2: torch.Tensor) -> torch.Tensor:
    """SSIM map of two images [H, W, C] (or [B, C, H, W]) in [0, 1]."""
    hwc = img1.dim() == 3
    if hwc:
        img1, img2 = img1.permute(2, 0, 1)[None], img2.permute(2, 0, 1)[None]
    ch = img1.shape[1]
    w = gaussian_window(dtype=img1.dtype, device=img1.device).expand(ch, 1, WINDOW, WINDOW)
    conv = lambda x: F.conv2d(x, w, padding=WINDOW // 2, groups=ch)  # noqa: E731
    mu1, mu2 = conv(img1), conv(img2)
    s1 = conv(img1 * img1) - mu1 * mu1
    s2 = conv(img2 * img2) - mu2 * mu2
    s12 = conv(img1 * img2) - mu1 * mu2
    a1, a2, b1, b2 = ssim_from_stats(mu1, mu2, s1, s2, s12)
    m = (a1 * a2) / (b1 * b2)
    return m[0].permute(1, 2, 0) if hwc else m


def ssim(img1: torch.Tensor, img2: torch.Tensor) -> torch.Tensor:
    """Mean SSIM (a scalar tensor, differentiable)."""
    return ssim_map(img1, img2).mean()
