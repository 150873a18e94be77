"""Optical flow without learned weights, backward warping and the validity masks.

Convention: a flow lives on the *target* frame's pixel grid (frame i+step) and points into the
*source* frame (frame i): target pixel p shows what the source shows at p + flow(p). Warping the
source with it (``backward_warp``) gives the source seen from the target. Pixel index (x, y) has
its centre at (x + 0.5, y + 0.5) in ``Camera.K`` coordinates; ``cv2.remap`` addresses pixel
centres by index, so the two differ by 0.5 and the flow (a difference) is the same in both.

Estimators, each with its name and parameters in every result:
- ``geometric``: from the target's rendered depth and the known camera motion; exact for the
  rendered scene. Occlusion by a depth test against the source's rendered depth.
- ``opencv``: DIS (core OpenCV) at full resolution (finest scale 0) from the MEDIUM preset;
  ``opencv-deepflow``: DeepFlow from opencv-contrib (slower). Occlusion by the forward-backward
  test of Ruder et al. (GCPR 2016) as PoppingDetection applies it, with the polarity fixed
  (pixels where the test fires are *excluded*).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from smgs.camera import Camera

ESTIMATORS = ("geometric", "opencv", "opencv-deepflow")


@dataclass
class Flow:
    """flow [H, W, 2] (dx, dy) float32 on the target grid; valid [H, W]: where the estimator trusts
    it (not occluded, geometry present); name and parameters of the estimator."""

    flow: np.ndarray
    valid: np.ndarray
    estimator: str
    params: dict = field(default_factory=dict)


def pixel_grid(h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    return xs, ys


def backward_warp(source: np.ndarray, flow: np.ndarray, border_value: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Sample ``source`` [H, W, C] at p + flow(p) with bilinear ``cv2.remap`` (as PoppingDetection).

    Returns (warped [H, W, C], inside [H, W] bool): inside is true where all four bilinear taps
    lie in the source image (a ones channel warped along stays 1)."""
    h, w = flow.shape[:2]
    xs, ys = pixel_grid(h, w)
    map_x = np.ascontiguousarray(xs + flow[..., 0], dtype=np.float32)
    map_y = np.ascontiguousarray(ys + flow[..., 1], dtype=np.float32)
    src = np.asarray(source, dtype=np.float32)
    src = src[..., None] if src.ndim == 2 else src
    stacked = np.concatenate([src, np.ones(src.shape[:2] + (1,), np.float32)], axis=2)
    out = cv2.remap(stacked, map_x, map_y, interpolation=cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_CONSTANT, borderValue=border_value)
    out = out.reshape(h, w, -1)
    # remap's bilinear weights are fixed-point (1/32 px), so a fully inside sample gives exactly 1.
    inside = out[..., -1] >= 1.0 - 1e-4
    return out[..., :-1], inside


def border_mask(h: int, w: int, border: int) -> np.ndarray:
    """True except within ``border`` pixels of the image edge (PoppingDetection ignores 20 px)."""
    m = np.zeros((h, w), bool)
    if 2 * border < h and 2 * border < w:
        m[border:h - border, border:w - border] = True
    return m


def _np64(t) -> np.ndarray:
    return t.detach().double().cpu().numpy() if hasattr(t, "detach") else np.asarray(t, np.float64)


def geometric_flow(depth_target: np.ndarray, cam_target: Camera, cam_source: Camera,
                   depth_source: np.ndarray | None = None, rel_depth_tol: float = 0.02) -> Flow:
    """Flow from the target's depth (camera z, 0 where nothing was rendered) and the two cameras.

    A target pixel is valid when it has depth, lands in front of the source camera, and — given
    ``depth_source`` — the source's rendered depth there (bilinear) agrees with the reprojected
    depth within ``rel_depth_tol`` (relative); otherwise something else is in front (occlusion) or
    the surface is not seen. Bilinear sampling mixes depths across edges, so pixels next to a depth
    discontinuity fail the test too, which is what an occlusion mask should do there.
    """
    d = np.asarray(depth_target, dtype=np.float64)
    h, w = d.shape
    if (cam_target.height, cam_target.width) != (h, w):
        raise ValueError(f"depth is {w}x{h} but the target camera is {cam_target.width}x{cam_target.height}")
    Kt, Ks = _np64(cam_target.K), _np64(cam_source.K)
    Vt, Vs = _np64(cam_target.viewmat), _np64(cam_source.viewmat)
    xs, ys = pixel_grid(h, w)
    u, v = xs.astype(np.float64) + 0.5, ys.astype(np.float64) + 0.5
    has_depth = np.isfinite(d) & (d > 0)
    z = np.where(has_depth, d, 1.0)
    X = np.stack([(u - Kt[0, 2]) / Kt[0, 0] * z, (v - Kt[1, 2]) / Kt[1, 1] * z, z], -1)  # target camera
    T = Vs @ np.linalg.inv(Vt)  # target camera -> source camera
    Y = X @ T[:3, :3].T + T[:3, 3]
    zs = Y[..., 2]
    front = zs > 1e-6
    zs_safe = np.where(front, zs, 1.0)
    us = Ks[0, 0] * Y[..., 0] / zs_safe + Ks[0, 2]
    vs = Ks[1, 1] * Y[..., 1] / zs_safe + Ks[1, 2]
    flow = np.stack([us - u, vs - v], -1)
    valid = has_depth & front
    params: dict = {"rel_depth_tol": rel_depth_tol, "occlusion": "none"}
    if depth_source is not None:
        ds, inside = backward_warp(np.asarray(depth_source, np.float32), flow.astype(np.float32))
        ds = ds[..., 0].astype(np.float64)
        visible = inside & (ds > 0) & (np.abs(ds - zs) <= rel_depth_tol * np.abs(zs))
        valid &= visible
        params["occlusion"] = "depth_test"
    flow = np.where((has_depth & front)[..., None], flow, 0.0)  # no geometry: no flow
    return Flow(flow.astype(np.float32), valid, "geometric", params)


