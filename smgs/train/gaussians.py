"""Trainable Gaussians: raw parameters (the optimiser's leaves) and their activations.

means: identity; scales: exp; opacities: sigmoid; quats: normalised by the renderer (wxyz);
sh0 [N,1,3] and shN [N,K-1,3]: SH coefficients (3DGS ``features_dc`` / ``features_rest``);
alpha, beta: exp or softplus (``ParamInit``); gamma: the same activation divided by the scene
extent (scale-aware, see ``GaussianConfig``).
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

from smgs.raster.sh import num_sh_bases, rgb_to_sh0
from smgs.train.sections import GaussianConfig, ParamInit

PARAM_NAMES: tuple[str, ...] = ("means", "scales", "quats", "opacities", "sh0", "shN", "alpha", "beta",
                                "gamma")
"""Every parameter group, in a fixed order (optimiser groups, checkpoints, error messages)."""


def _activate(raw: torch.Tensor, kind: str) -> torch.Tensor:
    if kind == "exp":
        return torch.exp(raw)
    if kind == "softplus":
        return F.softplus(raw)
    raise ValueError(f"unknown activation {kind!r}; expected 'exp' or 'softplus'")


def _inverse(value: float, kind: str) -> float:
    if value <= 0:
        raise ValueError(f"initial value must be > 0 for activation {kind!r}, got {value}")
    if kind == "exp":
        return math.log(value)
    if kind == "softplus":
        return value + math.log(-math.expm1(-value))   # log(e^v − 1), stable
    raise ValueError(f"unknown activation {kind!r}; expected 'exp' or 'softplus'")


def _gamma_raw(cfg: GaussianConfig, extent: float, scales: torch.Tensor) -> torch.Tensor:
    """Raw γ (stored relative to ``extent``) of Gaussians with initial ``scales`` [N, 3]:
    γ_rel = init, or init·extent/σ_i with σ_i the mean initial scale (``gamma_unit="splat"``)."""
    if cfg.gamma_unit not in ("splat", "extent"):
        raise ValueError(f"unknown gamma_unit {cfg.gamma_unit!r}; expected 'splat' or 'extent'")
    n = scales.shape[0]
    base = _inverse(cfg.gamma.init, cfg.gamma.activation)   # also validates init > 0
    if cfg.gamma_unit == "extent":
        return torch.full((n,), base, dtype=torch.float32, device=scales.device)
    sigma = scales.double().mean(1)
    if not bool((sigma > 0).all()) or not bool(torch.isfinite(sigma).all()):
        raise ValueError("gamma_unit='splat' needs positive finite initial scales; "
                         "use gamma_unit='extent' for Gaussians without a size")
    value = cfg.gamma.init * float(extent) / sigma
    raw = value.log() if cfg.gamma.activation == "exp" else value + torch.log(-torch.expm1(-value))
    return raw.float()


def inverse_sigmoid(x: torch.Tensor) -> torch.Tensor:
    return torch.log(x / (1 - x))


def knn_scale(points: torch.Tensor, k: int = 3) -> torch.Tensor:
    """sqrt of the mean squared distance to the k nearest other points (3DGS ``distCUDA2``: k = 3),
    clamped at 1e-7 before the sqrt as 3DGS does. A k-d tree (scipy's ``cKDTree``) answers the
    query in O(n log n) time and O(n) memory: 100K random points in well under a second, where
    dense distance blocks took a minute and gigabytes. Exact (not approximate) neighbours, in
    float64; a duplicate point is a neighbour at distance 0, as in distCUDA2."""
    from scipy.spatial import cKDTree

    n = points.shape[0]
    if n <= 1:
        return points.new_ones(n)
    k = min(k, n - 1)
    p = points.detach().to("cpu", torch.float64).numpy()
    if not np.isfinite(p).all():
        raise ValueError(f"knn_scale: {int((~np.isfinite(p)).any(1).sum())} of {n} points are not finite "
                         "(NaN or inf coordinates); fix or drop them before initialising Gaussians")
    # k + 1: the query point itself comes back at distance 0; dropping the smallest distance drops
    # it (or an exact duplicate, whose distance is the same 0), so the rest are the k nearest others
    d, _ = cKDTree(p).query(p, k=k + 1)
    mean_d2 = np.square(d[:, 1:]).mean(1)
    out = torch.from_numpy(np.sqrt(np.maximum(mean_d2, 1e-7)))
    return out.to(device=points.device, dtype=points.dtype)


class Gaussians:
    """The raw parameters of N Gaussians as a dict of leaf tensors (``params``) plus the
    activation rules. The densification strategy and the optimiser edit ``params`` in place of
    the dict (new tensors), so always read them through this object."""

    def __init__(self, params: dict[str, torch.Tensor], cfg: GaussianConfig, extent: float,
                 sh_degree: int) -> None:
        missing = set(PARAM_NAMES) - set(params)
        if missing:
            raise ValueError(f"Gaussians: missing parameter groups {sorted(missing)}")
        self.params = params
        self.cfg = cfg
        self.extent = float(extent)
        self.max_sh_degree = int(sh_degree)

    # -- construction ------------------------------------------------------------------------
    @classmethod
    def from_points(cls, points: torch.Tensor, colors: torch.Tensor, cfg: GaussianConfig, extent: float,
                    sh_degree: int, scales: torch.Tensor | None = None, *,
                    device: torch.device | str) -> "Gaussians":
        """3DGS initialisation: colour to the SH DC term, log kNN scale (isotropic), identity
        rotation, opacity ``init_opacity``; α, β, γ at their configured initial values. Every
        parameter is created on ``device`` (the inputs are moved there first)."""
        points = points.to(device=device, dtype=torch.float32)
        n = points.shape[0]
        if scales is None:
            scales = knn_scale(points)[:, None].expand(n, 3)
        k = num_sh_bases(sh_degree)

        def full(shape: tuple[int, ...], value: float) -> torch.Tensor:
            return torch.full(shape, value, dtype=torch.float32, device=device)

        quats = full((n, 4), 0.0)
        quats[:, 0] = 1.0
        p = {
            "means": points.clone(),
            "scales": torch.log(scales.to(device=device, dtype=torch.float32)).clone(),
            "quats": quats,
            "opacities": inverse_sigmoid(full((n,), float(cfg.init_opacity))),
            "sh0": rgb_to_sh0(colors.to(device=device, dtype=torch.float32))[:, None, :].clone(),
            "shN": full((n, k - 1, 3), 0.0),
            "alpha": full((n,), _inverse(cfg.alpha.init, cfg.alpha.activation)),
            "beta": full((n,), _inverse(cfg.beta.init, cfg.beta.activation)),
            "gamma": _gamma_raw(cfg, extent, scales.to(device=device, dtype=torch.float32)),
        }
        return cls({name: t.contiguous().requires_grad_(True) for name, t in p.items()}, cfg, extent,
                   sh_degree)

    # -- activated values --------------------------------------------------------------------
    def __len__(self) -> int:
        return self.params["means"].shape[0]

    @property
    def means(self) -> torch.Tensor:
        return self.params["means"]

    @property
    def scales(self) -> torch.Tensor:
        return torch.exp(self.params["scales"])

    @property
    def quats(self) -> torch.Tensor:
        return self.params["quats"]

    @property
    def opacities(self) -> torch.Tensor:
        return torch.sigmoid(self.params["opacities"])

    @property
    def sh(self) -> torch.Tensor:
        return torch.cat([self.params["sh0"], self.params["shN"]], dim=1)

    @property
    def alpha(self) -> torch.Tensor:
        return _activate(self.params["alpha"], self.cfg.alpha.activation)

    @property
    def beta(self) -> torch.Tensor:
        return _activate(self.params["beta"], self.cfg.beta.activation)

    @property
    def gamma_rel(self) -> torch.Tensor:
        """γ relative to the scene extent (the configured, stored quantity)."""
        return _activate(self.params["gamma"], self.cfg.gamma.activation)

    @property
    def gamma(self) -> torch.Tensor:
        """γ in world units (1/length), as the renderer multiplies it with a depth difference."""
        return self.gamma_rel / self.extent

    # -- helpers for the strategy ------------------------------------------------------------
    def raw(self, name: str) -> torch.Tensor:
        return self.params[name]

    def state_dict(self) -> dict[str, torch.Tensor]:
        return {k: v.detach().clone() for k, v in self.params.items()}

    @property
    def device(self) -> torch.device:
        return self.params["means"].device

    def load_state_dict(self, state: dict[str, torch.Tensor]) -> None:
        """Restore parameters onto this model's device (a checkpoint from another device loads)."""
        missing = set(PARAM_NAMES) - set(state)
        if missing:
            raise ValueError(f"checkpoint lacks parameter groups {sorted(missing)}")
        dev = self.device
        self.params = {k: state[k].detach().to(dev, copy=True).contiguous().requires_grad_(True)
                       for k in PARAM_NAMES}


def flat_layout(n: int, depth: float, spacing: float, center: torch.Tensor | None = None,
                rotation: torch.Tensor | None = None, jitter: float = 0.0,
                generator: torch.Generator | None = None, device: torch.device | str | None = None) -> torch.Tensor:
    """n points on a centred square grid (row-major, ⌈√n⌉ per row) ``spacing`` apart, at ``depth``
    in front of a camera (camera-to-world ``rotation``, ``center``): the paper's "identical
    Gaussians slightly apart at depth 1" (supp. Sec. 6). ``jitter`` moves each point in x and y by
    a uniform offset in ±jitter·spacing (drawn from ``generator``, on its device). The points are
    on ``device`` (default: the generator's device, else torch's default)."""
    if device is None and generator is not None:
        device = generator.device
    side = max(1, math.ceil(math.sqrt(n)))
    idx = torch.arange(n, device=device)
    gx = (idx % side).double() - (side - 1) / 2
    gy = (idx // side).double() - (math.ceil(n / side) - 1) / 2
    if jitter:
        off = (torch.rand(n, 2, generator=generator, dtype=torch.float64, device=device) * 2 - 1) * jitter
        gx, gy = gx + off[:, 0], gy + off[:, 1]
    local = torch.stack([gx * spacing, gy * spacing, torch.full_like(gx, depth)], dim=1)
    if rotation is not None:
        local = local @ rotation.to(device=local.device, dtype=torch.float64).T
    if center is not None:
        local = local + center.to(device=local.device, dtype=torch.float64)
    return local.float()
