"""Popping measured where it happens: synthetic depth-order flips and the frame-to-frame change at
the flip (issue: the averaged flow-warped MSE/FLIP of Table 4 dilutes popping, since the frames
where a depth order flips are a small share of all pairs).

Each scene is a few flat Gaussians (scale 0 along their normal) seen from a camera that orbits the
origin about the image's vertical axis, from -``max_deg`` to +``max_deg`` in ``n_frames`` even
steps: the view depths of the splats' centres swap order exactly at 0°, between the two middle
frames (the flip; ``flip_pair`` finds it from the centres, and the scenes are built so that it is
there). A method's popping ratio is the change between the two frames at the flip divided by the
median change between the other consecutive frames; the change of a pair is the mean over pixels
of the squared difference summed over RGB (float frames, no quantisation). 1 = no pop; the smooth
orbit alone changes every pair about equally.

Scenes (every splat flat; colours distinct):
- ``coplanar_pair``: two overlapping discs on one plane, opacity 0.6;
- ``crossing_30``: two elongated splats on planes crossing at 30° (normals ±15° about the vertical),
  opacity 0.6: which one is in front differs per pixel, on either side of the crossing line;
- ``coplanar_four``: four overlapping discs on one plane, opacity 0.6;
- ``opaque_pair``: the coplanar pair at opacity 0.9;
- ``control``: two discs far apart in depth whose centres never swap (the ratio must be 1 ± noise).

Methods are fixed render settings of the one renderer (``PopMethod``), not trained models: the
same splats through each compositing rule.
"""

from __future__ import annotations

import math
from contextlib import contextmanager
import statistics
from dataclasses import dataclass, field

import torch

from smgs.camera import Camera
from smgs.raster import rasterize
from smgs.raster.projection import quat_to_rotmat


@dataclass(frozen=True)
class FlipScene:
    """Activated Gaussian parameters (float64) and what the scene shows."""

    name: str
    means: torch.Tensor       # [N, 3]
    quats: torch.Tensor       # [N, 4] wxyz
    scales: torch.Tensor      # [N, 3]
    opacities: torch.Tensor   # [N]
    colors: torch.Tensor      # [N, 3]
    description: str
    has_flip: bool = True


@dataclass(frozen=True)
class PopMethod:
    """A compositing rule applied to fixed splats: render mode, order and the per-splat α, β, γ."""

    name: str
    mode: str
    sort: str = "global"
    alpha: float = 1.0
    beta: float = 0.0
    gamma: float = 0.0


POP_METHODS: tuple[PopMethod, ...] = (
    PopMethod("3dgs", "3dgs"),
    PopMethod("stopthepop", "3dgs", "per_pixel"),
    PopMethod("gef_only", "gef_only", alpha=2.0),
    PopMethod("softmax_only", "softmax_only", beta=5.0, gamma=1.0),
    PopMethod("softmax_gs", "softmax_gs", alpha=2.0, beta=5.0, gamma=1.0),
    PopMethod("softmax_gs+per_pixel", "softmax_gs", "per_pixel", alpha=2.0, beta=5.0, gamma=1.0),
    PopMethod("softmax_only β30", "softmax_only", beta=30.0, gamma=1.0),
)


def _about_y(deg: float) -> list[float]:
    h = math.radians(deg) / 2
    return [math.cos(h), 0.0, math.sin(h), 0.0]


def _scene(name, means, quats, scales, opacity, colors, description, has_flip=True) -> FlipScene:
    t = lambda x: torch.tensor(x, dtype=torch.float64)  # noqa: E731
    n = len(means)
    return FlipScene(name, t(means), t(quats), t(scales), torch.full((n,), float(opacity), dtype=torch.float64),
                     t(colors), description, has_flip)


RED, BLUE, GREEN, YELLOW = [1.0, 0.1, 0.1], [0.1, 0.2, 1.0], [0.1, 0.9, 0.2], [0.95, 0.85, 0.1]


