"""``transforms.json`` scenes (NeRF Blender synthetic, instant-ngp, nerfstudio).

Conventions handled:

- Intrinsics: ``fl_x, fl_y, cx, cy, w, h`` or ``camera_angle_x`` (and ``camera_angle_y``), global or
  per frame (a frame's keys override the global ones). ``fl_y`` falls back to ``camera_angle_y``
  then to ``fl_x`` (square pixels, as 3DGS's Blender reader); ``cx, cy`` default to the image
  centre; ``w, h`` to the size of the image file. ``cx, cy`` are taken in the COLMAP convention
  (top-left pixel centre at 0.5), which is what instant-ngp's colmap2nerf.py copies.
- Poses: ``transform_matrix`` is camera-to-world in the OpenGL/NeRF convention (+x right, +y up,
  looking down -z); the camera's y and z axes are flipped to get OpenCV, then inverted.
- Distortion: ``k1..k6, p1, p2`` (OpenCV order k1, k2, p1, p2, k3..k6). Non-zero coefficients are
  undistorted away with OpenCV (``cv2.getOptimalNewCameraMatrix`` with alpha=0, i.e. the same image
  size with every output pixel valid, then ``remap`` with bicubic interpolation) before any resize,
  and the meta says so; with ``undistort=False`` such a scene is refused. Fisheye models are refused.
- ``aabb_scale``, ``scale``, ``offset`` are instant-ngp's mapping of the world into its ray-marching
  unit cube. Splatting has no such cube and the metrics do not depend on the world's units (the
  learning rates use the camera extent), so the file's world coordinates are kept unchanged; the
  three values are recorded in the meta and not otherwise used.
- Splits: Blender's ``transforms_train.json`` / ``transforms_test.json`` (``val`` unused, as 3DGS),
  or nerfstudio's ``train_filenames`` / ``test_filenames``, else every 8th of the name-sorted frames.
- RGBA images (Blender) are composited on ``background`` (white by default, as the NeRF synthetic
  protocol) and ``scene.background`` is set.
- No SfM points: ``scene.points`` is None (methods initialise randomly).
"""

from __future__ import annotations

import json
import math
import threading
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

import numpy as np
import torch

from smgs.camera import Camera
from smgs.data.images import (ResolutionRule, check_aspect, check_min_size, check_pinhole, check_scene_scale,
                              describe_resampling, image_size, parallel_map, read_image, resize_image,
                              scale_intrinsics)
from smgs.data.rules import get_generic_rule
from smgs.data.scene import (DatasetNotFoundError, MissingImageError, Scene, SceneFormatError, View,
                             camera_extent, check_split, split_description, split_every)

LAYOUT = ("<scene>/transforms.json (instant-ngp / nerfstudio) or <scene>/transforms_{train,test}.json "
          "(Blender), with frames[].file_path relative to the json file")
DIST_KEYS = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")  # OpenCV's order
_INTRINSIC_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h", "camera_angle_x", "camera_angle_y", "camera_model",
                   "is_fisheye") + DIST_KEYS


def _read_json(p: Path) -> dict:
    try:
        with open(p) as f:
            d = json.load(f)
    except json.JSONDecodeError as e:
        raise SceneFormatError(f"corrupt transforms file {p}: {e}") from e
    if not isinstance(d, dict) or not isinstance(d.get("frames"), list) or not d["frames"]:
        raise SceneFormatError(f"transforms file {p} has no 'frames' list; expected {LAYOUT}")
    return d


def _find_transforms(path: Path) -> tuple[dict[str, dict], Path, dict[str, Path]]:
    """{split: json}, the base folder and {split: file}. split "all" means: no explicit split."""
    if path.is_file():
        return {"all": _read_json(path)}, path.parent, {"all": path}
    if not path.is_dir():
        raise DatasetNotFoundError(f"transforms scene {path} does not exist; expected {LAYOUT}")
    if (path / "transforms.json").is_file():
        return {"all": _read_json(path / "transforms.json")}, path, {"all": path / "transforms.json"}
    tr, te = path / "transforms_train.json", path / "transforms_test.json"
    if tr.is_file() and te.is_file():
        return {"train": _read_json(tr), "test": _read_json(te)}, path, {"train": tr, "test": te}
    raise DatasetNotFoundError(f"no transforms.json (nor transforms_train.json + transforms_test.json) in {path}; "
                               f"expected {LAYOUT}")


def _frame_name(file_path: str) -> str:
    return str(PurePosixPath(file_path.replace("\\", "/")))  # drops a leading "./"


