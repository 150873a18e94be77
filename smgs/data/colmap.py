"""COLMAP scenes through pycolmap (Mip-NeRF360, Tanks&Temples, Deep Blending, LLFF, a user's capture).

Layout expected::

    <scene>/images/...          full-resolution images, named as in the model
    <scene>/images_2/ ...       optional pre-downscaled copies (Mip-NeRF360 ships JPEG images_2/4/8)
    <scene>/sparse/0/{cameras,images,points3D}.{bin,txt}   (or directly in <scene>/sparse/)

Cameras must be undistorted PINHOLE / SIMPLE_PINHOLE, as for 3DGS.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from smgs.camera import Camera
from smgs.data.images import (ResolutionRule, check_aspect, check_min_size, check_pinhole, check_scene_scale,
                              describe_resampling, find_image, image_size, parallel_map, read_image, resize_image,
                              resolve_auto_folder, scale_intrinsics)
from smgs.data.rules import get_generic_rule
from smgs.data.scene import (DatasetNotFoundError, MissingImageError, Scene, SceneFormatError, View,
                             camera_extent, check_split, split_description, split_every, view_key)

LAYOUT = ("<scene>/images/<name as in the model>, optional <scene>/images_N/, and a COLMAP model "
          "<scene>/sparse/0/{cameras,images,points3D}.{bin,txt} (or <scene>/sparse/)")
SUPPORTED_MODELS = ("PINHOLE", "SIMPLE_PINHOLE")
_MODEL_FILES = ("cameras", "images", "points3D")
# Smallest record of each binary file (COLMAP src/colmap/scene/reconstruction_io.cc layouts): used to
# refuse a corrupt header before pycolmap tries to allocate a garbage-sized array.
_MIN_RECORD_BYTES = {"cameras": 4 + 4 + 8 + 8 + 3 * 8, "images": 4 + 32 + 24 + 4 + 1 + 8,
                     "points3D": 8 + 24 + 3 + 8 + 8}


@dataclass
class ColmapImage:
    """One registered image of a model, at the model's camera resolution."""

    name: str
    camera_id: int
    model: str
    K: np.ndarray          # [3, 3] float64, for the camera's width x height
    width: int
    height: int
    viewmat: np.ndarray    # [4, 4] float64 world-to-camera (OpenCV axes, as COLMAP)


@dataclass
class ColmapModel:
    path: Path
    images: list[ColmapImage]         # registered images, name-sorted
    points: np.ndarray | None         # [M, 3] float64
    colors: np.ndarray | None         # [M, 3] uint8
    n_unregistered: int
    quaternion_note: str | None = None   # how many rotations were normalised (QUAT_TOLERANCE)


def find_model_dir(scene_dir: Path) -> Path:
    """``sparse/0`` if it exists, else ``sparse`` holding the model files directly."""
    scene_dir = Path(scene_dir)
    if not scene_dir.is_dir():
        raise DatasetNotFoundError(f"COLMAP scene folder {scene_dir} does not exist; expected {LAYOUT}")
    for cand in (scene_dir / "sparse" / "0", scene_dir / "sparse"):
        if any((cand / f"{f}.{ext}").is_file() for f in _MODEL_FILES for ext in ("bin", "txt")):
            return cand
    raise SceneFormatError(f"no COLMAP model in {scene_dir}: looked for {scene_dir / 'sparse' / '0'} and "
                           f"{scene_dir / 'sparse'}; expected {LAYOUT}")


def _check_model_files(model_dir: Path) -> None:
    missing = [f for f in _MODEL_FILES
               if not (model_dir / f"{f}.bin").is_file() and not (model_dir / f"{f}.txt").is_file()]
    if missing:
        raise SceneFormatError(f"COLMAP model {model_dir} is incomplete: missing "
                               f"{', '.join(m + '.bin/.txt' for m in missing)}; expected {LAYOUT}")
    for f in _MODEL_FILES:
        p = model_dir / f"{f}.bin"
        if not p.is_file():
            continue
        size = p.stat().st_size
        if size < 8:
            raise SceneFormatError(f"corrupt COLMAP model file {p}: {size} bytes, shorter than its header")
        with open(p, "rb") as fh:
            (count,) = struct.unpack("<Q", fh.read(8))
        if count * _MIN_RECORD_BYTES[f] > size - 8:
            raise SceneFormatError(
                f"corrupt COLMAP model file {p}: its header announces {count} records, which cannot fit "
                f"in {size} bytes. Re-export the model (colmap model_converter) or restore the file.")


