"""The compiled backends' tile lists, emulated in PyTorch for the reference renderer.

The patch scope of k_max (docs/kmax-scope.md) puts a splat in the softmax head of a tile's pixels
by its position in that tile's depth-sorted list, so the reference must know the lists exactly as
the kernels build them: a splat is listed in every tile its conservative 3σ box touches
(``splat_box`` in csrc/cpu_kernel.cpp and csrc/cuda_kernel.cu, transcribed here operation by
operation in float64, so float32 inputs give the kernels' boxes bit for bit), only where its
opacity is at least 1/255 and the box meets the image; lists are in depth order, ties by index.
"""

from __future__ import annotations

import torch

from smgs.raster import constants as K

NOT_LISTED = 2**31 - 1
"""Position of a splat in a tile that does not list it (never inside a head)."""

# 2·γ6 with the unit roundoff u = 2^-24: the float32 error bound of q (csrc/cpu_kernel.cpp, splat_box)
_GAMMA2 = 16.0 * 5.9604644775390625e-8


def splat_boxes(means2d: torch.Tensor, conics: torch.Tensor, opacities: torch.Tensor, width: int,
                height: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(listed [N] bool, box [N, 4] long: inclusive pixel ranges x0, x1, y0, y1) as the kernels'
    ``splat_box``: the box of the ellipse where the float32 q can be <= 4.5, or the whole image
    where no such bound exists (non-positive-definite conic, bound too loose)."""
    m = means2d.detach().double()
    mx, my = m[:, 0], m[:, 1]
    a, b, c = conics.detach().double().unbind(-1)
    det = a * c - b * b
    pd = torch.isfinite(m).all(1) & torch.isfinite(conics.detach()).all(1) & (a > 0) & (c > 0) & (det > 0)
    one = torch.ones_like(a)
    a_, c_, det_ = (torch.where(pd, t, one) for t in (a, c, det))   # finite values off the PD branch
    lmax = 0.5 * (a_ + c_) + torch.sqrt(0.25 * (a_ - c_) * (a_ - c_) + b * b)
    lmin = det_ / lmax
    kappa = 1.0 + 2.0 * b.abs() / lmin
    g = _GAMMA2 * kappa
    bounded = pd & (g < 0.5)
    qmax = -K.P_MIN / (1.0 - torch.where(bounded, g, 0 * g))
    rx = torch.sqrt(2.0 * qmax * c_ / det_)
    ry = torch.sqrt(2.0 * qmax * a_ / det_)
    sx = 1e-6 * (1.0 + mx.abs() + rx)
    sy = 1e-6 * (1.0 + my.abs() + ry)
    fx0, fx1 = torch.ceil(mx - rx - sx - K.PIXEL_CENTER), torch.floor(mx + rx + sx - K.PIXEL_CENTER)
    fy0, fy1 = torch.ceil(my - ry - sy - K.PIXEL_CENTER), torch.floor(my + ry + sy - K.PIXEL_CENTER)
    off = (fx1 < 0) | (fy1 < 0) | (fx0 > width - 1) | (fy0 > height - 1) | (fx0 > fx1) | (fy0 > fy1)
    box = torch.stack([fx0.clamp(0, width - 1), fx1.clamp(0, width - 1), fy0.clamp(0, height - 1),
                       fy1.clamp(0, height - 1)], 1)
    whole = torch.tensor([0, width - 1, 0, height - 1], dtype=box.dtype, device=box.device)
    box = torch.where(bounded[:, None], box, whole).long()
    listed = (opacities.detach() >= K.ALPHA_MIN) & ~(bounded & off)
    return listed, box


def list_positions(means2d: torch.Tensor, conics: torch.Tensor, opacities: torch.Tensor, depths: torch.Tensor,
                   width: int, height: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(positions [tiles, N] int64, tile of each pixel [H·W] int64): the position of splat j in the
    depth-sorted list of tile t (``NOT_LISTED`` where t does not list it), tiles row-major with
    ``constants.TILE_SIZE`` pixels a side. Dense over tiles × splats: for the reference's small scenes."""
    ts = K.TILE_SIZE
    tx, ty = -(-width // ts), -(-height // ts)
    listed, box = splat_boxes(means2d, conics, opacities, width, height)
    order = torch.sort(depths.detach(), stable=True).indices     # depth order, ties by index
    b = box[order] // ts                                          # tile ranges, sorted
    col = torch.arange(tx, device=box.device)
    row = torch.arange(ty, device=box.device)
    in_x = (col[:, None] >= b[None, :, 0]) & (col[:, None] <= b[None, :, 1])      # [tx, N]
    in_y = (row[:, None] >= b[None, :, 2]) & (row[:, None] <= b[None, :, 3])      # [ty, N]
    member = (in_y[:, None, :] & in_x[None, :, :]).reshape(tx * ty, -1) & listed[order][None, :]
    pos_sorted = torch.where(member, torch.cumsum(member.long(), 1) - 1, torch.full_like(member, NOT_LISTED,
                                                                                        dtype=torch.long))
    pos = torch.empty_like(pos_sorted)
    pos[:, order] = pos_sorted
    ys, xs = torch.meshgrid(torch.arange(height, device=box.device), torch.arange(width, device=box.device),
                            indexing="ij")
    pixel_tile = ((ys // ts) * tx + xs // ts).reshape(-1)
    return pos, pixel_tile
