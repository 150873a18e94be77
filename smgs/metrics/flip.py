"""ꟻLIP (LDR) through NVIDIA's ``flip-evaluator`` package, as a raw per-pixel error map so callers
can average it under a mask (the package has no mask argument).

The package calls ``sys.exit(1)`` on bad arguments instead of raising, so every input is validated
here first and a stray ``SystemExit`` is turned into an exception.
"""

from __future__ import annotations

import numpy as np
import torch

from smgs.metrics.result import Missing

FLIP_PPD = 67.0
"""Pixels per degree: the package default and PoppingDetection's 0.7 m wide 4K monitor at 0.7 m
((0.7·3840/0.7)·π/180 = 67.02; the package and the issue use 67)."""

FLIP_NAME = "flip_ldr_ppd67"


def flip_available() -> bool | Missing:
    try:
        import flip_evaluator  # noqa: F401
    except ImportError as e:  # the wheel is a project dependency; say so if it is absent
        return Missing(f"flip-evaluator is not installed ({e})")
    return True


def _as_hwc_float32(img: torch.Tensor | np.ndarray, name: str) -> np.ndarray:
    a = img.detach().cpu().numpy() if isinstance(img, torch.Tensor) else np.asarray(img)
    if a.ndim != 3 or a.shape[2] != 3:
        raise ValueError(f"FLIP {name} must be [H, W, 3], got {a.shape}")
    if a.shape[0] < 1 or a.shape[1] < 1:
        raise ValueError(f"FLIP {name} is empty: {a.shape}")
    a = np.ascontiguousarray(a, dtype=np.float32)
    if not np.isfinite(a).all():
        raise ValueError(f"FLIP {name} has non-finite values")
    if a.min() < 0.0 or a.max() > 1.0:
        raise ValueError(f"FLIP LDR {name} must lie in [0, 1] (sRGB), got [{a.min()}, {a.max()}]")
    return a


def flip_error_map(reference: torch.Tensor | np.ndarray, test: torch.Tensor | np.ndarray,
                   ppd: float = FLIP_PPD) -> np.ndarray:
    """Per-pixel LDR ꟻLIP error [H, W] in [0, 1] of ``test`` against ``reference`` (both sRGB
    [H, W, 3] in [0, 1]). Raises ValueError for invalid input, ImportError without the package."""
    import flip_evaluator

    ref = _as_hwc_float32(reference, "reference")
    tst = _as_hwc_float32(test, "test")
    if ref.shape != tst.shape:
        raise ValueError(f"FLIP images differ in shape: {ref.shape} vs {tst.shape}")
    if not (np.isfinite(ppd) and ppd > 0):
        raise ValueError(f"FLIP ppd must be a positive number, got {ppd}")
    try:
        err, _, _ = flip_evaluator.evaluate(ref, tst, "LDR", inputsRGB=True, applyMagma=False,
                                            computeMeanError=False, parameters={"ppd": float(ppd)})
    except SystemExit as e:  # the package exits the interpreter on errors it detects
        raise ValueError(f"flip_evaluator rejected its arguments (exit code {e.code})") from None
    err = np.asarray(err, dtype=np.float32)
    return err.reshape(err.shape[0], err.shape[1])


def flip_mean(reference, test, mask: np.ndarray | None = None, ppd: float = FLIP_PPD) -> float:
    """Mean ꟻLIP over the pixels where ``mask`` is true (all pixels without a mask)."""
    err = flip_error_map(reference, test, ppd)
    if mask is None:
        return float(err.mean())
    mask = np.asarray(mask, dtype=bool)
    n = int(mask.sum())
    if n == 0:
        raise ValueError("FLIP mask selects no pixel")
    return float(err[mask].mean())
