"""Image reading, resolution rules and resizing shared by the loaders.

Resampling matters for the numbers: JPEG ``images_N`` folders as shipped versus our own downscaling
of the full-resolution images moves PSNR by 0.3-0.5 dB (docs/usage.md, "Resolution rules"), so
every loader records which one it used (``describe_resampling``).
"""

from __future__ import annotations

import math
import os
import re
import statistics
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
from PIL import Image

from smgs.data.errors import SceneFormatError

# PIL filters by name. BICUBIC is what 3DGS (PILtoTorch: ``Image.resize`` default) and gsplat
# (``_resize_image_folder``) use, so it is the default for our own downscaling.
RESAMPLE: dict[str, Image.Resampling] = {
    "bicubic": Image.Resampling.BICUBIC,
    "lanczos": Image.Resampling.LANCZOS,
    "bilinear": Image.Resampling.BILINEAR,
    "box": Image.Resampling.BOX,
    "nearest": Image.Resampling.NEAREST,
}

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".webp")

MIN_SIDE = 16
"""The smallest image side (px) a scene is trained and scored at: one tile of the renderer
(``smgs.raster.constants.TILE_SIZE``), above SSIM's 11-px window (on smaller images its window is
mostly zero padding). A 1x1 image scores 32 dB and SSIM 0.998 whatever the model."""

PRINCIPAL_POINT_SLACK = 1.0
"""How far (in image sizes) a principal point may lie outside its image: a crop can move it out of
the frame, but one image size beyond the edge is a unit or entry error (normalised, swapped or
scaled values), which renders every view off its rays."""

FIELD_OF_VIEW_DEG = (0.5, 170.0)
"""The angles of view (degrees, across the image's width and across its height) a pinhole camera may
have: a 1200 mm lens on a full-frame sensor sees 1.7° across, an undistorted wide-angle capture
about 120°; 180° is a focal length of 0 and a focal length of 1e12 px a field of view of 1e-8°,
both a unit or entry error (a focal length in mm, or normalised by the image size) that trains a
model nobody can use: a ~180° view collapses, a 1e-8° one overflows float32 at the first step."""


@dataclass(frozen=True)
class ResolutionRule:
    """How to get a training image from what is on disk.

    images: source folder under the scene ("images", "images_4", ...). "auto" takes the smallest
        shipped ``images_N`` folder that is still at least ``max_width`` wide (else "images") -
        only for presets that downscale anyway (the cpu one), to avoid decoding 5K JPEGs.
    factor: divide the source size by this (3DGS ``-r N``; size rounded half up).
    max_width: images wider than this are downscaled to this width, keeping the aspect ratio
        (3DGS ``-r -1`` with 1600; the height is truncated as 3DGS does). Never upsamples.
    resample: PIL filter for our own resizing (see RESAMPLE).
    label: said next to every number the rule produced (e.g. that a preset is not the paper's).
    """

    name: str = "native"
    images: str = "images"
    factor: float | None = None
    max_width: int | None = None
    resample: str = "bicubic"
    label: str = ""

    def __post_init__(self) -> None:
        if self.resample not in RESAMPLE:
            raise ValueError(f"unknown resample {self.resample!r}; expected one of {', '.join(RESAMPLE)}")
        if self.factor is not None and self.factor <= 0:
            raise ValueError(f"factor must be > 0, got {self.factor}")
        if self.max_width is not None and self.max_width <= 0:
            raise ValueError(f"max_width must be > 0, got {self.max_width}")

    def target_size(self, width: int, height: int) -> tuple[int, int]:
        """Output (width, height) for a source image of this size."""
        w, h = width, height
        if self.factor is not None and self.factor != 1:
            w, h = _round_half_up(w / self.factor), _round_half_up(h / self.factor)
        if self.max_width is not None and w > self.max_width:
            # Integer arithmetic: 3DGS's int(h / (w / 1600)) can lose a pixel to float rounding.
            w, h = self.max_width, (h * self.max_width) // w
        return max(w, 1), max(h, 1)

    def with_overrides(self, **kw) -> "ResolutionRule":
        """A copy with the given non-None fields replaced (name kept unless given)."""
        kw = {k: v for k, v in kw.items() if v is not None}
        return replace(self, **kw) if kw else self


def _round_half_up(x: float) -> int:
    return int(np.floor(x + 0.5))


