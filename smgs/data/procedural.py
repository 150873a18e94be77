"""A procedural 3D scene for the embedded default run and the tests (no download, a second to make).

Boxes with one flat colour per face, a sphere coloured by octant and a checkerboard ground square,
in front of a constant background, seen by a ring of cameras looking at the centre. Images are
ray cast analytically (not splatted), so the target has true sharp edges: each pixel is the box
filter of ``supersample``² ray samples, as a camera integrates over its pixel area, so only pixels
a boundary crosses mix colours. SfM-like points are hits of random pixel rays (hence on visible
surfaces) with a little position and colour noise. World: z up, metres-ish units.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np
import torch

from smgs.camera import Camera
from smgs.data.formats import SceneRequest
from smgs.data.images import MIN_SIDE
from smgs.data.scene import Scene, View, camera_extent, check_split, split_description, split_every
from smgs.ranges import Range

_EPS = 1e-9

# Rays: one origin o [3] (every ray of a camera starts at its centre) and directions d [3, N], one
# contiguous row per axis. Row-wise arithmetic on 1-D arrays is several times faster in numpy than
# [N, 3] columns or BLAS [N,3]x[3,3] products (whose threads crawl when the cores are busy).


@dataclass
class Box:
    """An oriented box (yaw about z); face order: -x, +x, -y, +y, -z, +z (local axes)."""

    center: np.ndarray
    half: np.ndarray
    yaw: float
    colors: np.ndarray  # [6, 3] in [0, 1]

    def _rot(self) -> np.ndarray:
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])  # local -> world

    def intersect(self, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Entry distance (inf on miss) and face index, for rays starting outside the box."""
        R = self._rot()
        ol = R.T @ (o - self.center)
        t0 = np.full(d.shape[1], -np.inf)
        t_exit = np.full(d.shape[1], np.inf)
        axis = np.zeros(d.shape[1], dtype=np.int64)
        plus = np.zeros(d.shape[1], dtype=bool)
        for a in range(3):  # slab test per local axis
            da = R[0, a] * d[0] + R[1, a] * d[1] + R[2, a] * d[2]
            da = np.where(np.abs(da) < _EPS, _EPS, da)
            t1, t2 = (-self.half[a] - ol[a]) / da, (self.half[a] - ol[a]) / da
            near, far = np.minimum(t1, t2), np.maximum(t1, t2)
            better = near > t0
            t0 = np.where(better, near, t0)
            axis = np.where(better, a, axis)
            plus = np.where(better, da < 0, plus)  # moving towards -axis: enters the + face
            t_exit = np.minimum(t_exit, far)
        t = np.where((t0 <= t_exit) & (t0 > 0), t0, np.inf)
        return t, 2 * axis + plus

    def color(self, face: np.ndarray) -> np.ndarray:
        return self.colors[face]

    def distance(self, p: np.ndarray) -> np.ndarray:
        """Unsigned distance of points [N, 3] to the box surface."""
        q = np.abs((p - self.center) @ self._rot()) - self.half
        outside = np.linalg.norm(np.maximum(q, 0), axis=1)
        inside = np.minimum(q.max(axis=1), 0)
        return np.abs(outside + inside)


