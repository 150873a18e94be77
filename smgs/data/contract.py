"""The scene contract: what every ``Scene`` passes after its format's ``load`` and before a method sees
it, whatever the format, built-in or plug-in (docs/adding-a-scene-format.md, "What the harness checks").

The formats' own checks (``check(request)``: which file, which line) refuse what they can name early,
before a pixel is decoded; this is the net under all of them, on what ``load`` returned: a ``Scene``
of ``View`` objects; images at least ``MIN_SIDE`` px a side, shaped as their cameras say; view names
unique after path normalisation (``view_key``), and test views' render files too; finite intrinsics
with an angle of view within ``FIELD_OF_VIEW_DEG``; finite, normalised poses (a rotation and a
translation); a view to train on, and one to test on where the run scores test views.
"""

from __future__ import annotations

import math
from pathlib import PurePosixPath
from typing import Any

import torch

from smgs.camera import Camera
from smgs.data.images import MIN_SIDE, field_of_view_problem
from smgs.data.errors import SceneContractError
from smgs.data.scene import Scene, View, view_key

POSE_TOLERANCE = 1e-3
"""How far a view's rotation may be from orthonormal (``|RᵀR − I|``, element-wise): float32 poses
are ~1e-7 off; a scaled or sheared matrix is no camera pose (the transforms.json loader's bound)."""

SHOWN = 5
"""Problems listed in one error; the count of the others follows."""

GUIDE = "docs/adding-a-scene-format.md#what-the-harness-checks"


def check_scene_contract(scene: Any, where: str, needs_test: bool = True) -> Scene:
    """``scene`` if it keeps the contract (the module's docstring), else ``SceneContractError``
    naming ``where`` (the format and the scene it was asked for) and every problem (the first
    ``SHOWN``). ``needs_test``: the run scores test views (a hold-out was asked for)."""
    if not isinstance(scene, Scene):
        raise SceneContractError(f"{where}: load returned {_kind(scene)}, not a smgs.data.Scene; a scene format's "
                                 f"load(request) returns a Scene of View objects ({GUIDE})")
    problems = _list_problems(scene, "train") + _list_problems(scene, "test")
    if not problems:
        problems = _split_problems(scene, needs_test) + _name_problems(scene) + _grouped(_views(scene)) \
            + _scene_problems(scene)
    if problems:
        more = f"; and {len(problems) - SHOWN} more" if len(problems) > SHOWN else ""
        raise SceneContractError(f"{where} breaks the scene contract ({GUIDE}): " + "; ".join(problems[:SHOWN]) + more)
    return scene


def _kind(x: Any) -> str:
    return "None" if x is None else f"a {type(x).__name__}"


def _views(scene: Scene) -> list[View]:
    """Every view once (a flat scene may list its one view as train and test)."""
    out, seen = [], set()
    for v in [*scene.train, *scene.test]:
        if id(v) not in seen:
            seen.add(id(v))
            out.append(v)
    return out


def _list_problems(scene: Scene, part: str) -> list[str]:
    views = getattr(scene, part)
    if not isinstance(views, (list, tuple)):
        return [f"scene.{part} is {_kind(views)}, not a list of smgs.data.View"]
    return [f"scene.{part}[{i}] is {_kind(v)}, not a smgs.data.View" for i, v in enumerate(views)
            if not isinstance(v, View)][:SHOWN]


def _split_problems(scene: Scene, needs_test: bool) -> list[str]:
    out = []
    if not scene.train:
        out.append("no view to train on (scene.train is empty)")
    if needs_test and not scene.test:
        out.append("no test view, and the run scores test views: hold out every n-th view as the request asks "
                   "(request.test_every; smgs.data.split_every does it)")
    return out


def _name_problems(scene: Scene) -> list[str]:
    """Names unique across the scene after normalisation (``view_key``); test views' render files
    (their stems) unique. A flat scene's one view may be both its train and its test view (a 2D
    target, scored on itself: ``smgs.data.patterns``)."""
    out = []
    first: dict[str, tuple[View, str]] = {}
    for v, part in [(v, "train") for v in scene.train] + [(v, "test") for v in scene.test]:
        key = view_key(v.name)
        if key not in first:
            first[key] = (v, part)
            continue
        seen, seen_part = first[key]
        if seen is v and seen_part != part and scene.flat:
            continue
        if seen is not v:
            what = f"views {seen.name!r} and {v.name!r} are one name ({key})"
        elif seen_part != part:
            what = f"view {v.name!r} is both a training and a test view"
        else:
            what = f"view {v.name!r} is listed twice in scene.{part}"
        out.append(f"{what}: one image would count as two views, and a test view's copy may train; give each "
                   "view its own name and hold test views out of training")
    stems: dict[str, View] = {}
    for v in scene.test:   # their renders are saved as renders/<stem>.png (protocols.train_loop)
        stem = PurePosixPath(view_key(v.name)).stem
        other = stems.setdefault(stem, v)
        if view_key(other.name) != view_key(v.name):   # (one name twice is said above)
            out.append(f"test views {other.name!r} and {v.name!r} would write one render file "
                       f"(renders/{stem}.png); give them names with different stems")
    return out


