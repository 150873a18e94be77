"""Dataset protocols as data, and ``load_scene``: the one entry point the protocol runner calls.

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
from typing import Mapping, Sequence

from smgs.data.images import ResolutionRule
from smgs.data.rules import GENERIC_RULES
from smgs.data.scene import DatasetNotFoundError, Scene

DATA_ROOT_ENV = "SMGS_DATA_ROOT"


@dataclass(frozen=True, eq=False)
class DatasetSpec:
    """A benchmark dataset: where its scenes live under the data root and its resolution rules.

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

DATASETS: dict[str, DatasetSpec] = {
    "mipnerf360": DatasetSpec(
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
        }),
    "tandt": DatasetSpec(
        name="tandt",
        folders=("tandt", "tandt_db/tandt"),
        scenes=("train", "truck"),
        rules={
            "paper": {"*": ResolutionRule("paper", max_width=1600,
                                          label="Softmax-GS paper: width 1600 when wider (never upsampled)")},
            "3dgs": {"*": ResolutionRule("3dgs", max_width=1600, label="3DGS full_eval: images, -r -1")},
            "cpu": {"*": GENERIC_RULES["cpu"]},
        }),
    "deepblending": DatasetSpec(
        name="deepblending",
        folders=("db", "tandt_db/db"),
        scenes=("drjohnson", "playroom"),
        rules={
            "paper": {"*": ResolutionRule("paper", label="Softmax-GS paper: native resolution")},
            "3dgs": {"*": ResolutionRule("3dgs", max_width=1600, label="3DGS full_eval: images, -r -1")},
            "cpu": {"*": GENERIC_RULES["cpu"]},
        }),
}


def get_dataset(name: str) -> DatasetSpec:
    if name not in DATASETS:
        raise ValueError(f"unknown dataset {name!r}; expected one of {', '.join(DATASETS)}")
    return DATASETS[name]


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


def load_dataset_scene(dataset: str, scene: str, data_root: str | Path | None = None, rule: str = "paper",
                       test_every: int | None = 8, **overrides) -> Scene:
    """A benchmark scene under a named resolution rule; ``overrides`` go to ``load_colmap``
    (images, factor, max_width, resample, workers)."""
    from smgs.data.colmap import load_colmap

    spec = get_dataset(dataset)
    root = resolve_data_root(data_root)
    sdir = spec.scene_dir(root, scene)
    res = spec.rule(rule, scene)
    custom = {k: v for k, v in overrides.items() if k in ("images", "factor", "max_width", "resample") and v is not None}
    return load_colmap(sdir, rule=res, test_every=test_every, name=scene,
                       meta={"dataset": dataset, "scene": scene, "data_root": str(root),
                             **({"rule_overrides": custom} if custom else {})},
                       **overrides)


SCENE_KINDS = ("colmap", "transforms", "procedural") + tuple(DATASETS)