def _check_binary_sizes(model_dir: Path, rec) -> None:
    """pycolmap reads a truncated file without complaint (a cut cameras.bin yields a garbage focal
    length), so each binary file must be exactly as long as the records it was read into."""
    expected = {
        "cameras": 8 + sum(4 + 4 + 8 + 8 + 8 * len(c.params) for c in rec.cameras.values()),
        "images": 8 + sum(4 + 32 + 24 + 4 + len(i.name.encode()) + 1 + 8 + 24 * i.num_points2D()
                          for i in rec.images.values()),
        "points3D": 8 + sum(8 + 24 + 3 + 8 + 8 + 8 * p.track.length() for p in rec.points3D.values()),
    }
    for f, n in expected.items():
        p = model_dir / f"{f}.bin"
        if p.is_file() and p.stat().st_size != n:
            raise SceneFormatError(
                f"corrupt COLMAP model file {p}: {p.stat().st_size} bytes, but the records read from it take "
                f"{n} bytes (truncated or padded). Re-export the model (colmap model_converter) or restore the file.")


def import_pycolmap():
    """pycolmap, imported with this process's SIGTERM handling kept: importing it installs glog's
    failure-signal handler, which answers SIGTERM with a native stack dump and a kill instead of the
    handler the process had (the runner's clean stop: its log's "interrupted" line, the cell's last
    checkpoint kept). The handler the process had is put back after the import."""
    import signal
    import threading

    main = threading.current_thread() is threading.main_thread()
    before = signal.getsignal(signal.SIGTERM) if main else None
    import pycolmap

    if before is not None:   # None: installed outside Python, nothing of ours to keep
        signal.signal(signal.SIGTERM, before)
    return pycolmap


def model_file(model_dir: Path, name: str) -> Path:
    """The file of a model's ``cameras`` / ``images`` / ``points3D`` that pycolmap reads (.bin first)."""
    b = Path(model_dir) / f"{name}.bin"
    return b if b.is_file() else Path(model_dir) / f"{name}.txt"


def model_files(model_dir: Path) -> list[Path]:
    """The files of a model that pycolmap reads (``model_file`` of each: .bin first)."""
    return [p for p in (model_file(model_dir, f) for f in _MODEL_FILES) if p.is_file()]


QUAT_TOLERANCE = 0.01
"""A rotation quaternion whose length is within this of 1 is normalised (and the scene's meta says how
many were); one further off, of length 0 or not finite, is refused. COLMAP writes unit quaternions,
so a length off by more than 1 % is an edited or corrupt file, whose rotation cannot be trusted."""


def _cameras(model_dir: Path, rec) -> dict[int, tuple[str, np.ndarray, int, int]]:
    """camera id -> (model, K, width, height); a distorted model or unusable intrinsics are refused."""
    cams = {}
    for cid, cam in rec.cameras.items():
        model = cam.model.name
        if model not in SUPPORTED_MODELS:
            raise SceneFormatError(
                f"COLMAP camera {cid} in {model_dir} uses the {model} model; smgs (like 3DGS) needs "
                f"undistorted {' or '.join(SUPPORTED_MODELS)} cameras. Undistort the scene first: "
                f"colmap image_undistorter --image_path <scene>/images --input_path {model_dir} "
                "--output_path <new scene> --output_type COLMAP")
        K = np.asarray(cam.calibration_matrix(), dtype=np.float64)
        check_pinhole(f"{model_file(model_dir, 'cameras')}, camera {cid}", K, (int(cam.width), int(cam.height)))
        cams[cid] = (model, K, int(cam.width), int(cam.height))
    return cams


