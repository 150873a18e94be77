"""The per-pixel training loss terms, fused on CPU: the photometric loss (1 − λ)·L1 + λ·(1 − SSIM)
and the β/γ ray-variance regulariser.

``PhotometricLoss`` computes the loss and, in the same call, its gradient with respect to the
render: on float32 CPU tensors in one compiled pass (``csrc/image_loss.cpp``, built just in time
like the CPU renderer), elsewhere with the PyTorch path of ``smgs.train.loss`` (L1 and the fast
SSIM). Both follow ``smgs.metrics.ssim`` (window and constants are passed from there), and
tests/test_train_image_loss.py checks the compiled pass against the metric in value and gradient.
It also returns the MSE, so the training PSNR costs no extra pass. ``ray_variance`` is
``smgs.train.loss.ray_variance`` in one compiled pass each way on float32 CPU sums (the same
fallback rule).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn.functional as F
from torch.autograd.function import once_differentiable

from smgs.metrics.ssim import C1, C2, gaussian_kernel_1d
from smgs.raster.cpu_build import cpu_extension, use_cpu_kernel
from smgs.raster.kernel_clock import kernel
from smgs.train.loss import SSIMLoss
from smgs.train.loss import ray_variance as ray_variance_torch

log = logging.getLogger(__name__)

_CSRC = Path(__file__).parent / "csrc"


_JIT = cpu_extension("smgs_image_loss_cpu", [_CSRC / "image_loss.cpp"], "training-loss kernel")


def fused_available() -> bool:
    """Whether the compiled CPU loss can be used here (builds it on first call; a failed build raises ``BuildError``)."""
    return _JIT.is_available()


@dataclass
class LossParts:
    """The loss (a differentiable scalar tensor) and its parts for logs: L1, SSIM and MSE as one
    detached tensor [3] on the render's device (float64 from the compiled pass), so that the
    trainer reads them with the step's other values in its one host wait; ``l1``, ``ssim`` and
    ``mse`` read them one by one."""

    total: torch.Tensor
    values: torch.Tensor

    @property
    def l1(self) -> float:
        return float(self.values[0])

    @property
    def ssim(self) -> float:
        return float(self.values[1])

    @property
    def mse(self) -> float:
        return float(self.values[2])


class _PhotometricCPU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, y, window, lam):  # type: ignore[override]
        with kernel("loss"):
            stats, grad = _JIT.module().forward(x, y, window, lam, C1, C2, ctx.needs_input_grad[0])
        ctx.save_for_backward(grad)
        ctx.mark_non_differentiable(stats)
        return stats[0].to(x.dtype), stats

    @staticmethod
    @once_differentiable
    def backward(ctx, g, _g_stats):  # type: ignore[override]
        (grad,) = ctx.saved_tensors
        # the loss itself (g = 1, the trainer's case: a CPU scalar, read without a wait) takes the
        # gradient as computed, no [H, W, C] product
        return (grad if float(g) == 1.0 else grad * g), None, None, None


class _RayVarianceCPU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, reg, r: int):  # type: ignore[override]
        ctx.save_for_backward(reg)
        ctx.r = r
        with kernel("loss"):
            return _JIT.module().ray_variance(reg, r, reg.new_empty(0))[0]

    @staticmethod
    @once_differentiable
    def backward(ctx, g):  # type: ignore[override]
        (reg,) = ctx.saved_tensors
        with kernel("loss"):
            return _JIT.module().ray_variance(reg, ctx.r, g.detach().contiguous())[0], None


def ray_variance(reg: torch.Tensor, fused: bool | None = None) -> torch.Tensor:
    """``smgs.train.loss.ray_variance`` (per-ray weighted variances [R] from the renderer's reg
    sums [H, W, 1 + 2R]), compiled on float32 CPU tensors where the extension is available
    (``fused`` as in ``PhotometricLoss``)."""
    if use_cpu_kernel(_JIT, fused, (reg,), "sums"):
        return _RayVarianceCPU.apply(reg, (reg.shape[-1] - 1) // 2)
    return ray_variance_torch(reg)


class PhotometricLoss:
    """(1 − λ)·L1(x, y) + λ·(1 − SSIM(x, y)) of a render x [H, W, C] against a fixed target y.

    ``fused``: None uses the compiled CPU pass wherever it applies (float32 CPU tensors, the
    extension available), True requires it, False always uses the PyTorch path."""

    def __init__(self, lambda_dssim: float = 0.2, fused: bool | None = None) -> None:
        self.lam = float(lambda_dssim)
        self.fused = fused
        self._ssim = SSIMLoss()
        self._window: torch.Tensor | None = None    # the compiled pass's window (on the CPU, made there)

    def __call__(self, x: torch.Tensor, y: torch.Tensor) -> LossParts:
        if x.shape != y.shape or x.dim() != 3:
            raise ValueError(f"render and target must be [H, W, C] of one shape, got {tuple(x.shape)} "
                             f"and {tuple(y.shape)}")
        if use_cpu_kernel(_JIT, self.fused, (x,), "images"):
            if self._window is None:
                self._window = gaussian_kernel_1d(device=x.device).to(torch.float32)
            total, stats = _PhotometricCPU.apply(x, y.detach().to(x.dtype), self._window, self.lam)
            return LossParts(total, stats[1:])
        l1v = F.l1_loss(x, y)
        ssim_v = self._ssim(x, y)
        total = (1 - self.lam) * l1v + self.lam * (1 - ssim_v)
        mse = F.mse_loss(x.detach(), y)
        return LossParts(total, torch.stack([l1v.detach(), ssim_v.detach(), mse]))
