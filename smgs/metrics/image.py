"""Image metrics computed once, in one place, the way the 3DGS evaluation computes them.

3DGS saves renders as PNG (``torchvision.utils.save_image``: ×255, +0.5, clamp, truncate to uint8)
and reads them back with PIL before ``metrics.py`` runs, so every metric here sees 8-bit
quantised predictions and ground truths. PSNR is per image, then the mean over images; SSIM is
``smgs.metrics.ssim`` (11×11 Gaussian window, σ 1.5, zero padding, mean of the map); LPIPS is the
VGG network of ``smgs.metrics.lpips`` and is ``Missing`` without local weights; FLIP is LDR at
67 ppd. Per-image values are kept; means derive from them.
"""

from __future__ import annotations

import io
import math
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
import torch

from smgs.metrics import lpips as lpips_mod
from smgs.metrics.lpips_weights import ensure_weights
from smgs.metrics.flip import FLIP_NAME, flip_available, flip_error_map
from smgs.metrics.result import Missing, json_value
from smgs.metrics.ssim import ssim as ssim_3dgs


def to_uint8(img: torch.Tensor) -> torch.Tensor:
    """[H, W, C] float in [0, 1] -> uint8, exactly as ``torchvision.utils.save_image`` rounds."""
    return img.detach().float().mul(255).add(0.5).clamp(0, 255).to(torch.uint8)


def quantize_8bit(img: torch.Tensor) -> torch.Tensor:
    """The float image a PNG round trip (save, read back, /255) gives, without touching disk."""
    return to_uint8(img).float().div(255.0).to(img.device)


ERROR_MAP_VMAX = 0.25
"""|error| (mean over RGB, images in [0, 1]) at which an error map saturates: one fixed scale, so maps of
different methods at the same view compare by colour."""


def abs_error_map(pred: torch.Tensor, gt: torch.Tensor, vmax: float = ERROR_MAP_VMAX) -> np.ndarray:
    """|pred − gt| of two [H, W, 3] images in [0, 1] (8-bit quantised first, as the metrics see them),
    mean over RGB, as a uint8 [H, W, 3] heat map: black (0) → red → yellow → white (≥ vmax)."""
    if pred.shape != gt.shape:
        raise ValueError(f"error map of images of different shapes: {tuple(pred.shape)} vs {tuple(gt.shape)}")
    err = (quantize_8bit(pred.float()) - quantize_8bit(gt.float())).abs().mean(-1).cpu().numpy()
    return (heat_colors(err, vmax) * 255 + 0.5).astype(np.uint8)


def heat_colors(err: np.ndarray, vmax: float = ERROR_MAP_VMAX) -> np.ndarray:
    """An error map [H, W] as float RGB [H, W, 3] in [0, 1]: black (0) → red → yellow → white (≥ vmax),
    the one scale of every error map the harness draws."""
    t = np.clip(err / vmax, 0.0, 1.0) * 3.0  # three ramps: red, then green, then blue
    return np.stack([np.clip(t, 0, 1), np.clip(t - 1, 0, 1), np.clip(t - 2, 0, 1)], axis=-1)


def png_roundtrip(img: torch.Tensor) -> torch.Tensor:
    """Encode as PNG with PIL and decode again (slow; tests check quantize_8bit against it)."""
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(to_uint8(img).cpu().numpy()).save(buf, format="PNG")
    buf.seek(0)
    return torch.from_numpy(np.asarray(Image.open(buf)).copy()).float().div(255.0)


def psnr(pred: torch.Tensor, gt: torch.Tensor) -> float:
    """PSNR in dB for images in [0, 1] (3DGS ``utils/image_utils.psnr``); inf for equal images."""
    return psnr_from_mse(float(((pred.double() - gt.double()) ** 2).mean()))


def psnr_from_mse(mse: float) -> float:
    """PSNR in dB of a mean squared error of images in [0, 1]; inf for 0."""
    return math.inf if mse == 0.0 else -10.0 * math.log10(mse)


def ssim(pred: torch.Tensor, gt: torch.Tensor) -> float:
    """SSIM as 3DGS computes it (see ``smgs.metrics.ssim``), as a float."""
    with torch.no_grad():
        return float(ssim_3dgs(pred.float(), gt.float()))