def _viewmat(img, where: Path) -> tuple[np.ndarray, float]:
    """An image's [4, 4] world-to-camera matrix and how far its quaternion's length was from 1
    (normalised when within ``QUAT_TOLERANCE``); a pose that is no rotation and translation is
    refused naming the image and the file."""
    pose = img.cam_from_world()
    q = np.asarray(pose.rotation.quat, dtype=np.float64)   # x, y, z, w
    t = np.asarray(pose.translation, dtype=np.float64)
    what = f"{where}, image {img.name!r} (id {img.image_id})"
    fix = "Re-export the model from COLMAP or remove the image (colmap image_deleter)"
    shown = ", ".join(f"{v:g}" for v in (q[3], q[0], q[1], q[2]))
    if not np.isfinite(q).all() or not np.isfinite(t).all():
        raise SceneFormatError(f"{what}: its pose is not finite (quaternion qw, qx, qy, qz = {shown}; translation "
                               f"{', '.join(f'{v:g}' for v in t)}). {fix}")
    n = float(np.linalg.norm(q))
    if abs(n - 1) > QUAT_TOLERANCE:
        raise SceneFormatError(f"{what}: its rotation quaternion (qw, qx, qy, qz = {shown}) has length {n:g}, not 1 "
                               f"(more than {QUAT_TOLERANCE:g} off: an edited or corrupt value, no rotation). {fix}")
    vm = np.eye(4)
    if abs(n - 1) > 1e-6:
        import pycolmap

        vm[:3, :3] = np.asarray(pycolmap.Rotation3d(q / n).matrix(), dtype=np.float64)
        vm[:3, 3] = t
    else:
        vm[:3, :] = np.asarray(pose.matrix(), dtype=np.float64)
    return vm, abs(n - 1)


def _check_unique_names(where: Path, images) -> None:
    """Each image name once, also under another spelling of its path (``view_key``): a name twice
    is one file seen as two views, one of which may be held out as a test view while its copy trains."""
    ids: dict[str, list[tuple[int, str]]] = {}
    for img in images:   # by the path a name names: ./image010.png is image010.png
        ids.setdefault(view_key(img.name), []).append((int(img.image_id), img.name))
    twice = {key: sorted(i) for key, i in ids.items() if len(i) > 1}
    if twice:
        def spelled(key: str, listed: list[tuple[int, str]]) -> str:
            names = sorted({n for _, n in listed} - {key})
            as_ = f" (also as {', '.join(names)})" if names else ""
            return f"{key}{as_} (image ids {', '.join(str(i) for i, _ in listed)})"

        listed = "; ".join(spelled(key, i) for key, i in sorted(twice.items())[:5])
        raise SceneFormatError(
            f"{where} lists {len(twice)} image name(s) more than once: {listed}"
            f"{' and more' if len(twice) > 5 else ''}. One file would be both a training and a test view; "
            "keep one image per name (colmap image_deleter) and export the model again")


def _check_unique_files(model_dir: Path, images: list[ColmapImage], paths: list[Path]) -> None:
    """Each image file once: two names of the model found as one file (``image010.jpg`` read from
    the ``image010.png`` an images_N folder holds, a link) would be one image as two views."""
    seen: dict[Path, str] = {}
    for im, p in zip(images, paths):
        key = p.resolve()
        if key in seen:
            raise SceneFormatError(
                f"COLMAP model {model_dir}: images {seen[key]!r} and {im.name!r} are both the file {p}: one file "
                "would be both a training and a test view; keep one image per file (colmap image_deleter)")
        seen[key] = im.name


