"""The benchmark datasets as data: where their scenes lie under the data root, and their resolution
rules (``DatasetSpec``). Each registers by name beside the scene formats (``smgs.data.registry``);
its format (COLMAP for the paper's three) reads a scene's folder from it.

Resolution rules (their sources, and why each result records which: docs/usage.md, "Resolution rules"):

- ``paper``  (Softmax-GS): Mip-NeRF360 and T&T resized to width 1600 keeping the aspect ratio, from
  the full-resolution ``images`` with PIL BICUBIC (what 3DGS's ``-r -1`` does); never upsampled, so
  the 3DGS ``tandt_db`` T&T images (under 1600 px) stay native. Deep Blending at native resolution.
- ``3dgs``   (3DGS full_eval.py, gsplat/nerfbaselines benchmarks): Mip-NeRF360 ``images_4`` outdoor /
  ``images_2`` indoor JPEGs as shipped; T&T and DB ``images``; any image wider than 1600 -> 1600.
- ``gsplat`` (gsplat PR #507): Mip-NeRF360 downscaled 4x / 2x from the full-resolution images with
  PIL BICUBIC instead of the shipped JPEGs (about +0.3 dB against ``3dgs``).
- ``cpu``    a preset for machines without a GPU: max width 400 from the smallest shipped folder
  that is wide enough. Not a paper protocol; its label says so in every table it feeds.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping

from smgs.data.images import ResolutionRule
from smgs.data.rules import GENERIC_RULES
from smgs.data.errors import DatasetNotFoundError

DATA_ROOT_ENV = "SMGS_DATA_ROOT"


@dataclass(frozen=True, eq=False)
class DatasetSpec:
    """A benchmark dataset: where its scenes live under the data root and its resolution rules.

    format: the scene format of its scenes (a name in ``smgs.data.registry``: colmap, transforms).
    folders: candidate folders under the data root, first match wins (3DGS's tandt_db archive
        unpacks to tandt/ and db/; the Mip-NeRF360 archive to 360_v2/ when not renamed).
    scenes: the paper's scenes (the default grid); extra_scenes load too but are not in the grid.
    groups: scene -> group names used by per-group rules (Mip-NeRF360 indoor / outdoor).
    rules: rule name -> group ("*" = any scene) -> ResolutionRule.
    """

    name: str
    folders: tuple[str, ...]
    scenes: tuple[str, ...]
    rules: Mapping[str, Mapping[str, ResolutionRule]]
    groups: Mapping[str, tuple[str, ...]] = field(default_factory=dict)
    extra_scenes: tuple[str, ...] = ()
    layout: str = "<scene>/images/, <scene>/sparse/0/{cameras,images,points3D}.bin"
    format: str = "colmap"

    def group_of(self, scene: str) -> str:
        for g, members in self.groups.items():
            if scene in members:
                return g
        return "*"

    def rule(self, rule: str, scene: str) -> ResolutionRule:
        if rule not in self.rules:
            raise ValueError(f"dataset {self.name!r} has no resolution rule {rule!r}; "
                             f"expected one of {', '.join(self.rules)}")
        by_group = self.rules[rule]
        g = self.group_of(scene)
        return by_group[g] if g in by_group else by_group["*"]

    def scene_dir(self, data_root: str | Path, scene: str) -> Path:
        """The folder of ``scene``; a DatasetNotFoundError names every folder looked in."""
        if scene not in self.scenes + self.extra_scenes:
            raise ValueError(f"unknown {self.name} scene {scene!r}; expected one of "
                             f"{', '.join(self.scenes + self.extra_scenes)}")
        root = Path(data_root)
        looked = [root / f / scene for f in self.folders]
        for d in looked:
            if d.is_dir():
                return d
        raise DatasetNotFoundError(
            f"{self.name} scene {scene!r} not found; looked in {', '.join(str(d) for d in looked)}. "
            f"Expected {root}/{self.folders[0]}/{self.layout}")


MIPNERF360_OUTDOOR = ("bicycle", "garden", "stump", "flowers", "treehill")
MIPNERF360_INDOOR = ("bonsai", "counter", "kitchen", "room")

MIPNERF360 = DatasetSpec(
    name="mipnerf360",
    folders=("mipnerf360", "360_v2"),
    scenes=("bicycle", "bonsai", "counter", "garden", "kitchen", "room", "stump"),
    extra_scenes=("flowers", "treehill"),
    groups={"outdoor": MIPNERF360_OUTDOOR, "indoor": MIPNERF360_INDOOR},
    layout="<scene>/{images,images_2,images_4,images_8}/, <scene>/sparse/0/",
    rules={
        "paper": {"*": ResolutionRule("paper", images="images", max_width=1600,
                                      label="Softmax-GS paper: width 1600 from full-res images (PIL BICUBIC)")},
        "3dgs": {"outdoor": ResolutionRule("3dgs", images="images_4", max_width=1600,
                                           label="3DGS full_eval: JPEG images_4 (outdoor) as shipped"),
                 "indoor": ResolutionRule("3dgs", images="images_2", max_width=1600,
                                          label="3DGS full_eval: JPEG images_2 (indoor) as shipped")},
        "gsplat": {"outdoor": ResolutionRule("gsplat", images="images", factor=4,
                                             label="gsplat: full-res downscaled 4x, PIL BICUBIC (no JPEG)"),
                   "indoor": ResolutionRule("gsplat", images="images", factor=2,
                                            label="gsplat: full-res downscaled 2x, PIL BICUBIC (no JPEG)")},
        "cpu": {"*": GENERIC_RULES["cpu"]},
    })

TANDT = DatasetSpec(
    name="tandt",
    folders=("tandt", "tandt_db/tandt"),
    scenes=("train", "truck"),
    rules={
        "paper": {"*": ResolutionRule("paper", max_width=1600,
                                      label="Softmax-GS paper: width 1600 when wider (never upsampled)")},
        "3dgs": {"*": ResolutionRule("3dgs", max_width=1600, label="3DGS full_eval: images, -r -1")},
        "cpu": {"*": GENERIC_RULES["cpu"]},
    })

DEEPBLENDING = DatasetSpec(
    name="deepblending",
    folders=("db", "tandt_db/db"),
    scenes=("drjohnson", "playroom"),
    rules={
        "paper": {"*": ResolutionRule("paper", label="Softmax-GS paper: native resolution")},
        "3dgs": {"*": ResolutionRule("3dgs", max_width=1600, label="3DGS full_eval: images, -r -1")},
        "cpu": {"*": GENERIC_RULES["cpu"]},
    })


def resolve_data_root(data_root: str | Path | None = None) -> Path:
    """``data_root`` if given, else $SMGS_DATA_ROOT."""
    if data_root is None:
        data_root = os.environ.get(DATA_ROOT_ENV)
    if not data_root:
        raise DatasetNotFoundError(f"no data root: pass data_root or set ${DATA_ROOT_ENV} to the folder "
                                   "holding mipnerf360/, tandt/ and db/")
    root = Path(data_root).expanduser()
    if not root.is_dir():
        raise DatasetNotFoundError(f"data root {root} does not exist; expected it to hold mipnerf360/<scene>, "
                                   "tandt/<scene> and db/<scene> (COLMAP layouts as distributed)")
    return root
