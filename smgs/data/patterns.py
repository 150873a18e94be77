"""The 2D pattern targets of the paper's Table 1 (Sec. 4.1): ``circle4``, ``rect4``, ``oval4``.

The paper does not publish its images; these are our definitions: a shape centred in the frame,
cut by the vertical and horizontal lines through its centre into four flat colours, on black.
Edges are sharp (a pixel takes the colour of the region containing its centre; no
anti-aliasing), and the shapes are defined in resolution-free units (the shorter image side is 1),
so any resolution gives the same picture.

The scene: one camera at the origin looking down +z (OpenCV), focal length = the shorter side in
pixels (the image spans 1 world unit at depth 1), the same view for train and test, ``flat=True``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import torch

from smgs.camera import Camera
from smgs.data.formats import SceneRequest
from smgs.data.images import MIN_SIDE
from smgs.data.scene import Scene, View
from smgs.ranges import Range

PATTERNS: tuple[str, ...] = ("circle4", "rect4", "oval4")

QUADRANT_COLORS: tuple[tuple[int, int, int], ...] = (
    (230, 57, 70),    # top-left: red
    (42, 157, 143),   # top-right: teal
    (69, 123, 230),   # bottom-left: blue
    (244, 200, 60),   # bottom-right: yellow
)
"""Four flat 8-bit colours, far apart from each other and from black."""

# Shape sizes in units of the shorter image side (centred coordinates X, Y in [-0.5, 0.5]).
CIRCLE_RADIUS = 0.35
RECT_HALF = (0.36, 0.24)      # half width, half height
OVAL_AXES = (0.42, 0.26)      # semi-axes along X and Y


def _coords(width: int, height: int) -> tuple[torch.Tensor, torch.Tensor]:
    s = min(width, height)
    y, x = torch.meshgrid(torch.arange(height, dtype=torch.float64), torch.arange(width, dtype=torch.float64),
                          indexing="ij")
    return (x + 0.5 - width / 2) / s, (y + 0.5 - height / 2) / s


def pattern_mask(name: str, width: int, height: int) -> torch.Tensor:
    """[H, W] bool: pixel centres inside the shape."""
    X, Y = _coords(width, height)
    if name == "circle4":
        return X * X + Y * Y <= CIRCLE_RADIUS ** 2
    if name == "rect4":
        return (X.abs() <= RECT_HALF[0]) & (Y.abs() <= RECT_HALF[1])
    if name == "oval4":
        return (X / OVAL_AXES[0]) ** 2 + (Y / OVAL_AXES[1]) ** 2 <= 1.0
    raise ValueError(f"unknown pattern {name!r}; known: {', '.join(PATTERNS)}")


def make_pattern(name: str, width: int = 128, height: int | None = None) -> torch.Tensor:
    """The target image, uint8 [H, W, 3]."""
    height = width if height is None else height
    inside = pattern_mask(name, width, height)
    X, Y = _coords(width, height)
    quadrant = (Y > 0).long() * 2 + (X > 0).long()           # 0 TL, 1 TR, 2 BL, 3 BR
    cols = torch.tensor(QUADRANT_COLORS, dtype=torch.uint8)
    img = cols[quadrant]
    img[~inside] = 0
    return img


def pattern_camera(width: int, height: int) -> Camera:
    f = float(min(width, height))
    K = torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])
    return Camera(K, torch.eye(4), width, height)


def pattern_scene(name: str, width: int = 128, height: int | None = None) -> Scene:
    """A flat scene whose single view (train = test) is the pattern. ``extent`` is 1 (the
    3DGS camera-extent rule degenerates for one camera; 1 is the size of the image at depth 1)."""
    height = width if height is None else height
    view = View(camera=pattern_camera(width, height), image=make_pattern(name, width, height), name=name)
    return Scene(name=name, train=[view], test=[view], extent=1.0, flat=True,
                 meta={"dataset": "patterns", "pattern": name, "width": width, "height": height,
                       "definition": "smgs.data.patterns (our own; the paper's images are unpublished)"})


def write_targets(out_dir: str | Path, width: int = 256) -> list[Path]:
    """Save the three targets as PNGs (docs/results/table1.md shows them); returns the paths."""
    from PIL import Image

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for name in PATTERNS:
        p = out / f"{name}.png"
        Image.fromarray(make_pattern(name, width).numpy()).save(p, optimize=True)
        paths.append(p)
    return paths


@dataclass(frozen=True)
class PatternFormat:
    """The 2D patterns as a scene format (``kind: pattern``): the scene's name is the pattern
    (``PATTERNS``), ``size`` its side in px."""

    size: int = 128

    RANGES: ClassVar[dict[str, Range]] = {"size": Range(MIN_SIDE, integer=True)}

    def inputs(self, request: SceneRequest) -> list:
        """No file: the scene is made from the config alone."""
        return []

    def load(self, request: SceneRequest) -> Scene:
        return pattern_scene(request.scene, self.size)