def _grouped(views: list[View]) -> list[str]:
    """Each view's problems, one line per problem with the views that have it (the first few named)."""
    by_problem: dict[str, list[str]] = {}
    for v in sorted(views, key=lambda v: view_key(v.name)):
        for problem in _view_problems(v):
            by_problem.setdefault(problem, []).append(repr(v.name))
    out = []
    for problem, names in by_problem.items():
        more = f" and {len(names) - 3} more" if len(names) > 3 else ""
        out.append(f"view{'s' if len(names) > 1 else ''} {', '.join(names[:3])}{more}: {problem}")
    return out


def _view_problems(v: View) -> list[str]:
    """What is wrong with one view (each problem without the view's name: ``_grouped`` adds it)."""
    cam = v.camera
    if not isinstance(cam, Camera):
        return [f"its camera is {_kind(cam)}, not a smgs.camera.Camera"]
    img = v.image
    if not isinstance(img, torch.Tensor) or img.ndim != 3 or img.shape[2] != 3:
        shape = tuple(img.shape) if isinstance(img, torch.Tensor) else _kind(img)
        return [f"its image is {shape}; a view's image is an RGB tensor [H, W, 3] (uint8, or float in [0, 1])"]
    h, w = int(img.shape[0]), int(img.shape[1])
    out = []
    if (w, h) != (cam.width, cam.height):
        out.append(f"its image is {w}x{h} px but its camera {cam.width}x{cam.height}; "
                   "scale the camera with the image (smgs.data.images.scale_intrinsics)")
    if min(w, h) < MIN_SIDE:
        out.append(f"{w}x{h} px, under the {MIN_SIDE} px a side that a score needs (one renderer tile; "
                   "SSIM's window is 11 px); load larger images")
    if img.is_floating_point() and not bool(torch.isfinite(img).all()):
        out.append("its image holds NaN or infinite values")
    return out + _intrinsics_problems(cam) + _pose_problems(cam)


def _intrinsics_problems(cam: Camera) -> list[str]:
    K = cam.K.detach().double().cpu()
    fx, fy, cx, cy = (float(K[i, j]) for i, j in ((0, 0), (1, 1), (0, 2), (1, 2)))
    if not all(math.isfinite(v) for v in (fx, fy, cx, cy)):
        return [f"its intrinsics (fx, fy, cx, cy) = ({fx:g}, {fy:g}, {cx:g}, {cy:g}) are not finite"]
    if fx <= 0 or fy <= 0:
        return [f"its focal length (fx, fy) = ({fx:g}, {fy:g}); a focal length is a positive number of pixels"]
    fov = field_of_view_problem(fx, fy, (cam.width, cam.height))
    return [fov] if fov else []


def _pose_problems(cam: Camera) -> list[str]:
    V = cam.viewmat.detach().double().cpu()
    if not bool(torch.isfinite(V).all()):
        return ["its pose (viewmat, world-to-camera) holds NaN or infinite values"]
    R = V[:3, :3]
    off = float((R.T @ R - torch.eye(3, dtype=R.dtype)).abs().max())
    det = float(torch.linalg.det(R))
    if off > POSE_TOLERANCE or det <= 0:
        return [f"its pose's rotation is no rotation (|RᵀR − I| up to {off:.3g}, det {det:.4g}): a scaled, "
                "sheared or mirrored matrix; a viewmat is [R t; 0 0 0 1] with R orthonormal, det +1"]
    if (V[3] - V.new_tensor([0.0, 0.0, 0.0, 1.0])).abs().max() > POSE_TOLERANCE:
        return [f"its pose's last row is {[round(float(x), 4) for x in V[3]]}, not [0, 0, 0, 1]"]
    return []


def _scene_problems(scene: Scene) -> list[str]:
    out = []
    try:
        extent = float(scene.extent)
    except (TypeError, ValueError):
        extent = math.nan
    if not (math.isfinite(extent) and extent > 0):
        out.append(f"scene.extent = {scene.extent!r}; it is the cameras' spread (smgs.data.camera_extent), a "
                   "positive number")
    pts = scene.points
    if pts is not None:
        if not isinstance(pts, torch.Tensor) or pts.ndim != 2 or pts.shape[1] != 3:
            out.append(f"scene.points is {tuple(pts.shape) if isinstance(pts, torch.Tensor) else _kind(pts)}; "
                       "SfM points are a tensor [M, 3]")
        elif not bool(torch.isfinite(pts).all()):
            out.append("scene.points holds NaN or infinite values")
        elif scene.point_colors is not None and tuple(scene.point_colors.shape) != tuple(pts.shape):
            out.append(f"scene.point_colors is {tuple(scene.point_colors.shape)}, the points {tuple(pts.shape)}")
    return out