def read_colmap_model(model_dir: Path, with_points: bool = True) -> ColmapModel:
    """Read and check a COLMAP model with pycolmap. Every failure names the path (and the camera or
    image): intrinsics that cannot render (``check_pinhole``), poses that are not finite rotations,
    an image name listed twice."""
    pycolmap = import_pycolmap()  # imported here: listing datasets should not need it

    model_dir = Path(model_dir)
    if not model_dir.is_dir():
        raise DatasetNotFoundError(f"COLMAP model folder {model_dir} does not exist; expected {LAYOUT}")
    _check_model_files(model_dir)
    try:
        rec = pycolmap.Reconstruction(str(model_dir))
    except (ValueError, IndexError, RuntimeError, MemoryError, OSError) as e:
        raise SceneFormatError(f"corrupt COLMAP model in {model_dir}: pycolmap could not read it ({e}). "
                               f"Expected {LAYOUT}") from e
    _check_binary_sizes(model_dir, rec)
    cams = _cameras(model_dir, rec)
    images_file = model_file(model_dir, "images")
    registered = [img for img in rec.images.values() if img.has_pose]
    _check_unique_names(images_file, registered)
    images, off = [], []
    for img in registered:
        model, K, w, h = cams[img.camera_id]
        vm, dev = _viewmat(img, images_file)
        off.append(dev)
        images.append(ColmapImage(img.name, int(img.camera_id), model, K, w, h, vm))
    if not images:
        raise SceneFormatError(f"COLMAP model {model_dir} has no registered images")
    images.sort(key=lambda im: im.name)

    points = colors = None
    if with_points and len(rec.points3D) > 0:
        pts = list(rec.points3D.values())
        points = np.array([p.xyz for p in pts], dtype=np.float64)
        colors = np.array([p.color for p in pts], dtype=np.uint8)
    normalised = [d for d in off if d > 1e-6]
    note = (f"{len(normalised)} rotation quaternion(s) of {images_file.name} normalised (length off 1 by up to "
            f"{max(normalised):.2g})") if normalised else None
    return ColmapModel(model_dir, images, points, colors, len(rec.images) - len(registered), note)


@dataclass
class ColmapSources:
    """What a COLMAP scene is loaded from, each part found and checked (``colmap_sources``)."""

    scene_dir: Path
    model_dir: Path
    model: ColmapModel
    rule: ResolutionRule
    folder_name: str
    paths: list[Path]           # each model image's file, in model.images order


def colmap_sources(path: str | Path, images: str | None = None, rule: ResolutionRule | str = "3dgs", *,
                   factor: float | None = None, max_width: int | None = None, resample: str | None = None,
                   test_every: int | None = 8, model_dir: str | Path | None = None,
                   with_points: bool = True) -> ColmapSources:
    """Everything ``load_colmap`` checks before it decodes a pixel: the model (read and checked), the
    image folder and every image's file, a split that leaves a view to train on, and images of at
    least ``MIN_SIDE`` px under the rule (from the first image's header). The runner calls it for
    each scene before any cell runs, so a folder that is no scene stops the sweep up front."""
    if isinstance(rule, str):
        rule = get_generic_rule(rule)
    rule = rule.with_overrides(images=images, factor=factor, max_width=max_width, resample=resample)
    scene_dir = Path(path)
    mdir = Path(model_dir) if model_dir is not None else find_model_dir(scene_dir)
    model = read_colmap_model(mdir, with_points=with_points)
    tr, _ = split_every([im.name for im in model.images], test_every)
    check_split(f"COLMAP model {mdir}", len(model.images), len(tr), split_description(test_every))

    folder_name = rule.images
    if folder_name == "auto":
        folder_name = resolve_auto_folder(scene_dir, model.images[0].name, rule.max_width)
    folder = scene_dir / folder_name
    if not folder.is_dir():
        raise DatasetNotFoundError(f"image folder {folder} does not exist (COLMAP model {mdir}); expected {LAYOUT}")
    paths = []
    for im in model.images:
        p = find_image(folder, im.name)
        if p is None:
            raise MissingImageError(f"image {folder / im.name} (listed in COLMAP model {mdir}) is missing; "
                                    f"every image of the model must be in {folder}")
        paths.append(p)
    _check_unique_files(mdir, model.images, paths)
    src = image_size(paths[0])
    check_min_size(paths[0], rule.target_size(*src), rule, src)
    return ColmapSources(scene_dir, mdir, model, rule, folder_name, paths)


ALPHA_NOTE = ("alpha is dropped: the ground truth is the files' RGB as stored, not composited, as 3DGS reads a "
              "COLMAP scene (its 2023 code meant to multiply RGB by alpha, but its check tests the image height, "
              "not the channel count; its 2024 code keeps RGB as stored and masks only the training render)")