def load_scene(kind: str, *, path: str | Path | None = None, dataset: str | None = None,
               scene: str | None = None, data_root: str | Path | None = None, rule: str | None = None,
               images: str | None = None, factor: float | None = None, max_width: int | None = None,
               resample: str | None = None, test_every: int | None = 8, undistort: bool = True,
               n_views: int = 24, size: Sequence[int] = (128, 96), seed: int = 0,
               trajectory_between: int | None = None, workers: int | None = None) -> Scene:
    """Build a scene from plain config values.

    kind: "procedural" (n_views, size, seed); "colmap" with ``path`` (a user's scene) or with
        ``dataset`` + ``scene`` (a benchmark scene under ``data_root`` / $SMGS_DATA_ROOT);
        "transforms" with ``path``; or a dataset name ("mipnerf360", "tandt", "deepblending")
        with ``scene``.
    rule: resolution rule name (datasets: "paper" default, "3dgs", "gsplat", "cpu"; a user's scene:
        "3dgs" default, "native", "paper", "cpu"); images / factor / max_width / resample override it.
    trajectory_between: if set, a video trajectory through the test cameras with that many frames
        between consecutive ones (the paper's consistency protocol uses 128).
    """
    if kind not in SCENE_KINDS:
        raise ValueError(f"unknown scene kind {kind!r}; expected one of {', '.join(SCENE_KINDS)}")
    if kind in DATASETS:
        dataset, kind = kind, "colmap"
    if kind == "procedural":
        from smgs.data.procedural import make_procedural_scene
        s = make_procedural_scene(n_views=n_views, size=tuple(size), seed=seed, test_every=test_every)
    elif kind == "colmap":
        overrides = dict(images=images, factor=factor, max_width=max_width, resample=resample, workers=workers)
        if dataset is not None:
            if scene is None:
                raise ValueError(f"dataset {dataset!r} needs a scene: one of {', '.join(get_dataset(dataset).scenes)}")
            s = load_dataset_scene(dataset, scene, data_root, rule or "paper", test_every, **overrides)
        else:
            if path is None:
                raise ValueError("kind='colmap' needs path=<scene folder> or dataset=<name> and scene=<name>")
            from smgs.data.colmap import load_colmap
            s = load_colmap(path, rule=rule or "3dgs", test_every=test_every, **overrides)
    else:
        if path is None:
            raise ValueError("kind='transforms' needs path=<folder with transforms.json, or the file>")
        from smgs.data.transforms import load_transforms
        s = load_transforms(path, images=images, rule=rule or "3dgs", factor=factor, max_width=max_width,
                            resample=resample, test_every=test_every, undistort=undistort, workers=workers)
    if trajectory_between is not None:
        # The consistency protocol's own interpolation (slerp, near-static frames dropped), so a
        # scene's trajectory and the Table 4 scoring agree frame for frame.
        from smgs.data.trajectory import interpolate_trajectory
        keys = [v.camera for v in (s.test if len(s.test) >= 2 else s.train)]
        traj = interpolate_trajectory(keys, trajectory_between)
        s.trajectory = traj.cameras()
        s.meta["trajectory"] = (f"{trajectory_between} frames between consecutive "
                                f"{'test' if len(s.test) >= 2 else 'train'} cameras, {len(traj.dropped)} "
                                f"near-static frames dropped: {len(s.trajectory)} frames")
    return s


def check_scene(kind: str, *, path: str | Path | None = None, dataset: str | None = None, scene: str | None = None,
                data_root: str | Path | None = None, rule: str | None = None, images: str | None = None,
                factor: float | None = None, max_width: int | None = None, resample: str | None = None,
                test_every: int | None = 8, n_views: int = 24, **unused: object) -> None:
    """Raise what ``load_scene`` with the same arguments would raise about the scene's files, without
    decoding an image (the other arguments of ``load_scene`` are accepted and not needed): a folder
    that is no scene, a model or transforms file that cannot give meaningful views (broken
    intrinsics or poses, an image listed twice), a missing image, a split with nothing to train on,
    images under ``smgs.data.images.MIN_SIDE`` px. The runner calls it for every scene of a sweep
    before any cell runs."""
    if kind not in SCENE_KINDS:
        raise ValueError(f"unknown scene kind {kind!r}; expected one of {', '.join(SCENE_KINDS)}")
    if kind in DATASETS:
        dataset, kind = kind, "colmap"
    if kind == "procedural":
        from smgs.data.procedural import check_procedural_split
        check_procedural_split(n_views, test_every)
        return
    over = dict(images=images, factor=factor, max_width=max_width, resample=resample)
    if kind == "colmap":
        from smgs.data.colmap import colmap_sources
        if dataset is not None:
            spec = get_dataset(dataset)
            colmap_sources(spec.scene_dir(resolve_data_root(data_root), str(scene)), rule=spec.rule(rule or "paper", str(scene)),
                           test_every=test_every, with_points=False, **over)
        else:
            colmap_sources(path, rule=rule or "3dgs", test_every=test_every, with_points=False, **over)
        return
    from smgs.data.transforms import transforms_sources
    transforms_sources(path, rule=rule or "3dgs", test_every=test_every, **over)