@dataclass
class ImageMetrics:
    """Per-image metrics of one set of predictions against ground truth (8-bit quantised).

    ``lpips`` and ``flip`` hold a list of per-image values or ``Missing(reason)``; ``lpips_name``
    names the network, the weights and the input convention that produced the values.
    """

    names: list[str]
    psnr: list[float]
    ssim: list[float]
    lpips: list[float] | Missing
    lpips_name: str
    flip: list[float] | Missing
    flip_name: str = FLIP_NAME
    quantized: bool = True
    extra: dict = field(default_factory=dict)

    @staticmethod
    def _mean(values: list[float] | Missing) -> float | Missing:
        if isinstance(values, Missing):
            return values
        return float(np.mean(values)) if values else Missing("no images")

    def means(self) -> dict[str, float | Missing]:
        """Scene means keyed by metric name; the LPIPS and FLIP keys carry their net/settings."""
        return {"psnr": self._mean(self.psnr), "ssim": self._mean(self.ssim),
                self.lpips_name: self._mean(self.lpips), self.flip_name: self._mean(self.flip)}

    def to_json(self) -> dict:
        per_view = {"psnr": self.psnr, "ssim": self.ssim, self.lpips_name: self.lpips,
                    self.flip_name: self.flip}
        return {"names": self.names, "quantized_8bit": self.quantized,
                "mean": json_value(self.means()), "per_view": json_value(per_view), **self.extra}


def _check_pair(pred: torch.Tensor, gt: torch.Tensor, i: int) -> None:
    if pred.dim() != 3 or pred.shape[-1] != 3:
        raise ValueError(f"image {i}: predictions must be [H, W, 3], got {tuple(pred.shape)}")
    if pred.shape != gt.shape:
        raise ValueError(f"image {i}: prediction {tuple(pred.shape)} and ground truth "
                         f"{tuple(gt.shape)} differ in shape")


def evaluate_images(preds: Sequence[torch.Tensor], gts: Sequence[torch.Tensor],
                    names: Sequence[str] | None = None, *,
                    lpips: "lpips_mod.LPIPS | Missing | None" = None, lpips_net: str = "vgg",
                    lpips_weights: str | None = None,
                    lpips_input: "lpips_mod.InputConvention" = "lpips", flip: bool = True,
                    quantize: bool = True, device: torch.device | str | None = None) -> ImageMetrics:
    """PSNR, SSIM, LPIPS and FLIP per image.

    ``lpips``: a loaded network, a ``Missing`` to skip with that reason, or None to load ``lpips_net``
    from ``lpips_weights`` / ``$SMGS_LPIPS_WEIGHTS`` / the per-user cache, set up there on first use
    (``smgs.metrics.lpips_weights.ensure_weights``; Missing with the reason where it cannot be) with input
    convention ``lpips_input`` ("lpips": [0, 1] mapped to [-1, 1] as the lpips package; "3dgs":
    [0, 1] fed unchanged as the 3DGS evaluation does; see ``smgs.metrics.lpips``).
    ``quantize``: round both images to 8 bits first, as 3DGS's PNG round trip does.
    ``device``: where PSNR, SSIM and LPIPS are computed (None: the first prediction's device); FLIP
    runs on the host (its package takes numpy arrays).
    """
    if len(preds) != len(gts):
        raise ValueError(f"{len(preds)} predictions but {len(gts)} ground-truth images")
    names = [f"{i:05d}" for i in range(len(preds))] if names is None else list(names)
    dev = torch.device(device) if device is not None else (preds[0].device if len(preds) else None)
    if lpips is None:
        found = ensure_weights(lpips_net, lpips_weights)   # set up on first use where it can be
        lpips = found if isinstance(found, Missing) else \
            lpips_mod.load_lpips(lpips_net, found, input_convention=lpips_input, device=dev)
    lpips_name = (lpips.name if isinstance(lpips, lpips_mod.LPIPS)
                  else lpips_mod.metric_name(lpips_net, lpips_input))
    flip_ok = flip_available() if flip else Missing("FLIP not requested")
    psnrs: list[float] = []
    ssims: list[float] = []
    lps: list[float] = []
    flips: list[float] = []
    for i, (p, g) in enumerate(zip(preds, gts)):
        _check_pair(p, g, i)
        p, g = p.detach().float().to(dev), g.detach().float().to(dev)
        if quantize:
            p, g = quantize_8bit(p), quantize_8bit(g)
        psnrs.append(psnr(p, g))
        ssims.append(ssim(p, g))
        if isinstance(lpips, lpips_mod.LPIPS):
            lps.append(lpips.distance(p, g))
        if flip_ok is True:
            flips.append(float(flip_error_map(g, p).mean()))
    return ImageMetrics(names=names, psnr=psnrs, ssim=ssims,
                        lpips=lps if isinstance(lpips, lpips_mod.LPIPS) else lpips,
                        lpips_name=lpips_name, flip=flips if flip_ok is True else flip_ok,
                        quantized=quantize)