def _image_path(base: Path, file_path: str, folder: str | None) -> Path:
    rel = PurePosixPath(_frame_name(file_path))
    if folder is not None:
        if len(rel.parts) < 2:
            raise SceneFormatError(f"cannot take images from folder {folder!r}: file_path {file_path!r} has no "
                                   "folder component to replace")
        rel = PurePosixPath(folder, *rel.parts[1:])
    p = base / rel
    if p.is_file():
        return p
    if not p.suffix:  # Blender writes "./train/r_0" without the extension
        for ext in (".png", ".jpg", ".jpeg"):
            if p.with_suffix(ext).is_file():
                return p.with_suffix(ext)
    raise MissingImageError(f"image {p} (frame file_path {file_path!r}) is missing; expected {LAYOUT}")


def _pose_opencv(c2w_gl, where: str) -> np.ndarray:
    """World-to-camera (OpenCV) from an OpenGL camera-to-world."""
    try:
        c2w = np.asarray(c2w_gl, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise SceneFormatError(f"{where}: transform_matrix is not a matrix of numbers ({e})") from None
    if c2w.shape == (3, 4):
        c2w = np.vstack([c2w, [0, 0, 0, 1]])
    if c2w.shape != (4, 4):
        raise SceneFormatError(f"{where}: transform_matrix must be 4x4, got {c2w.shape}")
    if not np.isfinite(c2w).all():
        rows, cols = np.nonzero(~np.isfinite(c2w))
        part = "translation" if all(c == 3 for c in cols) else "rotation" if all(c < 3 for c in cols) else "pose"
        raise SceneFormatError(f"{where}: transform_matrix has {len(rows)} non-finite value(s) in its {part} "
                               f"(at row, column {', '.join(f'({r}, {c})' for r, c in zip(rows, cols))}); "
                               "fix or remove the frame")
    R = c2w[:3, :3]
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-3) or np.linalg.det(R) < 0:
        raise SceneFormatError(f"{where}: transform_matrix rotation is not a proper rotation "
                               f"(det {np.linalg.det(R):.4f}); scaled or mirrored poses are not supported")
    c2w = c2w.copy()
    c2w[:3, 1:3] *= -1  # OpenGL (y up, z back) -> OpenCV (y down, z forward)
    return np.linalg.inv(c2w)


def _number(cam: dict, key: str, where: str, default: float | None = None) -> float | None:
    """``cam[key]`` as a finite number (``default`` when absent); NaN, inf or a word is refused."""
    if key not in cam:
        return default
    try:
        v = float(cam[key])
    except (TypeError, ValueError):
        v = math.nan
    if not math.isfinite(v):
        raise SceneFormatError(f"{where}: {key} = {cam[key]!r} is not a finite number; fix it in the file")
    return v


def _focal_from_angle(cam: dict, key: str, size: int, where: str) -> float:
    """The focal length (px) of a field of view ``cam[key]`` in radians across ``size`` pixels."""
    angle = _number(cam, key, where)
    if not 0 < angle < math.pi:
        across = "horizontal" if key.endswith("x") else "vertical"
        raise SceneFormatError(f"{where}: {key} = {angle:g} is no field of view; it is the {across} angle of view "
                               "in radians, between 0 and π (0.69 for a 50 mm lens on a 36 mm wide sensor)")
    return 0.5 * size / math.tan(0.5 * angle)


def _intrinsics(cam: dict, file_size: tuple[int, int], where: str) -> tuple[np.ndarray, tuple[int, int], np.ndarray]:
    """(K, (w, h) that K refers to, OpenCV distortion vector); values that cannot render (a focal
    length of 0 or NaN, a principal point far off the image, a NaN distortion) are refused naming
    the file, the frame and the key."""
    if str(cam.get("camera_model", "OPENCV")).upper() not in ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE") or cam.get("is_fisheye"):
        raise SceneFormatError(f"{where}: camera model {cam.get('camera_model', 'fisheye')!r} is not supported; "
                               "undistort the images to a pinhole camera first")
    w = int(round(_number(cam, "w", where, file_size[0])))
    h = int(round(_number(cam, "h", where, file_size[1])))
    if w <= 0 or h <= 0:
        raise SceneFormatError(f"{where}: image size w x h = {w}x{h}; w and h are the image's size in pixels")
    if "fl_x" in cam:
        fx = _number(cam, "fl_x", where)
    elif "camera_angle_x" in cam:
        fx = _focal_from_angle(cam, "camera_angle_x", w, where)
    else:
        raise SceneFormatError(f"{where}: no focal length (fl_x or camera_angle_x); expected {LAYOUT}")
    if "fl_y" in cam:
        fy = _number(cam, "fl_y", where)
    elif "camera_angle_y" in cam and "fl_x" not in cam:
        fy = _focal_from_angle(cam, "camera_angle_y", h, where)
    else:
        fy = fx
    K = np.array([[fx, 0, _number(cam, "cx", where, w / 2)], [0, fy, _number(cam, "cy", where, h / 2)], [0, 0, 1]],
                 dtype=np.float64)
    check_pinhole(where + " (fl_x, fl_y, cx, cy)", K, (w, h))
    dist = np.array([_number(cam, k, where, 0.0) for k in DIST_KEYS])
    return K, (w, h), dist