def flip_scenes() -> dict[str, FlipScene]:
    """The four flip scenes and the control, by name (module docstring)."""
    flat = [0.5, 0.5, 0.0]
    ident = [1.0, 0.0, 0.0, 0.0]
    # crossing planes: normals at ±15° about y, centres 0.3 apart along each plane, long along it
    ua = [math.cos(math.radians(15)), 0.0, -math.sin(math.radians(15))]
    ub = [math.cos(math.radians(-15)), 0.0, -math.sin(math.radians(-15))]
    scenes = [
        _scene("coplanar_pair", [[-0.3, 0, 0], [0.3, 0, 0]], [ident] * 2, [flat] * 2, 0.6, [RED, BLUE],
               "two coplanar discs, opacity 0.6"),
        _scene("crossing_30", [[-0.3 * c for c in ua], [0.3 * c for c in ub]], [_about_y(15), _about_y(-15)],
               [[0.9, 0.3, 0.0]] * 2, 0.6, [RED, BLUE], "two elongated splats on planes crossing at 30°, opacity 0.6"),
        _scene("coplanar_four", [[-0.45, 0, 0], [-0.15, 0, 0], [0.15, 0, 0], [0.45, 0, 0]], [ident] * 4, [flat] * 4,
               0.6, [RED, GREEN, BLUE, YELLOW], "four coplanar discs of distinct colours, opacity 0.6"),
        _scene("opaque_pair", [[-0.3, 0, 0], [0.3, 0, 0]], [ident] * 2, [flat] * 2, 0.9, [RED, BLUE],
               "two coplanar discs, opacity 0.9"),
        _scene("control", [[-0.3, 0, -0.6], [0.3, 0, 0.6]], [ident] * 2, [flat] * 2, 0.6, [RED, BLUE],
               "two discs 1.2 apart in depth: no flip", has_flip=False),
    ]
    return {s.name: s for s in scenes}


def orbit_path(n_frames: int = 40, max_deg: float = 10.0, radius: float = 4.0, width: int = 64, height: int = 48,
               focal: float = 60.0) -> list[Camera]:
    """Cameras on a circle of ``radius`` about the origin in the x-z plane, looking at the origin,
    from -max_deg to +max_deg; with an even ``n_frames`` 0° lies between the two middle frames.
    float64 matrices, the rotation orthonormal to float64 rounding."""
    if n_frames < 4 or n_frames % 2:
        raise ValueError(f"n_frames must be even and >= 4 (0° between the middle frames), got {n_frames}")
    cams = []
    for k in range(n_frames):
        th = math.radians(max_deg * (2 * k / (n_frames - 1) - 1))
        R = quat_to_rotmat(torch.tensor(_about_y(-math.degrees(th)), dtype=torch.float64))  # world -> camera
        V = torch.eye(4, dtype=torch.float64)
        V[:3, :3] = R
        V[:3, 3] = torch.tensor([0.0, 0.0, radius], dtype=torch.float64)   # the origin at depth `radius`
        K = torch.tensor([[focal, 0, width / 2], [0, focal, height / 2], [0, 0, 1]], dtype=torch.float64)
        cams.append(Camera(K, V, width, height))
    return cams


def centre_order(scene: FlipScene, camera: Camera) -> list[int]:
    """The global sort's order: splats by the view depth of their centres (ties by index)."""
    V = camera.viewmat.double()
    z = scene.means @ V[2, :3] + V[2, 3]
    return torch.sort(z, stable=True).indices.tolist()


def flip_pair(scene: FlipScene, cameras: list[Camera]) -> int | None:
    """k such that the centres' depth order differs between frames k and k+1 (the only such k), or
    None where it never changes; more than one change is an error (the ratio needs one flip)."""
    orders = [centre_order(scene, c) for c in cameras]
    ks = [k for k in range(len(orders) - 1) if orders[k] != orders[k + 1]]
    if len(ks) > 1:
        raise ValueError(f"scene {scene.name!r}: the centre order changes {len(ks)} times along the path "
                         f"(pairs {ks}); shorten the path so that it crosses one flip")
    return ks[0] if ks else None