def _gray_u8(rgb: np.ndarray) -> np.ndarray:
    a = np.asarray(rgb)
    if a.dtype != np.uint8:
        a = (np.clip(a.astype(np.float32), 0, 1) * 255 + 0.5).astype(np.uint8)
    return cv2.cvtColor(np.ascontiguousarray(a[..., :3]), cv2.COLOR_RGB2GRAY)


def dis_params(dis) -> dict:
    return {"algorithm": "DIS", "preset": "MEDIUM", "finest_scale": dis.getFinestScale(),
            "patch_size": dis.getPatchSize(), "patch_stride": dis.getPatchStride(),
            "gd_iterations": dis.getGradientDescentIterations(),
            "vr_iterations": dis.getVariationalRefinementIterations(),
            "mean_normalization": bool(dis.getUseMeanNormalization()),
            "spatial_propagation": bool(dis.getUseSpatialPropagation()), "opencv": cv2.__version__}


def _make_flow_fn(method: str):
    if method == "opencv":
        dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
        dis.setFinestScale(0)  # full resolution: scale 1-2 presets estimate at 1/2-1/4 and upsample
        return (lambda a, b: dis.calc(a, b, None)), dis_params(dis)
    if method == "opencv-deepflow":
        if not hasattr(cv2, "optflow"):
            raise RuntimeError("DeepFlow needs opencv-contrib (cv2.optflow is missing)")
        df = cv2.optflow.createOptFlow_DeepFlow()
        return (lambda a, b: df.calc(a, b, None)), {"algorithm": "DeepFlow", "opencv": cv2.__version__}
    raise ValueError(f"unknown image-flow estimator {method!r}; expected 'opencv' or 'opencv-deepflow'")


def forward_backward_valid(flow_ts: np.ndarray, flow_st: np.ndarray) -> np.ndarray:
    """Ruder et al.'s consistency test on the target grid; True where the flow is trusted.

    Inconsistent: |f_ts + f_st(p + f_ts)|² > 0.01 (|f_ts|² + |f_st(p + f_ts)|²) + 0.5.
    Motion boundary: |∇f_ts|² > 0.01 |f_ts|² + 0.002.
    """
    st_w, _ = backward_warp(flow_st, flow_ts)
    s = flow_ts + st_w
    inconsistent = (s ** 2).sum(-1) > 0.01 * ((flow_ts ** 2).sum(-1) + (st_w ** 2).sum(-1)) + 0.5
    gy_u, gx_u = np.gradient(flow_ts[..., 0])
    gy_v, gx_v = np.gradient(flow_ts[..., 1])
    grad2 = gx_u ** 2 + gy_u ** 2 + gx_v ** 2 + gy_v ** 2
    boundary = grad2 > 0.01 * (flow_ts ** 2).sum(-1) + 0.002
    return ~(inconsistent | boundary)


def image_flow(rgb_target: np.ndarray, rgb_source: np.ndarray, method: str = "opencv",
               fb_check: bool = True) -> Flow:
    """Flow from the two images alone (target grid -> source), with the forward-backward test."""
    calc, params = _make_flow_fn(method)
    gt, gs = _gray_u8(rgb_target), _gray_u8(rgb_source)
    flow_ts = np.asarray(calc(gt, gs), dtype=np.float32)  # cv2: gt(p) ≈ gs(p + flow)
    if fb_check:
        flow_st = np.asarray(calc(gs, gt), dtype=np.float32)
        valid = forward_backward_valid(flow_ts, flow_st)
    else:
        valid = np.ones(flow_ts.shape[:2], bool)
    return Flow(flow_ts, valid, method, {**params, "forward_backward_check": fb_check})