class _Undistorter:
    """Undistortion maps, computed once per (K, distortion, size) and shared by the threads."""

    def __init__(self) -> None:
        self._maps: dict[tuple, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        self._lock = threading.Lock()

    def __call__(self, img: np.ndarray, K: np.ndarray, dist: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        import cv2

        size = (img.shape[1], img.shape[0])
        key = (tuple(np.round(K.ravel(), 9)), tuple(dist), size)
        with self._lock:
            if key not in self._maps:
                # OpenCV puts pixel centres at integers, smgs/COLMAP at +0.5: shift in and out.
                Kcv = K.copy()
                Kcv[:2, 2] -= 0.5
                d = dist if np.any(dist[4:]) else dist[:4]
                newK, _ = cv2.getOptimalNewCameraMatrix(Kcv, d, size, 0.0, size)
                m1, m2 = cv2.initUndistortRectifyMap(Kcv, d, None, newK, size, cv2.CV_32FC1)
                newK = newK.astype(np.float64)
                newK[:2, 2] += 0.5
                self._maps[key] = (m1, m2, newK)
            m1, m2, newK = self._maps[key]
        out = cv2.remap(img, m1, m2, interpolation=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
        return out, newK.copy()


@dataclass(frozen=True)
class _Entry:
    """One frame as the files describe it: its split, merged intrinsics, frame dict, image file."""

    split: str
    cam: dict
    frame: dict
    path: Path
    where: str


@dataclass(frozen=True)
class TransformsSources:
    """What a transforms.json scene is loaded from, each part found and checked (``transforms_sources``)."""

    path: Path
    files: dict[str, dict]
    base: Path
    entries: list[_Entry]
    rule: ResolutionRule
    split: tuple[list[int], list[int], str]   # train and test indices into entries, and how chosen
    json_files: tuple[Path, ...] = ()          # the transforms file(s) read

    @property
    def root(self) -> dict:
        return next(iter(self.files.values()))


def transforms_sources(path: str | Path, images: str | None = None, rule: ResolutionRule | str = "3dgs", *,
                       factor: float | None = None, max_width: int | None = None, resample: str | None = None,
                       test_every: int | None = 8) -> TransformsSources:
    """Everything ``load_transforms`` checks before it decodes a pixel: the files, every frame's image
    file (each used by one frame only) and intrinsics, a split that leaves a view to train on and
    holds none out that also trains, and images of at least ``MIN_SIDE`` px under the rule. The
    runner calls it for each scene before any cell runs."""
    if isinstance(rule, str):
        rule = get_generic_rule(rule)
    rule = rule.with_overrides(factor=factor, max_width=max_width, resample=resample)
    if images == "auto":
        raise ValueError("images='auto' is for COLMAP scenes; name the folder (e.g. 'images_4')")
    path = Path(path)
    files, base, sources = _find_transforms(path)
    entries = _entries(files, base, images, sources)
    _check_unique_images(entries)
    for e in entries:
        _intrinsics(e.cam, _reference_size(base, images, e), e.where)
    names = [_frame_name(e.frame["file_path"]) for e in entries]
    split = _split(files, sources, entries, names, test_every)
    check_split(base, len(entries), len(split[0]), split[2])
    src = image_size(entries[0].path)
    check_min_size(entries[0].path, rule.target_size(*src), rule, src)
    return TransformsSources(path, files, base, entries, rule, split, tuple(sources.values()))


def _reference_size(base: Path, images: str | None, e: _Entry,
                    read: tuple[int, int] | None = None) -> tuple[int, int]:
    """The size a frame's intrinsics refer to: w, h in the file, else its image at file_path's
    (``read``: the size of ``e.path`` where the caller has read that image, which is the one at
    file_path when no ``images`` folder replaces file_path's)."""
    if "w" in e.cam and "h" in e.cam:
        return int(round(_number(e.cam, "w", e.where))), int(round(_number(e.cam, "h", e.where)))
    if images is None:
        return read or image_size(e.path)
    return image_size(_image_path(base, e.frame["file_path"], None))


def _check_unique_images(entries: list[_Entry]) -> None:
    """One frame per image file: a file used twice is one view, which the split may hold out as a
    test view while its copy trains."""
    seen: dict[Path, _Entry] = {}
    for e in entries:
        key = e.path.resolve()
        if key in seen:
            raise SceneFormatError(
                f"{seen[key].where} and {e.where} use the same image {e.path}: one file would be both a training "
                "and a test view. Keep one frame per image (remove the duplicate frame)")
        seen[key] = e


def load_transforms(path: str | Path, images: str | None = None, rule: ResolutionRule | str = "3dgs", *,
                    factor: float | None = None, max_width: int | None = None, resample: str | None = None,
                    test_every: int | None = 8, undistort: bool = True,
                    background: tuple[float, float, float] | None = None, name: str | None = None,
                    meta: dict | None = None, workers: int | None = None) -> Scene:
    """Load a transforms.json scene (see the module docstring for the conventions).

    images: take the pixels from this folder instead of the first folder of each file_path (e.g.
        "images_4" for "images/0001.jpg"); intrinsics are rescaled to the size actually loaded.
    rule, factor, max_width, resample: as for ``load_colmap`` (the rule's ``images`` is not used).
    undistort: undistort non-zero distortion with OpenCV; False refuses such scenes.
    """
    src_files = transforms_sources(path, images, rule, factor=factor, max_width=max_width, resample=resample,
                                   test_every=test_every)
    path, files, base, entries, rule = src_files.path, src_files.files, src_files.base, src_files.entries, src_files.rule
    root = src_files.root
    distorted = any(float(e.cam.get(k, 0.0)) != 0.0 for e in entries for k in DIST_KEYS)
    if distorted and not undistort:
        raise SceneFormatError(f"{base}: the cameras have non-zero distortion coefficients "
                               f"({', '.join(k for k in DIST_KEYS if entries[0].cam.get(k))}); smgs renders "
                               "pinhole cameras only. Load with undistort=True, or undistort the images first")
    bg = np.asarray(background if background is not None else (1.0, 1.0, 1.0), dtype=np.float64)
    loader = _FrameLoader(base, images, rule, bg)
    loaded = parallel_map(lambda i: loader(entries[i]), range(len(entries)), workers)
    check_scene_scale([(e.path, src, ksize) for e, (_, _, _, src, ksize) in zip(entries, loaded)])
    views = []
    for e, (img, K, vm, _, _) in zip(entries, loaded):
        c = Camera(torch.from_numpy(K).float(), torch.from_numpy(vm).float(), img.shape[1], img.shape[0])
        views.append(View(c, torch.from_numpy(img), _frame_name(e.frame["file_path"])))
    tr, te, split_desc = src_files.split
    train, test = [views[i] for i in tr], [views[i] for i in te]

    src0 = loaded[0][3]
    out0 = (views[0].camera.width, views[0].camera.height)
    folder = images if images is not None else (PurePosixPath(views[0].name).parts[0]
                                                if len(PurePosixPath(views[0].name).parts) > 1 else ".")
    dist0 = entries[0].cam
    alpha_seen = loader.alpha_seen.is_set()
    info = {
        "loader": "transforms",
        "dataset": "transforms",
        "scene": name or (path if path.is_dir() else path.parent).resolve().name,
        "source": str(path),
        "rule": rule.name,
        "rule_label": rule.label,
        "images_folder": folder,
        "resample_filter": rule.resample,
        "image_size": list(out0),
        "downscale_factor": round(loaded[0][4][0] / out0[0], 6),
        "resampling": describe_resampling(folder, entries[0].path.suffix, src0, out0, rule),
        "distortion": {k: float(dist0[k]) for k in DIST_KEYS if float(dist0.get(k, 0.0)) != 0.0} or None,
        "undistortion": ("OpenCV getOptimalNewCameraMatrix(alpha=0, same size) + remap INTER_CUBIC, "
                         "before resizing; intrinsics replaced by the new camera") if distorted else "none (no distortion)",
        "pose_convention": "OpenGL camera-to-world -> OpenCV world-to-camera (y, z flipped)",
        "instant_ngp_box": {k: root[k] for k in ("aabb_scale", "scale", "offset") if k in root} or None,
        "instant_ngp_box_note": "recorded only: world coordinates kept as in the file",
        "split": split_desc,
        "test_every": test_every if "all" in files else None,
        "n_images": len(views),
        "n_train": len(train),
        "n_test": len(test),
        "n_points": 0,
        "alpha_composited_on": bg.tolist() if alpha_seen else None,
    }
    if "ply_file_path" in root:
        info["ply_file_path_not_loaded"] = root["ply_file_path"]
    info.update(meta or {})
    return Scene(name=info["scene"], train=train, test=test, extent=camera_extent([v.camera for v in train]),
                 points=None, point_colors=None,
                 background=torch.tensor(bg, dtype=torch.float32) if alpha_seen else None, meta=info)


def _entries(files: dict[str, dict], base: Path, images: str | None, sources: dict[str, Path]) -> list[_Entry]:
    """Every frame of the files in order, its intrinsics the file's global ones under its own."""
    frames: list[tuple[str, dict, dict, int]] = []  # (split, global, frame, index in its file)
    for split, d in files.items():
        glob = {k: d[k] for k in _INTRINSIC_KEYS if k in d}
        frames += [(split, glob, f, i) for i, f in enumerate(d["frames"])]
    entries = []
    for split, glob, fr, i in frames:
        if not isinstance(fr, dict):
            raise SceneFormatError(f"{sources[split]} frame {i}: not an object; expected {LAYOUT}")
        where = f"{sources[split]} frame {i} ({fr.get('file_path')!r})"
        if "file_path" not in fr or "transform_matrix" not in fr:
            raise SceneFormatError(f"{where}: a frame needs file_path and transform_matrix; expected {LAYOUT}")
        cam = {**glob, **{k: fr[k] for k in _INTRINSIC_KEYS if k in fr}}
        entries.append(_Entry(split, cam, fr, _image_path(base, fr["file_path"], images), where))
    return entries


class _FrameLoader:
    """Reads one frame (from worker threads): alpha composited on ``bg``, undistorted, resized by
    the rule, with its intrinsics following each step; notes whether any image had alpha."""

    def __init__(self, base: Path, images: str | None, rule: ResolutionRule, bg: np.ndarray) -> None:
        self.base, self.images, self.rule, self.bg = base, images, rule, bg
        self.undistorter = _Undistorter()
        self.alpha_seen = threading.Event()

    def __call__(self, e: _Entry):
        img = read_image(e.path, keep_alpha=True)
        src = (img.shape[1], img.shape[0])
        K, ksize, dist = _intrinsics(e.cam, _reference_size(self.base, self.images, e, src), e.where)
        check_aspect(e.path, src, ksize)
        K = scale_intrinsics(K, ksize, src)
        if img.shape[2] == 4:
            self.alpha_seen.set()
            a = img[..., 3:].astype(np.float64) / 255.0
            img = np.round(img[..., :3] * a + 255.0 * self.bg * (1 - a)).astype(np.uint8)
        if np.any(dist != 0):
            img, K = self.undistorter(img, K, dist)
        out = self.rule.target_size(*src)
        img = resize_image(img, out, self.rule.resample)
        K = scale_intrinsics(K, src, out)
        return img, K, _pose_opencv(e.frame["transform_matrix"], e.where), src, ksize


def _split(files: dict[str, dict], sources: dict[str, Path], entries: list[_Entry], names: list[str],
           test_every: int | None) -> tuple[list[int], list[int], str]:
    """Train and test indices (each name-sorted) and how they were chosen: separate train/test
    files, file lists in transforms.json, else every ``test_every``-th name-sorted image. A name in
    both file lists is refused: its view would be scored as held out while it trains."""
    root = next(iter(files.values()))
    if "all" not in files:
        tr = [i for i, e in enumerate(entries) if e.split == "train"]
        te = [i for i, e in enumerate(entries) if e.split == "test"]
        split_desc = "explicit: transforms_train.json / transforms_test.json"
    elif "train_filenames" in root and "test_filenames" in root:
        trn = {_frame_name(n) for n in root["train_filenames"]}
        ten = {_frame_name(n) for n in root["test_filenames"]}
        both = sorted(trn & ten)
        if both:
            raise SceneFormatError(
                f"{sources['all']}: {len(both)} image(s) in both train_filenames and "
                f"test_filenames ({', '.join(both[:5])}{' …' if len(both) > 5 else ''}): a training view would be "
                "scored as held out. List each image in one of them")
        tr = [i for i, n in enumerate(names) if n in trn]
        te = [i for i, n in enumerate(names) if n in ten]
        split_desc = "explicit: train_filenames / test_filenames in transforms.json"
    else:
        tr, te = split_every(names, test_every)
        split_desc = split_description(test_every)
    return sorted(tr, key=lambda i: names[i]), sorted(te, key=lambda i: names[i]), split_desc