def render_frames(scene: FlipScene, method: PopMethod, cameras: list[Camera],
                  backend: str = "reference") -> list[torch.Tensor]:
    """[H, W, 3] float64 frames of ``scene`` through ``method`` along ``cameras``, black background."""
    n = scene.means.shape[0]
    full = lambda v: torch.full((n,), v, dtype=torch.float64)  # noqa: E731
    frames = []
    for cam in cameras:
        out = rasterize(scene.means, scene.quats, scene.scales, scene.opacities, scene.colors, cam,
                        alpha=full(method.alpha), beta=full(method.beta), gamma=full(method.gamma),
                        mode=method.mode, sort=method.sort, backend=backend)
        frames.append(out.rgb.detach())
    return frames


def frame_changes(frames: list[torch.Tensor]) -> list[float]:
    """Per consecutive pair: the mean over pixels of the squared difference summed over channels."""
    return [float(((b - a) ** 2).sum(-1).mean()) for a, b in zip(frames, frames[1:])]


@dataclass
class PopResult:
    scene: str
    method: str
    ratio: float             # change at the flip / median change elsewhere (inf where elsewhere is 0)
    at_flip: float
    elsewhere: float
    flip_index: int          # the pair (k, k+1) of the flip
    changes: list[float] = field(default_factory=list)


def popping_ratio(changes: list[float], flip_index: int) -> tuple[float, float, float]:
    """(ratio, change at the flip, median of the other changes)."""
    if not 0 <= flip_index < len(changes) or len(changes) < 2:
        raise ValueError(f"flip pair {flip_index} is not one of the {len(changes)} consecutive pairs")
    at, med = changes[flip_index], statistics.median(changes[:flip_index] + changes[flip_index + 1:])
    ratio = at / med if med > 0 else (1.0 if at == 0 else math.inf)
    return ratio, at, med


def popping_table(scenes: dict[str, FlipScene] | None = None, methods: tuple[PopMethod, ...] = POP_METHODS,
                  cameras: list[Camera] | None = None, backend: str = "reference",
                  keep_frames: bool = False) -> tuple[list[PopResult], dict[tuple[str, str], list[torch.Tensor]]]:
    """The popping ratio of every method on every scene (and, with ``keep_frames``, the frames by
    (scene, method)). The flip pair is the path's middle pair for every scene (the control's too:
    its ratio there must be 1 ± noise); a flip scene whose centres do not swap there is an error."""
    scenes = flip_scenes() if scenes is None else scenes
    cameras = orbit_path() if cameras is None else cameras
    with _one_thread():
        return _table(scenes, methods, cameras, backend, keep_frames)


@contextmanager
def _one_thread():
    """Renders of a few splats at 64x48 are per-op overhead: more threads only wait on each other
    (3 s on one thread, over a minute on two busy cores). The caller's setting comes back after."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(n)


def _table(scenes, methods, cameras, backend, keep_frames):
    middle = len(cameras) // 2 - 1
    results, kept = [], {}
    for s in scenes.values():
        k = flip_pair(s, cameras)
        if s.has_flip and k != middle:
            raise ValueError(f"scene {s.name!r}: its centres swap at pair {k}, not at the path's middle {middle}")
        if not s.has_flip and k is not None:
            raise ValueError(f"control scene {s.name!r}: its centres swap at pair {k}")
        for m in methods:
            frames = render_frames(s, m, cameras, backend)
            changes = frame_changes(frames)
            ratio, at, med = popping_ratio(changes, middle)
            results.append(PopResult(s.name, m.name, ratio, at, med, middle, changes))
            if keep_frames:
                kept[(s.name, m.name)] = frames
    return results, kept
