"""EWA projection of 3D Gaussians to 2D splats (OpenCV pinhole), in differentiable PyTorch."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from smgs.camera import Camera
from smgs.raster import constants as K


@dataclass
class Projected:
    """Splats of the Gaussians that survived culling; ``ids`` index the input Gaussians."""

    ids: torch.Tensor       # [M] long
    means2d: torch.Tensor   # [M, 2] pixels
    conics: torch.Tensor    # [M, 3] (a, b, c) of the inverse dilated 2D covariance
    depths: torch.Tensor    # [M] camera-space z
    radii: torch.Tensor     # [M, 2] half extents of the 3σ box in pixels (no gradient)


def quat_to_rotmat(quats: torch.Tensor) -> torch.Tensor:
    """Rotation matrices from quaternions (w, x, y, z), normalised here."""
    q = quats / quats.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], dim=-1).reshape(*q.shape[:-1], 3, 3)


def project_gaussians(means3d: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor,
                      camera: Camera, near_plane: float = K.NEAR_PLANE,
                      eps2d: float = K.EPS2D) -> Projected:
    """EWA splatting (Zwicker et al.; 3DGS): Σ2D = J W Σ Wᵀ Jᵀ + eps2d·I.

    Culls Gaussians in front of the near plane and those whose 3σ box misses the image (the box
    is exact for the ellipse, so culling never changes an image). As in 3DGS, the Jacobian is
    evaluated at the mean clamped to 1.3× the field of view, which keeps far off-axis splats from
    exploding.
    """
    dtype = means3d.dtype
    V = camera.viewmat.to(means3d.device, dtype)
    Kc = camera.K.to(means3d.device, dtype)
    Rw, tw = V[:3, :3], V[:3, 3]
    pc = means3d @ Rw.T + tw
    z = pc[:, 2]
    keep = z > near_plane
    ids = torch.nonzero(keep).squeeze(1)
    pc, z = pc[ids], z[ids]
    fx, fy, cx, cy = Kc[0, 0], Kc[1, 1], Kc[0, 2], Kc[1, 2]
    # The visible range of x/z widened by 30% of the half field of view each side (3DGS's
    # 1.3·tan(fov/2) for a centred principal point).
    mx, my = 0.15 * camera.width / fx, 0.15 * camera.height / fy
    tx = z * torch.clamp(pc[:, 0] / z, -cx / fx - mx, (camera.width - cx) / fx + mx)
    ty = z * torch.clamp(pc[:, 1] / z, -cy / fy - my, (camera.height - cy) / fy + my)
    zero = torch.zeros_like(z)
    J = torch.stack([fx / z, zero, -fx * tx / (z * z),
                     zero, fy / z, -fy * ty / (z * z)], dim=-1).reshape(-1, 2, 3)
    R = quat_to_rotmat(quats[ids])
    M = R * scales[ids][:, None, :]                      # R·S
    cov3 = M @ M.transpose(1, 2)
    JW = J @ Rw
    cov2 = JW @ cov3 @ JW.transpose(1, 2)
    sxx = cov2[:, 0, 0] + eps2d
    syy = cov2[:, 1, 1] + eps2d
    sxy = cov2[:, 0, 1]
    det = torch.clamp(sxx * syy - sxy * sxy, min=1e-12)
    conics = torch.stack([syy / det, -sxy / det, sxx / det], dim=-1)
    means2d = torch.stack([fx * pc[:, 0] / z + cx, fy * pc[:, 1] / z + cy], dim=-1)
    radii = K.SIGMA_EXTENT * torch.stack([sxx, syy], dim=-1).detach().sqrt()
    m2 = means2d.detach()
    onscreen = ((m2[:, 0] + radii[:, 0] > 0) & (m2[:, 0] - radii[:, 0] < camera.width)
                & (m2[:, 1] + radii[:, 1] > 0) & (m2[:, 1] - radii[:, 1] < camera.height))
    sel = torch.nonzero(onscreen).squeeze(1)
    return Projected(ids=ids[sel], means2d=means2d[sel], conics=conics[sel], depths=z[sel],
                     radii=radii[sel])
