"""A scene: train/test views, optional SfM points, background and video trajectory.

A scene declares what it has (``capabilities``); a method declares what it needs, and a run leaves
out every stage that nobody needs.
"""

from __future__ import annotations

import posixpath
from dataclasses import dataclass, field

import torch

from smgs.camera import Camera
from smgs.data.errors import DatasetNotFoundError, MissingImageError, SceneFormatError  # noqa: F401 (their old home)




@dataclass
class View:
    """One posed image. ``image`` is uint8 [H, W, 3] (8-bit, as stored on disk); ``rgb`` gives
    float [H, W, 3] in [0, 1]."""

    camera: Camera
    image: torch.Tensor
    name: str

    def __post_init__(self) -> None:
        h, w = self.image.shape[:2]
        if (w, h) != (self.camera.width, self.camera.height):
            raise ValueError(f"view {self.name!r}: image is {w}x{h} but its camera is "
                             f"{self.camera.width}x{self.camera.height}")

    @property
    def rgb(self) -> torch.Tensor:
        img = self.image
        return img.float() / 255.0 if img.dtype == torch.uint8 else img.float()


@dataclass
class Scene:
    """Everything a method may take from a dataset.

    extent: the 3DGS ``cameras_extent`` (1.1 × the largest distance of a train camera centre from
        their mean), the unit of the position learning rate and of the size thresholds.
    flat: the scene is a 2D target seen by one fixed camera (no view dependence: SH degree 0).
    meta: provenance recorded in every result (dataset, resolution rule, downscale factor,
        resampling, split rule, source path).
    """

    name: str
    train: list[View]
    test: list[View]
    extent: float
    points: torch.Tensor | None = None          # [M, 3] SfM points
    point_colors: torch.Tensor | None = None    # [M, 3] in [0, 1]
    background: torch.Tensor | None = None      # [3] in [0, 1]
    trajectory: list[Camera] | None = None      # video path for view-consistency metrics
    flat: bool = False
    meta: dict = field(default_factory=dict)

    @property
    def capabilities(self) -> set[str]:
        caps = set()
        if self.points is not None:
            caps.add("sfm_points")
        if self.background is not None:
            caps.add("background")
        if self.trajectory:
            caps.add("trajectory")
        if not self.flat:
            caps.add("view_dependence")
        return caps


def view_key(name: str) -> str:
    """A view's name as the path it names: separators as ``/``, ``./`` and ``a/../`` resolved, so
    ``./image010.png`` and ``image010.png`` are one image (a view's identity when names must be
    unique: the formats' checks and the scene contract, ``smgs.data.contract``)."""
    return posixpath.normpath(str(name).replace("\\", "/"))


def camera_extent(cameras: list[Camera]) -> float:
    """3DGS ``getNerfppNorm`` radius: 1.1 × max distance of the camera centres from their mean."""
    centers = torch.stack([c.center.double() for c in cameras])
    d = (centers - centers.mean(0)).norm(dim=1).max().item()
    return 1.1 * d if d > 0 else 1.0


def split_every(names: list[str], test_every: int | None = 8) -> tuple[list[int], list[int]]:
    """The LLFF / Mip-NeRF360 / 3DGS hold-out: over the **name-sorted** list, index % test_every == 0
    is test. Returns (train, test) indices into ``names`` (not into the sorted list).
    ``test_every`` None or 0 puts every image in train."""
    order = sorted(range(len(names)), key=lambda i: names[i])
    if not test_every:
        return order, []
    test = [i for k, i in enumerate(order) if k % test_every == 0]
    train = [i for k, i in enumerate(order) if k % test_every != 0]
    return train, test


def check_split(where: object, n_images: int, n_train: int, split: str) -> None:
    """A scene must leave at least one image to train on: a scene of one image (with the every-8th
    hold-out it is the test view) is refused naming the folder, before training pops from an
    empty list of views."""
    if n_train == 0:
        raise SceneFormatError(f"{where}: {n_images} image(s) and none left to train on after the split "
                               f"({split}); a scene needs at least 2 images (one to train on, one to test) and "
                               "a hold-out of every n-th image with n ≥ 2 (protocol.test_every)")


def split_description(test_every: int | None) -> str:
    if not test_every:
        return "no test split (all images train)"
    return f"every {test_every}th of the name-sorted images (index % {test_every} == 0) is test"