def find_image(folder: Path, name: str) -> Path | None:
    """``folder/name``, or the single file with the same stem and another image extension (a
    ``images_N`` folder may hold PNGs for JPEG originals)."""
    p = folder / name
    if p.is_file():
        return p
    parent = p.parent
    if not parent.is_dir():
        return None
    stem = p.stem
    cands = [q for q in parent.iterdir() if q.stem == stem and q.suffix.lower() in IMAGE_EXTENSIONS]
    return cands[0] if len(cands) == 1 else None


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) from the header only."""
    try:
        with Image.open(path) as im:
            return im.size
    except OSError as e:
        raise SceneFormatError(f"cannot read image {path}: {e}") from e


def read_image(path: Path, keep_alpha: bool = False) -> np.ndarray:
    """uint8 [H, W, 3] (or [H, W, 4] when ``keep_alpha`` and the file has alpha). EXIF orientation is
    not applied, as COLMAP and 3DGS do not apply it either: the pixels stay the ones COLMAP saw."""
    try:
        with Image.open(path) as im:
            has_alpha = im.mode in ("RGBA", "LA") or (im.mode == "P" and "transparency" in im.info)
            if keep_alpha and has_alpha:
                return np.array(im.convert("RGBA"))
            if im.mode in ("I;16", "I;16B", "I"):
                raise SceneFormatError(f"image {path} is {im.mode} (16-bit); expected 8-bit RGB")
            return np.array(im.convert("RGB"))
    except OSError as e:
        raise SceneFormatError(f"cannot read image {path}: {e}") from e


def resize_image(img: np.ndarray, size: tuple[int, int], resample: str = "bicubic") -> np.ndarray:
    """Resize a uint8 [H, W, C] image to (width, height) with a PIL filter."""
    if (img.shape[1], img.shape[0]) == tuple(size):
        return img
    return np.array(Image.fromarray(img).resize(tuple(size), RESAMPLE[resample]))


def scale_intrinsics(K: np.ndarray, from_size: tuple[int, int], to_size: tuple[int, int]) -> np.ndarray:
    """K of a camera whose image was resized from ``from_size`` to ``to_size`` (width, height).

    Per-axis factors of the actual sizes, so the image borders stay on the same rays; exact in the
    pixel-centre-at-+0.5 convention shared by COLMAP, instant-ngp and smgs.camera.
    """
    K = np.array(K, dtype=np.float64, copy=True)
    K[0] *= to_size[0] / from_size[0]
    K[1] *= to_size[1] / from_size[1]
    K[2] = (0.0, 0.0, 1.0)
    return K


def check_aspect(path: Path, img_size: tuple[int, int], cam_size: tuple[int, int], tol_px: float = 1.5) -> None:
    """Refuse an image whose aspect ratio does not match its camera (wrong folder, rotated image)
    instead of stretching the intrinsics silently. Rounded downscales differ by under a pixel."""
    w, h = img_size
    cw, ch = cam_size
    if abs(h - ch * w / cw) > tol_px and abs(w - cw * h / ch) > tol_px:
        raise SceneFormatError(
            f"image {path} is {w}x{h} but its camera is {cw}x{ch} (aspect {cw / ch:.4f} vs {w / h:.4f}); "
            "the image folder does not match the camera model (a rotated image, or images from another capture?)")


def check_min_size(where: object, size: tuple[int, int], rule: ResolutionRule, source: tuple[int, int]) -> None:
    """Refuse images smaller than ``MIN_SIDE`` on a side after the resolution rule, naming the fix."""
    w, h = size
    if min(w, h) < MIN_SIDE:
        raise SceneFormatError(
            f"{where}: the images are {w}x{h} px after the resolution rule ({rule.label or rule.name}; from "
            f"{source[0]}x{source[1]}), under the {MIN_SIDE} px a side that a score needs (one renderer tile; "
            "SSIM's window is 11 px). Use a larger protocol.max_width, or a rule that keeps more pixels "
            "(dataset.rule=native)")


def check_pinhole(where: str, K: np.ndarray, size: tuple[int, int]) -> None:
    """A camera's intrinsics can render its image: focal lengths finite and positive and giving an
    angle of view within ``FIELD_OF_VIEW_DEG``, the principal point finite and within
    ``PRINCIPAL_POINT_SLACK`` image sizes of the frame. ``where`` names the
    file and the camera or frame; the error says what to fix."""
    fx, fy, cx, cy = (float(v) for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
    w, h = size
    bad = [f"{n} = {v:g}" for n, v in (("fx", fx), ("fy", fy)) if not (math.isfinite(v) and v > 0)]
    if bad:
        raise SceneFormatError(f"{where}: focal length {', '.join(bad)}; a focal length is a positive number of "
                               "pixels. Fix the camera's calibration (or remove the camera and its images)")
    fov = field_of_view_problem(fx, fy, size)
    if fov:
        raise SceneFormatError(f"{where}: {fov}")
    s = PRINCIPAL_POINT_SLACK
    if not all(math.isfinite(v) for v in (cx, cy)) or not (-s * w <= cx <= (1 + s) * w and -s * h <= cy <= (1 + s) * h):
        raise SceneFormatError(
            f"{where}: principal point (cx, cy) = ({cx:g}, {cy:g}) lies more than one image size outside its "
            f"{w}x{h} image; cx and cy are pixels from the image's top-left corner (about {w / 2:g}, {h / 2:g} "
            "for an undistorted camera). Fix the camera's calibration (pixels, not normalised units)")


def field_of_view_problem(fx: float, fy: float, size: tuple[int, int]) -> str | None:
    """Why finite, positive focal lengths ``fx``, ``fy`` (px) give a ``size`` image an angle of view
    outside ``FIELD_OF_VIEW_DEG`` (None when they do not): the angle, the range and the focal lengths
    that fit it, and the likely cause."""
    lo, hi = FIELD_OF_VIEW_DEG
    for axis, f, n in (("fx", fx, size[0]), ("fy", fy, size[1])):
        angle = math.degrees(2 * math.atan(0.5 * n / f))
        if not lo <= angle <= hi:
            f_lo, f_hi = (0.5 * n / math.tan(math.radians(a) / 2) for a in (hi, lo))
            return (f"{axis} = {f:g} px gives the {n}-px {'width' if axis == 'fx' else 'height'} a field of view of "
                    f"{angle:.3g}°, outside the {lo:g}°–{hi:g}° a pinhole camera may have here (a focal length of "
                    f"{f_lo:.3g}–{f_hi:.3g} px); a focal length is in pixels of the image it calibrates, not mm "
                    "or normalised units. Fix the camera's calibration")
    return None


def check_scene_scale(images: Sequence[tuple[Path, tuple[int, int], tuple[int, int]]], tol_px: float = 1.5) -> None:
    """Every image at its camera's size divided by the scene's own factor: ``images`` is (file,
    image (w, h), camera (w, h)) per view. The factor of each axis is the median camera/image ratio
    (the lower median: an actual image's), so a shipped ``images_4`` folder passes with 4 and full
    images with 1, each axis rounded on its own; an image off that scale by more than ``tol_px``
    (a 1x1 file, a thumbnail, a truncated download of another size) is refused naming it.
    ``check_aspect`` alone passes such an image, whose aspect is measured at its own size."""
    if not images:
        return
    fx = statistics.median_low([cw / w for _, (w, _h), (cw, _ch) in images])
    fy = statistics.median_low([ch / h for _, (_w, h), (_cw, ch) in images])
    bad = [(p, (w, h), (cw, ch)) for p, (w, h), (cw, ch) in images
           if abs(w - cw / fx) > tol_px or abs(h - ch / fy) > tol_px]
    if bad:
        ok = next((x for x in images if x not in bad), images[0])
        factor = f"{fx:.4g}" if abs(fx / fy - 1) < 0.01 else f"{fx:.4g} across, {fy:.4g} down"
        lines = [f"{p} is {w}x{h}, its camera {cw}x{ch}" for p, (w, h), (cw, ch) in bad[:5]]
        more = f" and {len(bad) - 5} more" if len(bad) > 5 else ""
        raise SceneFormatError(
            f"{len(bad)} image(s) are not at the scene's scale (camera size / {factor}, as {ok[0]} is "
            f"{ok[1][0]}x{ok[1][1]} for a {ok[2][0]}x{ok[2][1]} camera): " + "; ".join(lines) + more
            + ". Each would be scored as a view of the whole image (a truncated download, a thumbnail, or an "
            "image from another folder?); replace it with the image at the scene's scale")


def images_n_folders(scene_dir: Path) -> list[tuple[int, Path]]:
    """The ``images_N`` folders of a scene as (N, path), N ascending."""
    out = []
    for p in scene_dir.iterdir() if scene_dir.is_dir() else []:
        m = re.fullmatch(r"images_(\d+)", p.name)
        if m and p.is_dir():
            out.append((int(m.group(1)), p))
    return sorted(out)


def resolve_auto_folder(scene_dir: Path, first_name: str, min_width: int | None) -> str:
    """For ``images="auto"``: the smallest shipped ``images_N`` whose image ``first_name`` is at
    least ``min_width`` wide; "images" if none is."""
    if min_width is None:
        return "images"
    for _, folder in sorted(images_n_folders(scene_dir), key=lambda t: -t[0]):
        p = find_image(folder, first_name)
        if p is not None and image_size(p)[0] >= min_width:
            return folder.name
    return "images"


def describe_resampling(folder: str, source_ext: str, src_size: tuple[int, int], out_size: tuple[int, int],
                        rule: ResolutionRule) -> str:
    """What was done to the pixels, for ``scene.meta['resampling']``."""
    fmt = {".jpg": "jpeg", ".jpeg": "jpeg", ".png": "png"}.get(source_ext.lower(), source_ext.lstrip(".").lower())
    if tuple(src_size) == tuple(out_size):
        if re.fullmatch(r"images_\d+", folder):
            return f"{fmt} {folder} as shipped"
        return f"none ({fmt} {folder} at native resolution)"
    return f"PIL {rule.resample.upper()} from {fmt} {folder} {src_size[0]}x{src_size[1]}"


def parallel_map(fn: Callable, items: Sequence, workers: int | None = None) -> list:
    """Map over items with threads (PIL and OpenCV release the GIL while decoding/resampling)."""
    workers = workers if workers is not None else min(4, os.cpu_count() or 1)
    if workers <= 1 or len(items) <= 1:
        return [fn(x) for x in items]
    with ThreadPoolExecutor(workers) as ex:
        return list(ex.map(fn, items))