@dataclass
class Sphere:
    """A sphere whose eight octants (by the sign of the normal) have their own flat colour."""

    center: np.ndarray
    radius: float
    colors: np.ndarray  # [8, 3]

    def intersect(self, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        oc = o - self.center
        b = oc[0] * d[0] + oc[1] * d[1] + oc[2] * d[2]
        disc = b * b - (oc @ oc - self.radius ** 2)
        t = -b - np.sqrt(np.maximum(disc, 0))
        t = np.where((disc >= 0) & (t > 0), t, np.inf)
        tt = np.where(np.isfinite(t), t, 0)
        octant = 4 * (oc[0] + tt * d[0] > 0) + 2 * (oc[1] + tt * d[1] > 0) + (oc[2] + tt * d[2] > 0)
        return t, octant

    def color(self, face: np.ndarray) -> np.ndarray:
        return self.colors[face]

    def distance(self, p: np.ndarray) -> np.ndarray:
        return np.abs(np.linalg.norm(p - self.center, axis=1) - self.radius)


@dataclass
class Ground:
    """The square |x|, |y| <= half at z = 0, a two-colour checkerboard of ``cell``-sized squares."""

    half: float
    cell: float
    colors: np.ndarray  # [2, 3]

    def intersect(self, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        dz = np.where(np.abs(d[2]) < _EPS, -_EPS, d[2])
        t = -o[2] / dz
        x, y = o[0] + t * d[0], o[1] + t * d[1]
        ok = (t > 0) & (np.abs(x) <= self.half) & (np.abs(y) <= self.half)
        checker = (np.floor(x / self.cell) + np.floor(y / self.cell)).astype(np.int64) % 2
        return np.where(ok, t, np.inf), checker

    def color(self, face: np.ndarray) -> np.ndarray:
        return self.colors[face]

    def distance(self, p: np.ndarray) -> np.ndarray:
        dx = np.maximum(np.abs(p[:, :2]) - self.half, 0)
        return np.sqrt((dx ** 2).sum(1) + p[:, 2] ** 2)


@dataclass
class ProceduralWorld:
    objects: list
    background: np.ndarray
    names: list[str] = field(default_factory=list)

    def cast(self, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Nearest hit of the rays o [3] + t d [3, N] (d unit): distance (inf on miss), object
        index (-1 on miss), face index within the object (a flat-colour region), colour [N, 3]."""
        n = d.shape[1]
        best = np.full(n, np.inf)
        obj = np.full(n, -1)
        face = np.zeros(n, dtype=np.int64)
        for k, ob in enumerate(self.objects):
            t, f = ob.intersect(o, d)
            closer = t < best
            best = np.where(closer, t, best)
            obj = np.where(closer, k, obj)
            face = np.where(closer, f, face)
        rgb = np.empty((n, 3))
        rgb[:] = self.background
        for k, ob in enumerate(self.objects):
            m = obj == k
            rgb[m] = ob.color(face[m])
        return best, obj, face, rgb

    def distance(self, p: np.ndarray) -> np.ndarray:
        """Distance of points [N, 3] to the nearest surface."""
        return np.min(np.stack([ob.distance(p) for ob in self.objects]), axis=0)


def make_world(seed: int = 0) -> ProceduralWorld:
    """The default layout, its colours and positions jittered a little by ``seed``."""
    rng = np.random.default_rng(seed)

    def col(c):  # saturated but not clipped, so noise and supersampling stay inside [0, 1]
        return np.clip(np.asarray(c, dtype=np.float64) + rng.uniform(-0.04, 0.04, np.shape(c)), 0.03, 0.97)

    def jit(v, s=0.05):
        return np.asarray(v, dtype=np.float64) + rng.uniform(-s, s, 3) * np.array([1, 1, 0])

    objects = [
        Ground(half=2.4, cell=0.6, colors=col([[0.82, 0.80, 0.74], [0.35, 0.38, 0.42]])),
        Box(jit([-0.65, -0.35, 0.35]), np.array([0.35, 0.35, 0.35]), math.radians(25) + rng.uniform(-0.1, 0.1),
            col([[0.85, 0.15, 0.12], [0.95, 0.55, 0.10], [0.90, 0.85, 0.15], [0.55, 0.10, 0.10],
                 [0.30, 0.05, 0.05], [0.98, 0.70, 0.60]])),
        Box(jit([0.65, 0.45, 0.25]), np.array([0.45, 0.2, 0.25]), math.radians(-15) + rng.uniform(-0.1, 0.1),
            col([[0.10, 0.30, 0.85], [0.15, 0.65, 0.90], [0.05, 0.15, 0.45], [0.45, 0.40, 0.90],
                 [0.05, 0.05, 0.25], [0.70, 0.85, 0.98]])),
        Box(jit([0.35, -0.75, 0.5]), np.array([0.15, 0.15, 0.5]), math.radians(40),
            col([[0.10, 0.60, 0.20], [0.50, 0.85, 0.30], [0.05, 0.35, 0.15], [0.75, 0.95, 0.55],
                 [0.02, 0.20, 0.05], [0.90, 0.95, 0.40]])),
        Sphere(jit([-0.3, 0.75, 0.4]), 0.4,
               col([[0.60, 0.20, 0.70], [0.95, 0.95, 0.95], [0.20, 0.80, 0.75], [0.95, 0.40, 0.65],
                    [0.15, 0.15, 0.15], [0.85, 0.75, 0.30], [0.35, 0.25, 0.90], [0.65, 0.95, 0.85]])),
    ]
    return ProceduralWorld(objects, background=np.array([0.62, 0.72, 0.86]),
                           names=["ground", "box_red", "box_blue", "pillar_green", "sphere"])


def ring_cameras(n: int, width: int, height: int, radius: float = 3.4, height_mean: float = 1.7,
                 height_amp: float = 0.35, target=(0.0, 0.0, 0.3), phase: float = 0.0,
                 fov_x_deg: float = 50.0) -> list[Camera]:
    """``n`` cameras on a ring around the z axis looking at ``target``; their height oscillates
    (three periods per turn) so the views are not coplanar, which SfM-like point sampling and
    multi-view fitting both like."""
    fx = 0.5 * width / math.tan(math.radians(fov_x_deg) / 2)
    cams = []
    for i in range(n):
        a = phase + 2 * math.pi * i / n
        eye = (radius * math.cos(a), radius * math.sin(a), height_mean + height_amp * math.sin(3 * a))
        cams.append(Camera.look_at(eye, target, (0.0, 0.0, 1.0), fx=fx, fy=fx, width=width, height=height))
    return cams


def _pixel_rays(cam: Camera, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Origin [3] and unit directions [3, N] through image points (u, v) (pixel units; pixel (i, j)
    spans [i, i+1) x [j, j+1))."""
    K = cam.K.double().numpy()
    x, y = (u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1]
    c2w = cam.camtoworld.double().numpy()
    R = c2w[:3, :3]
    d = np.stack([R[i, 0] * x + R[i, 1] * y + R[i, 2] for i in range(3)])
    d /= np.sqrt(d[0] ** 2 + d[1] ** 2 + d[2] ** 2)
    return c2w[:3, 3].copy(), d


def render_view(world: ProceduralWorld, cam: Camera, supersample: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """uint8 image [H, W, 3] and the object index at each pixel centre ([H, W], -1 = background).

    A pixel whose centre and four corners hit the same flat-colour region takes that colour; the
    others (those a boundary crosses) are the mean of ``supersample``² stratified samples, i.e. a
    box filter over the pixel as a camera sensor integrates. Same image as supersampling every
    pixel unless a feature fits between a pixel's corners and centre; 3-4x fewer rays.
    """
    w, h = cam.width, cam.height
    uc, vc = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    _, obj_c, face_c, rgb_c = world.cast(*_pixel_rays(cam, uc.ravel(), vc.ravel()))
    key_c = (obj_c * 64 + face_c).reshape(h, w)
    uk, vk = np.meshgrid(np.arange(w + 1.0), np.arange(h + 1.0))
    _, obj_k, face_k, _ = world.cast(*_pixel_rays(cam, uk.ravel(), vk.ravel()))
    key_k = (obj_k * 64 + face_k).reshape(h + 1, w + 1)
    uniform = ((key_k[:-1, :-1] == key_c) & (key_k[1:, :-1] == key_c)
               & (key_k[:-1, 1:] == key_c) & (key_k[1:, 1:] == key_c))
    img = rgb_c.reshape(h, w, 3).copy()
    if supersample > 1 and not uniform.all():
        jj, ii = np.nonzero(~uniform)
        off = (np.arange(supersample) + 0.5) / supersample
        ou, ov = (a.ravel() for a in np.meshgrid(off, off))
        u = (ii[:, None] + ou[None, :]).ravel()
        v = (jj[:, None] + ov[None, :]).ravel()
        _, _, _, rgb = world.cast(*_pixel_rays(cam, u, v))
        img[jj, ii] = rgb.reshape(len(ii), -1, 3).mean(1)
    return np.round(img * 255).astype(np.uint8), obj_c.reshape(h, w)


def sample_points(world: ProceduralWorld, cams: list[Camera], n_points: int, rng: np.random.Generator,
                  pos_noise: float, color_noise: float) -> tuple[np.ndarray, np.ndarray]:
    """Surface points hit by random pixel rays of the cameras (visible by construction), with noise."""
    pts, cols = [], []
    per = math.ceil(2 * n_points / len(cams))  # some rays hit the background
    for cam in cams:
        u = rng.uniform(0, cam.width, per)
        v = rng.uniform(0, cam.height, per)
        o, d = _pixel_rays(cam, u, v)
        t, obj, _, rgb = world.cast(o, d)
        hit = obj >= 0
        pts.append(o + t[hit, None] * d[:, hit].T)
        cols.append(rgb[hit])
    p, c = np.concatenate(pts), np.concatenate(cols)
    keep = rng.permutation(len(p))[:n_points]
    p = p[keep] + rng.normal(0, pos_noise, (len(keep), 3))
    c = np.clip(c[keep] + rng.normal(0, color_noise, (len(keep), 3)), 0, 1)
    return p, c


def view_name(i: int) -> str:
    return f"view_{i:03d}"


def check_procedural_split(n_views: int, test_every: int | None) -> None:
    """The procedural scene's hold-out leaves a view to train on (``check_split``)."""
    tr, _ = split_every([view_name(i) for i in range(n_views)], test_every)
    check_split(f"the procedural scene (dataset.n_views={n_views})", n_views, len(tr), split_description(test_every))


def make_procedural_scene(n_views: int = 24, size: tuple[int, int] = (128, 96), seed: int = 0,
                          test_every: int | None = 8, n_points: int = 3000, supersample: int = 3,
                          n_trajectory: int = 48, pos_noise: float = 0.01, color_noise: float = 0.03) -> Scene:
    """The procedural scene: ``n_views`` ring cameras of ``size`` = (width, height), every
    ``test_every``-th (name-sorted) view held out, ``n_points`` SfM-like points, and a video
    trajectory of ``n_trajectory`` cameras on a ring between the training views' heights."""
    if n_views < 2:
        raise ValueError(f"n_views must be >= 2, got {n_views}")
    check_procedural_split(n_views, test_every)
    width, height = int(size[0]), int(size[1])
    world = make_world(seed)
    rng = np.random.default_rng(seed + 1)
    cams = ring_cameras(n_views, width, height)
    views = []
    for i, cam in enumerate(cams):
        img, _ = render_view(world, cam, supersample)
        views.append(View(cam, torch.from_numpy(img), view_name(i)))
    tr, te = split_every([v.name for v in views], test_every)
    pts, cols = sample_points(world, cams, n_points, rng, pos_noise, color_noise)
    traj = ring_cameras(n_trajectory, width, height, height_amp=0.0, phase=math.pi / n_views) if n_trajectory else None
    train = [views[i] for i in tr]
    meta = {
        "loader": "procedural",
        "dataset": "procedural",
        "scene": f"procedural_s{seed}",
        "source": "smgs.data.procedural (generated, no download)",
        "rule": "procedural",
        "rule_label": "procedural scene, rendered at its native size",
        "image_size": [width, height],
        "downscale_factor": 1.0,
        "resampling": f"analytic ray casting, {supersample}x{supersample} samples per pixel (box filter)",
        "split": split_description(test_every),
        "test_every": test_every,
        "n_images": len(views),
        "n_train": len(train),
        "n_test": len(te),
        "n_points": int(len(pts)),
        "point_noise": {"position_std": pos_noise, "color_std": color_noise},
        "objects": world.names,
        "seed": seed,
    }
    return Scene(name=meta["scene"], train=train, test=[views[i] for i in te],
                 extent=camera_extent([v.camera for v in train]),
                 points=torch.from_numpy(pts).float(), point_colors=torch.from_numpy(cols).float(),
                 background=torch.tensor(world.background, dtype=torch.float32), trajectory=traj, meta=meta)


@dataclass(frozen=True)
class ProceduralFormat:
    """The procedural scene as a scene format (``kind: procedural``): ``n_views`` ring cameras of
    ``width`` x ``height`` px, made from ``seed``; one scene, whatever its name."""

    n_views: int = 24
    width: int = 128
    height: int = 96
    seed: int = 0

    RANGES: ClassVar[dict[str, Range]] = {"n_views": Range(2, integer=True), "width": Range(MIN_SIDE, integer=True),
                                          "height": Range(MIN_SIDE, integer=True), "seed": Range(0, integer=True)}

    def inputs(self, request: SceneRequest) -> list:
        """No file: the scene is made from the config alone."""
        return []

    def load(self, request: SceneRequest) -> Scene:
        return make_procedural_scene(n_views=self.n_views, size=(self.width, self.height), seed=self.seed,
                                     test_every=request.test_every)

    def check(self, request: SceneRequest) -> None:
        check_procedural_split(self.n_views, request.test_every)
