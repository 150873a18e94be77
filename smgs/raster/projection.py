"""EWA projection of 3D Gaussians to 2D splats (OpenCV pinhole), differentiable.

The projection is one autograd node with a hand-written backward: a few Gaussians per image make
the step cost the number of tensor ops, and autograd's graph of the same math has ~170 forward
and ~250 backward ops. tests/test_raster_projection.py checks the backward with ``gradcheck``.

On float32 CPU tensors the same math runs as one compiled pass each way (``csrc/projection_cpu.cpp``,
built just in time like the CPU renderer): even as one node, the ~40 forward and ~50 backward
tensor ops cost more than the arithmetic, at 4 Gaussians and at 10K. ``_Project`` stays the oracle
(tests/test_raster_projection_cpu.py) and the path for other dtypes and devices.

The view-dependent colours (``ShColours``: spherical harmonics along the view directions, + 0.5,
clamped) are part of that compiled pass, for the kept Gaussians only, with their adjoint in its
backward: in PyTorch (``sh.eval_sh``, the oracle and the other devices' path) each of the 16
coefficients is a select whose backward zero-fills the whole [N, 16, 3] tensor.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path

import torch
from torch.autograd.function import once_differentiable

from smgs.camera import Camera
from smgs.raster import constants as K
from smgs.raster.cpu_build import cpu_extension, use_cpu_kernel
from smgs.raster.device_glue import to_device
from smgs.raster.kernel_clock import kernel
from smgs.raster.sh import eval_sh, num_sh_bases

_CSRC = Path(__file__).parent / "csrc"


@dataclass
class Projected:
    """Splats of the Gaussians that survived culling; ``ids`` index the input Gaussians."""

    ids: torch.Tensor       # [M] long
    means2d: torch.Tensor   # [M, 2] pixels
    conics: torch.Tensor    # [M, 3] (a, b, c) of the inverse dilated 2D covariance
    depths: torch.Tensor    # [M] camera-space z
    radii: torch.Tensor     # [M, 2] half extents of the 3σ box in pixels (no gradient)
    # dense projection (``project_gaussians(dense=True)``): M = N, ids = arange(N), and this [N] bool
    # marks the rows that survived culling (the others have radius 0 and render at opacity 0)
    visible: torch.Tensor | None = None
    colors: torch.Tensor | None = None   # [M, C] where ``project_gaussians`` was given ``ShColours``


@dataclass(frozen=True)
class ShColours:
    """The view-dependent colours to make with the projection: real spherical harmonics of
    ``degree`` (``sh.eval_sh``) along the unit directions from the camera centre to the means, + 0.5,
    clamped at 0 where ``clamp`` (3DGS). The coefficients come as the trainer keeps them, in two
    parts read in place (no ``torch.cat`` per step): ``sh0`` [N, 1, C] (3DGS's features_dc) and
    ``rest`` [N, K−1, C] (features_rest); or as one tensor ``sh0`` [N, K, C] with ``rest`` None.
    K ≥ (degree + 1)²; the coefficients past the degree get zero gradients."""

    sh0: torch.Tensor
    rest: torch.Tensor | None
    degree: int
    clamp: bool = True

    def coefficients(self) -> torch.Tensor:
        """The [N, (degree + 1)², C] coefficients the degree uses, as one tensor (the PyTorch path)."""
        nb = num_sh_bases(self.degree)
        if self.rest is None:
            return self.sh0[:, :nb]
        return self.sh0 if nb == 1 else torch.cat([self.sh0, self.rest[:, :nb - 1]], dim=1)


def quat_to_rotmat(quats: torch.Tensor) -> torch.Tensor:
    """Rotation matrices from quaternions (w, x, y, z), normalised here."""
    q = quats / quats.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], dim=-1).reshape(*q.shape[:-1], 3, 3)


@functools.lru_cache(maxsize=8)
def _rot_linear(dtype: torch.dtype, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """(L [16, 9], c [9]) with vec(R) = vec(q qᵀ) @ L + c for a unit quaternion q = (w, x, y, z):
    the rotation matrix above as one matrix product of the outer product."""
    w, x, y, z = range(4)
    terms = [  # R entries, row-major: list of (coefficient, a, b) for q_a q_b, plus a constant
        (1, [(-2, y, y), (-2, z, z)]), (0, [(2, x, y), (-2, w, z)]), (0, [(2, x, z), (2, w, y)]),
        (0, [(2, x, y), (2, w, z)]), (1, [(-2, x, x), (-2, z, z)]), (0, [(2, y, z), (-2, w, x)]),
        (0, [(2, x, z), (-2, w, y)]), (0, [(2, y, z), (2, w, x)]), (1, [(-2, x, x), (-2, y, y)]),
    ]
    lin = torch.zeros(16, 9, dtype=torch.float64, device=device)
    const = torch.zeros(9, dtype=torch.float64, device=device)
    for k, (c, prods) in enumerate(terms):
        const[k] = c
        for coef, a, b in prods:
            lin[4 * a + b, k] += coef
    return lin.to(dtype=dtype, device=device), const.to(dtype=dtype, device=device)


@dataclass(frozen=True)
class _View:
    """The camera quantities the projection uses, in the Gaussians' dtype."""

    rw: torch.Tensor        # [3, 3] world-to-camera rotation
    tw: torch.Tensor        # [3] translation
    f: torch.Tensor         # [2] (fx, fy)
    c: torch.Tensor         # [2] (cx, cy)
    lo: torch.Tensor        # [2] lower limits of x/z, y/z for the Jacobian (3DGS's 1.3× fov)
    hi: torch.Tensor        # [2] upper limits
    size: torch.Tensor      # [2] (width, height)


VIEW_FLOATS = 22
"""Length of the packed view: rw (9), tw (3), f, c, lo, hi, size (2 each); the camera centre (3)
follows where asked for (``host_view(..., center=True)``)."""


def host_view(camera: Camera, dtype: torch.dtype, center: bool = False) -> torch.Tensor:
    """The camera quantities the projection (and, with ``center``, the SH view directions) use, as
    one host tensor in the Gaussians' dtype: [22], or [25] with the camera centre.

    Computed on the host from the camera's own tensors (a camera kept on the CPU, as the trainer's,
    costs no device copy and no wait), with the float arithmetic the projection used to do on the
    device (same IEEE operations, so the same bits)."""
    cpu = torch.device("cpu")
    V = camera.viewmat.to(cpu, dtype)
    Kc = camera.K.to(cpu, dtype)
    f = torch.stack([Kc[0, 0], Kc[1, 1]])
    c = torch.stack([Kc[0, 2], Kc[1, 2]])
    size = torch.tensor([camera.width, camera.height], dtype=dtype, device=cpu)
    # The visible range of x/z widened by 30% of the half field of view each side (3DGS's
    # 1.3·tan(fov/2) for a centred principal point).
    m = 0.15 * size / f
    parts = [V[:3, :3].reshape(-1), V[:3, 3], f, c, -c / f - m, (size - c) / f + m, size]
    if center:
        parts.append(camera.center.to(cpu, dtype))
    return torch.cat(parts)


def _view_of(packed: torch.Tensor) -> _View:
    """The ``_View`` of a packed view (``host_view``), as slices of it on its device."""
    return _View(packed[:9].reshape(3, 3), packed[9:12], packed[12:14], packed[14:16], packed[16:18],
                 packed[18:20], packed[20:22])


def _view(camera: Camera, dtype: torch.dtype, device: torch.device) -> _View:
    return _view_of(to_device(host_view(camera, dtype), torch.device(device)))


def _packed_view(view: _View) -> torch.Tensor:
    """``view`` as the flat [22] the compiled projection reads: rw, tw, f, c, lo, hi, size."""
    return torch.cat([view.rw.reshape(-1), view.tw, view.f, view.c, view.lo, view.hi, view.size])


def _ewa(pc: torch.Tensor, z: torch.Tensor, quats, scales, view: _View, eps2d: float):
    """The per-Gaussian forward math of ``_Project`` on camera-space points ``pc`` [M,3] whose depth
    column is ``z`` [M,1]: (means2d, conics, depths, radii), then the intermediates its backward reads."""
    r = pc[:, :2] / z
    u = torch.minimum(torch.maximum(r, view.lo), view.hi)
    ab = view.f / z                                                    # (fx/z, fy/z)
    D = view.rw[:2] - u[:, :, None] * view.rw[2]                       # [M, 2, 3]
    T = D * ab[:, :, None]
    qn = quats.norm(dim=-1, keepdim=True)
    q = quats / qn
    lin, const = _rot_linear(q.dtype, q.device)
    R = torch.addmm(const, (q[:, :, None] * q[:, None, :]).reshape(-1, 16), lin).reshape(-1, 3, 3)
    TR = T @ R
    P = TR * scales[:, None, :]
    cov = P @ P.transpose(1, 2)
    sxx = cov[:, 0, 0] + eps2d
    syy = cov[:, 1, 1] + eps2d
    sxy = cov[:, 0, 1]
    det_raw = sxx * syy - sxy * sxy
    det = det_raw.clamp_min(1e-12)
    conics = torch.stack([syy, -sxy, sxx], dim=-1) / det[:, None]
    means2d = torch.addcmul(view.c, view.f, r)
    radii = K.SIGMA_EXTENT * torch.stack([sxx, syy], dim=-1).sqrt()
    return (means2d, conics, z[:, 0], radii), (z, r, u, ab, D, T, q, qn, R, TR, scales, sxx, syy, sxy, det_raw, det)


def _ewa_backward(saved, view: _View, g_m2d, g_con, g_depth):
    """(g_means, g_quats, g_scales) of the rows ``_ewa`` computed."""
    z, r, u, ab, D, T, q, qn, R, TR, scales, sxx, syy, sxy, det_raw, det = saved
    # conic = (syy, −sxy, sxx) / det, det = max(sxx·syy − sxy², 1e-12) (clamp: torch's mask)
    inv = 1.0 / det
    ga, gb, gc = g_con.unbind(1)
    g_det = -(ga * syy - gb * sxy + gc * sxx) * inv * inv * (det_raw >= 1e-12)
    g_sxx = gc * inv + g_det * syy
    g_syy = ga * inv + g_det * sxx
    g_sxy = -gb * inv - 2 * sxy * g_det
    # Σ2D = P Pᵀ, sxy read from the upper triangle: dL/dP = (G + Gᵀ)·P
    G = torch.stack([2 * g_sxx, g_sxy, g_sxy, 2 * g_syy], dim=1).reshape(-1, 2, 2)
    s3 = scales[:, None, :]
    g_P = G @ (TR * s3)
    g_TR = g_P * s3
    g_s = (g_P * TR).sum(1)
    g_T = g_TR @ R.transpose(1, 2)
    g_R = T.transpose(1, 2) @ g_TR
    # T = diag(ab)·D, D = Rw[:2] − u ⊗ Rw[2]; ab = f / z
    g_ab = (g_T * D).sum(2)
    g_u = -(g_T @ view.rw[2]) * ab
    # u = clamp(r) passes the gradient inside the limits, bounds included (torch.clamp);
    # means2d = f·r + c; r = p_xy / z; depth = z
    g_r = g_u * ((r >= view.lo) & (r <= view.hi)) + g_m2d * view.f
    g_z = g_depth[:, None] - ((g_r * r).sum(1, keepdim=True) + (g_ab * ab).sum(1, keepdim=True)) / z
    g_means = torch.cat([g_r / z, g_z], 1) @ view.rw
    # vec(R) = vec(q qᵀ)·L + c; q = quats / |quats|
    lin, _ = _rot_linear(q.dtype, q.device)
    g_qq = (g_R.reshape(-1, 9) @ lin.T).reshape(-1, 4, 4)
    g_q = ((g_qq + g_qq.transpose(1, 2)) @ q[:, :, None])[:, :, 0]
    g_quats = (g_q - q * (q * g_q).sum(1, keepdim=True)) / qn
    return g_means, g_quats, g_s


class _Project(torch.autograd.Function):
    """(means3d, quats, scales) -> (ids, means2d, conics, depths, radii) of the culled splats.

    Per Gaussian: p = Rw·m + tw; r = p_xy / z; u = clamp(r) (the Jacobian's clamped direction);
    T = J·Rw = diag(f / z)·(Rw[:2] − u ⊗ Rw[2]); P = T·R(q̂)·diag(s); Σ2D = P Pᵀ + eps2d·I;
    conic = (Σyy, −Σxy, Σxx) / max(det, 1e-12); means2d = f·r + c; depth = z.
    """

    @staticmethod
    def forward(ctx, means3d, quats, scales, view: _View, near_plane: float, eps2d: float):  # type: ignore[override]
        n = means3d.shape[0]
        pc = torch.addmm(view.tw, means3d, view.rw.T)
        near = torch.nonzero(pc[:, 2] > near_plane).squeeze(1)
        if near.shape[0] != n:
            pc, quats, scales = pc[near], quats[near], scales[near]
        (means2d, conics, depths, radii), saved = _ewa(pc, pc[:, 2:3], quats, scales, view, eps2d)
        on = ((means2d + radii > 0) & (means2d - radii < view.size)).all(dim=1)
        sel = torch.nonzero(on).squeeze(1)
        m = near.shape[0]
        ids = near
        if sel.shape[0] != m:
            ids, means2d, conics, depths, radii = near[sel], means2d[sel], conics[sel], depths[sel], radii[sel]
        ctx.mark_non_differentiable(ids, radii)
        ctx.view = view
        ctx.n = n
        ctx.sel = None if sel.shape[0] == m else sel
        ctx.save_for_backward(near, *saved)
        return ids, means2d, conics, depths, radii

    @staticmethod
    def backward(ctx, _g_ids, g_m2d, g_con, g_depth, _g_radii):  # type: ignore[override]
        near, *saved = ctx.saved_tensors
        view, sel, n = ctx.view, ctx.sel, ctx.n
        m = saved[0].shape[0]
        if sel is not None:       # back to the rows of the near-plane survivors
            g_m2d = g_m2d.new_zeros(m, 2).index_copy_(0, sel, g_m2d)
            g_con = g_con.new_zeros(m, 3).index_copy_(0, sel, g_con)
            g_depth = g_depth.new_zeros(m).index_copy_(0, sel, g_depth)
        g_means, g_quats, g_s = _ewa_backward(saved, view, g_m2d, g_con, g_depth)
        if m != n:                # back to all Gaussians (those behind the near plane get 0)
            g_means = g_means.new_zeros(n, 3).index_copy_(0, near, g_means)
            g_quats = g_quats.new_zeros(n, 4).index_copy_(0, near, g_quats)
            g_s = g_s.new_zeros(n, 3).index_copy_(0, near, g_s)
        return g_means, g_quats, g_s, None, None, None


@functools.lru_cache(maxsize=8)
def _unit_conic(dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    return to_device(torch.tensor([1.0, 0.0, 1.0], dtype=dtype, device="cpu"), device)


class _ProjectDense(torch.autograd.Function):
    """``_Project`` without compaction: every Gaussian keeps its row, so nothing waits for a count of
    survivors (the lean glue, ``smgs.raster.device_glue``). A culled row (behind the near plane, or
    its 3σ box off the image) gets radius 0, ``visible`` False and placeholder values (mean 0, the
    unit conic, depth 0) that the caller renders at opacity 0, so it reaches no pixel, as if absent;
    its gradients are 0. The kept rows run ``_Project``'s operations on the same values."""

    @staticmethod
    def forward(ctx, means3d, quats, scales, view: _View, near_plane: float, eps2d: float):  # type: ignore[override]
        n = means3d.shape[0]
        pc = torch.addmm(view.tw, means3d, view.rw.T)
        near = pc[:, 2:3] > near_plane
        z = torch.where(near, pc[:, 2:3], 1.0)     # behind the near plane: any finite depth, unused
        (means2d, conics, depths, radii), saved = _ewa(pc, z, quats, scales, view, eps2d)
        on = ((means2d + radii > 0) & (means2d - radii < view.size)).all(dim=1, keepdim=True) & near
        means2d = torch.where(on, means2d, 0.0)
        conics = torch.where(on, conics, _unit_conic(conics.dtype, conics.device))
        depths = torch.where(on[:, 0], depths, 0.0)
        radii = torch.where(on, radii, 0.0)
        ids = torch.arange(n, device=means3d.device)
        visible = on[:, 0]
        ctx.mark_non_differentiable(ids, radii, visible)
        ctx.view = view
        ctx.save_for_backward(on, *saved)
        return ids, means2d, conics, depths, radii, visible

    @staticmethod
    def backward(ctx, _g_ids, g_m2d, g_con, g_depth, _g_radii, _g_visible):  # type: ignore[override]
        on, *saved = ctx.saved_tensors
        grads = _ewa_backward(saved, ctx.view, g_m2d, g_con, g_depth)
        # a culled row's intermediates may be anything (a zero quaternion, a placeholder depth):
        # its gradients are 0 whatever they hold
        return tuple(torch.where(on, g, 0.0) for g in grads) + (None, None, None)


_JIT = cpu_extension("smgs_projection_cpu", [_CSRC / "projection_cpu.cpp"], "projection kernel")


def fused_available() -> bool:
    """Whether the compiled CPU projection can be used here (builds it on first call; a failed build raises ``BuildError``)."""
    return _JIT.is_available()


class _ProjectCPU(torch.autograd.Function):
    """``_Project`` in one compiled pass each way, float32 CPU tensors, with the colours of ``ShColours``
    (``sh0``, ``rest``: an empty tensor where there is none) for the kept rows where ``sh0`` is given.
    The backward recomputes the per-Gaussian intermediates, so only the inputs and ``ids`` are saved;
    gradients the loss did not reach are not made (``set_materialize_grads(False)``) but read as zero."""

    @staticmethod
    def forward(ctx, means3d, quats, scales, view: torch.Tensor, near_plane: float, eps2d: float,  # type: ignore[override]
                sh0: torch.Tensor, rest: torch.Tensor, degree: int, clamp: bool):
        with kernel("projection+SH fwd"):
            ids, means2d, conics, depths, radii, colors = _JIT.module().forward(
                means3d, quats, scales, view, near_plane, eps2d, K.SIGMA_EXTENT, sh0, rest, degree, clamp)
        ctx.mark_non_differentiable(ids, radii)
        ctx.save_for_backward(means3d, quats, scales, ids, view, sh0, rest)
        ctx.args = (near_plane, eps2d)
        ctx.sh = (degree, clamp)
        ctx.set_materialize_grads(False)   # no zero gradients made for ids, radii or unused outputs
        return ids, means2d, conics, depths, radii, colors

    @staticmethod
    @once_differentiable
    def backward(ctx, _g_ids, g_m2d, g_con, g_depth, _g_radii, g_col):  # type: ignore[override]
        means3d, quats, scales, ids, view, sh0, rest = ctx.saved_tensors
        none = means3d.new_empty(0)
        g = lambda t: none if t is None else t.contiguous()  # noqa: E731
        with kernel("projection+SH bwd"):
            g_means, g_quats, g_s, g_sh0, g_rest = _JIT.module().backward(
                means3d, quats, scales, view, *ctx.args, ids, g(g_m2d), g(g_con), g(g_depth), sh0, rest, *ctx.sh,
                g(g_col))
        has_sh = sh0.dim() == 3
        return (g_means, g_quats, g_s, None, None, None, g_sh0 if has_sh else None,
                g_rest if has_sh and rest.dim() == 3 else None, None, None)


def _colours_torch(sh: ShColours, means3d: torch.Tensor, ids: torch.Tensor, center: torch.Tensor,
                   dense: bool) -> torch.Tensor:
    """The colours of ``sh`` for the rows ``ids`` (every row where ``dense``) in PyTorch: the oracle's
    formula (``sh.eval_sh``), the path of other dtypes and devices."""
    coefs = sh.coefficients()
    if not dense:
        coefs, means3d = coefs.index_select(0, ids), means3d.index_select(0, ids)
    dirs = None
    if sh.degree > 0:   # degree 0 has no view dependence
        dirs = means3d - center
        dirs = dirs / dirs.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    colors = eval_sh(sh.degree, coefs, dirs) + 0.5
    return colors.clamp_min(0.0) if sh.clamp else colors


def project_gaussians(means3d: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor,
                      camera: Camera, near_plane: float = K.NEAR_PLANE,
                      eps2d: float = K.EPS2D, fused: bool | None = None,
                      view: torch.Tensor | None = None, dense: bool = False,
                      sh: ShColours | None = None) -> Projected:
    """EWA splatting (Zwicker et al.; 3DGS): Σ2D = J W Σ Wᵀ Jᵀ + eps2d·I.

    Culls Gaussians in front of the near plane and those whose 3σ box misses the image (the box
    is exact for the ellipse, so culling never changes an image). As in 3DGS, the Jacobian is
    evaluated at the mean clamped to 1.3× the field of view, which keeps far off-axis splats from
    exploding.

    ``fused``: None uses the compiled CPU pass wherever it applies (float32 CPU tensors, the
    extension available), True requires it (RuntimeError naming why not), False always uses the
    PyTorch path. ``view``: the camera already packed on the Gaussians' device (``host_view``, then
    ``to_device``; with the centre where ``sh`` is given), else packed here. ``dense``: keep
    every Gaussian's row (``Projected.visible`` marks the survivors; the PyTorch path, for the lean
    glue of ``smgs.raster.device_glue``): no host synchronisation. ``sh``: the kept rows' colours
    too (``Projected.colors``), in the compiled pass where it runs.
    """
    if view is None:
        view = to_device(host_view(camera, means3d.dtype, center=sh is not None), means3d.device)
    if sh is not None and view.numel() <= VIEW_FLOATS:
        raise ValueError("project_gaussians: colours from SH need the camera centre in the packed view "
                         "(host_view(camera, dtype, center=True))")
    if dense:
        ids, means2d, conics, depths, radii, visible = _ProjectDense.apply(
            means3d, quats, scales, _view_of(view), float(near_plane), float(eps2d))
        colors = None if sh is None else _colours_torch(sh, means3d, ids, view[VIEW_FLOATS:], dense=True)
        return Projected(ids=ids, means2d=means2d, conics=conics, depths=depths, radii=radii, visible=visible,
                         colors=colors)
    tensors = (means3d, quats, scales) + (() if sh is None else tuple(t for t in (sh.sh0, sh.rest) if t is not None))
    if use_cpu_kernel(_JIT, fused, tensors, "means3d, quats, scales" + ("" if sh is None else " and SH coefficients")):
        none = means3d.new_empty(0)
        packed = view if sh is not None else view[:VIEW_FLOATS]
        sh_args = (none, none, 0, True) if sh is None else \
            (sh.sh0, none if sh.rest is None else sh.rest, int(sh.degree), bool(sh.clamp))
        ids, means2d, conics, depths, radii, colors = _ProjectCPU.apply(
            means3d, quats, scales, packed if packed.is_contiguous() else packed.contiguous(), float(near_plane),
            float(eps2d), *sh_args)
        return Projected(ids=ids, means2d=means2d, conics=conics, depths=depths, radii=radii,
                         colors=None if sh is None else colors)
    ids, means2d, conics, depths, radii = _Project.apply(means3d, quats, scales, _view_of(view), float(near_plane),
                                                         float(eps2d))
    colors = None if sh is None else _colours_torch(sh, means3d, ids, view[VIEW_FLOATS:], dense=False)
    return Projected(ids=ids, means2d=means2d, conics=conics, depths=depths, radii=radii, colors=colors)
