"""Per-pixel depth order (``sort="per_pixel"``, StopThePop, Radl et al. 2024): each pixel orders its
splats by the depth along its own ray where the splat's 3D response peaks.

For the ray o + t·d of a pixel and a Gaussian (μ, Σ), the response exp(-½(x-μ)ᵀΣ⁻¹(x-μ)) peaks at
t* = dᵀΣ⁻¹(μ - o) / dᵀΣ⁻¹d. In camera coordinates o = 0 and d = ((x - cx)/fx, (y - cy)/fy, 1) for the
pixel centre (x, y), so t* is the camera-space z of the peak. Only the direction of Σ⁻¹ matters
(t* is invariant to its scale), so each splat carries Q = Σ_i w_i r_i r_iᵀ with w_i = (s_min/s_i)²
over its rotated axes r_i (the thinnest axis has weight 1): a flat splat (s_min = 0) keeps only its
normal, and t* is the ray's intersection with its plane, the limit of a thinner and thinner one.
Nine numbers per splat: Q's upper triangle and b = Qμ; t* = b·d / dᵀQd (``peak_depth`` in
``smgs/raster/reference.py``). Where dᵀQd vanishes (a flat splat seen exactly edge-on) the splat's
centre depth is used. No gradient: the order is not differentiated.
"""

from __future__ import annotations

import torch

from smgs.camera import Camera
from smgs.raster.projection import quat_to_rotmat
from smgs.raster.types import RayDepth

SORTS: tuple[str, ...] = ("global", "per_pixel")


def check_sort(sort: str) -> str:
    if sort not in SORTS:
        raise ValueError(f"sort must be one of {', '.join(map(repr, SORTS))}, got {sort!r}")
    return sort


@torch.no_grad()
def ray_depth(means3d: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, camera: Camera) -> RayDepth:
    """The per-splat coefficients of ``means3d, quats, scales`` [M, ...] (the projected splats'
    rows) seen through ``camera``; formed in float64 so that nearly equal depths keep their order."""
    dev = means3d.device
    V = camera.viewmat.to(dev, torch.float64)
    rw, tw = V[:3, :3], V[:3, 3]
    mu = means3d.detach().double() @ rw.T + tw                        # [M, 3] camera space
    axes = rw @ quat_to_rotmat(quats.detach().double())                # [M, 3, 3], columns r_i
    s = scales.detach().double()
    s_min = s.min(dim=-1, keepdim=True).values
    # (s_min/s_i)², 1 on the thinnest axis (also where all scales are 0: a point, Q = I)
    w = torch.where(s == s_min, torch.ones_like(s), (s_min / torch.where(s > 0, s, torch.ones_like(s))) ** 2)
    Q = (axes * w[:, None, :]) @ axes.transpose(1, 2)                  # Σ_i w_i r_i r_iᵀ
    b = (Q @ mu[:, :, None])[:, :, 0]
    iu = torch.triu_indices(3, 3, device=dev)
    coefs = torch.cat([Q[:, iu[0], iu[1]], b], dim=1)
    Kc = camera.K.double()
    return RayDepth(coefs, float(Kc[0, 0]), float(Kc[1, 1]), float(Kc[0, 2]), float(Kc[1, 2]))