def load_colmap(path: str | Path, images: str | None = None, rule: ResolutionRule | str = "3dgs", *,
                factor: float | None = None, max_width: int | None = None, resample: str | None = None,
                test_every: int | None = 8, model_dir: str | Path | None = None, with_points: bool = True,
                name: str | None = None, meta: dict | None = None, workers: int | None = None) -> Scene:
    """Load a COLMAP scene.

    images: source folder under ``path`` ("images", "images_2", ...); overrides the rule's folder.
    rule: a ResolutionRule or the name of a generic one (smgs.data.rules.GENERIC_RULES: "native",
        "3dgs" = downscale above 1600 px width as 3DGS ``-r -1``, "cpu"); ``factor``, ``max_width``
        and ``resample`` override its fields.
    test_every: every Nth image of the name-sorted list is test (index % N == 0); None: no test.
    Intrinsics are rescaled per axis to the size of the image actually loaded.
    """
    sources = colmap_sources(path, images, rule, factor=factor, max_width=max_width, resample=resample,
                             test_every=test_every, model_dir=model_dir, with_points=with_points)
    scene_dir, mdir, model, rule = sources.scene_dir, sources.model_dir, sources.model, sources.rule
    folder_name, paths = sources.folder_name, sources.paths

    def load_one(i: int) -> tuple[np.ndarray, np.ndarray, tuple[int, int]]:
        im, p = model.images[i], paths[i]
        img = read_image(p, keep_alpha=True)
        if img.shape[2] == 4:   # the stored RGB is the ground truth, as 3DGS reads it (ALPHA_NOTE)
            with_alpha.append(p.name)
            img = img[..., :3]
        src = (img.shape[1], img.shape[0])
        check_aspect(p, src, (im.width, im.height))
        out = rule.target_size(*src)
        img = resize_image(img, out, rule.resample)
        return img, scale_intrinsics(im.K, (im.width, im.height), out), src

    with_alpha: list[str] = []
    loaded = parallel_map(load_one, range(len(model.images)), workers)
    check_scene_scale([(p, src, (im.width, im.height)) for p, (_, _, src), im in zip(paths, loaded, model.images)])
    views = []
    for im, (img, K, _) in zip(model.images, loaded):
        cam = Camera(torch.from_numpy(K).float(), torch.from_numpy(im.viewmat).float(), img.shape[1], img.shape[0])
        views.append(View(cam, torch.from_numpy(np.ascontiguousarray(img)), im.name))
    tr, te = split_every([v.name for v in views], test_every)   # colmap_sources checked it leaves a view to train on
    train, test = [views[i] for i in tr], [views[i] for i in te]

    src0 = loaded[0][2]
    out_sizes = sorted({(v.camera.width, v.camera.height) for v in views})
    factors = sorted({round(im.width / v.camera.width, 6) for im, v in zip(model.images, views)})
    info = {
        "loader": "colmap",
        "dataset": "colmap",
        "scene": name or scene_dir.resolve().name,
        "source": str(scene_dir),
        "model": str(mdir),
        "rule": rule.name,
        "rule_label": rule.label,
        "images_folder": folder_name,
        "resample_filter": rule.resample,
        "image_size": list(out_sizes[0]) if len(out_sizes) == 1 else [list(s) for s in out_sizes],
        "colmap_camera_size": [model.images[0].width, model.images[0].height],
        "downscale_factor": factors[0] if len(factors) == 1 else factors,
        "resampling": describe_resampling(folder_name, paths[0].suffix, src0, (views[0].camera.width,
                                                                             views[0].camera.height), rule),
        "camera_models": sorted({im.model for im in model.images}),
        "split": split_description(test_every),
        "test_every": test_every,
        "n_images": len(views),
        "n_train": len(train),
        "n_test": len(test),
        "n_unregistered_skipped": model.n_unregistered,
        "n_points": 0 if model.points is None else int(len(model.points)),
        "alpha_dropped": (f"{len(with_alpha)} of {len(views)} images have an alpha channel (e.g. "
                          f"{sorted(with_alpha)[0]}); {ALPHA_NOTE}") if with_alpha else None,
    }
    if model.quaternion_note:
        info["quaternions_normalised"] = model.quaternion_note
    info.update(meta or {})
    return Scene(
        name=info["scene"], train=train, test=test,
        extent=camera_extent([v.camera for v in train] or [v.camera for v in views]),
        points=None if model.points is None else torch.from_numpy(model.points).float(),
        point_colors=None if model.colors is None else torch.from_numpy(model.colors).float() / 255.0,
        meta=info)
