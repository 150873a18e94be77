"""The scene formats that read a folder: COLMAP (``colmap``) and transforms.json (``transforms``).

A folder is given by ``path`` (a user's own scene), or, without one, is the benchmark dataset's
scene under the data root (``SceneRequest.layout``: the paper's Mip-NeRF360, Tanks&Temples and Deep
Blending are COLMAP scenes so). The resolution rule is the format's ``rule`` where set, else the
protocol's; the default is ``paper`` for a benchmark (its own rule table, ``DatasetSpec.rules``)
and ``3dgs`` for a user's scene (``smgs.data.rules.GENERIC_RULES``). ``images``, ``factor``,
``max_width`` and ``resample`` override the rule.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

from smgs.data.datasets import resolve_data_root
from smgs.data.formats import SceneRequest
from smgs.data.images import MIN_SIDE, ResolutionRule
from smgs.data.scene import DatasetNotFoundError, Scene
from smgs.ranges import Range


@dataclass(frozen=True)
class FolderFormat:
    """The keys both folder formats take (their meaning: the module's docstring)."""

    path: str | None = None
    rule: str | None = None
    images: str | None = None
    factor: float | None = None
    max_width: int | None = None
    resample: str | None = None

    RANGES: ClassVar[dict[str, Range]] = {"factor": Range(0, lo_open=True, optional=True),
                                          "max_width": Range(MIN_SIDE, integer=True, optional=True)}

    def folder(self, request: SceneRequest) -> Path:
        """The scene's folder; a benchmark scene that is not there raises ``DatasetNotFoundError``
        naming every folder looked in."""
        if self.path:
            return Path(self.path)
        if request.layout is None:
            raise ValueError(f"dataset {request.dataset!r} needs the scene's folder: add dataset.path=/path/to/scene "
                             "(or path=... to smgs.data.load_scene)")
        return request.layout.scene_dir(resolve_data_root(request.data_root), request.scene)

    def source(self, request: SceneRequest) -> tuple[Path, ResolutionRule | str, dict[str, Any], dict[str, Any]]:
        """(folder, resolution rule, the rule's overrides, what a benchmark scene records beside)."""
        rule, cpu_width = request.resolution(self.rule)
        over = dict(images=self.images, factor=self.factor, max_width=self.max_width or cpu_width,
                    resample=self.resample)
        folder = self.folder(request)   # without a path, the benchmark's (no layout: refused there)
        if self.path:
            return folder, rule or "3dgs", over, {}
        custom = {k: v for k, v in over.items() if v is not None}
        root = resolve_data_root(request.data_root)
        meta = {"dataset": request.dataset, "scene": request.scene, "data_root": str(root),
                **({"rule_overrides": custom} if custom else {})}
        return folder, request.layout.rule(rule or "paper", request.scene), over, {"name": request.scene, "meta": meta}

    def missing(self, request: SceneRequest) -> str | None:
        if self.path:
            return None if Path(self.path).exists() else f"{request.dataset}: {self.path} does not exist"
        try:
            self.folder(request)
        except DatasetNotFoundError as e:
            return str(e)
        return None

    def suggestion(self) -> str:
        """For a ``path`` inside a scene (its images/ or sparse/ folder): the scene it is in."""
        if not self.path or self.is_scene(Path(self.path)):
            return ""
        for up in Path(self.path).resolve().parents[:2]:
            if self.is_scene(up):
                return f" (did you mean dataset.path={up}?)"
        return ""

    @staticmethod
    def is_scene(folder: Path) -> bool:
        return False


@dataclass(frozen=True)
class ColmapFormat(FolderFormat):
    """A COLMAP scene: <folder>/images/ (or images_N) and sparse/0/, undistorted PINHOLE cameras."""

    def load(self, request: SceneRequest) -> Scene:
        from smgs.data.colmap import load_colmap

        folder, rule, over, extra = self.source(request)
        return load_colmap(folder, rule=rule, test_every=request.test_every, **extra, **over)

    def check(self, request: SceneRequest) -> None:
        from smgs.data.colmap import colmap_sources

        folder, rule, over, _ = self.source(request)
        colmap_sources(folder, rule=rule, test_every=request.test_every, with_points=False, **over)

    def inputs(self, request: SceneRequest) -> list[Path]:
        """The model's files and every image it lists, from the folder the rule reads."""
        from smgs.data.colmap import colmap_sources, model_files

        folder, rule, over, _ = self.source(request)
        sources = colmap_sources(folder, rule=rule, test_every=request.test_every, with_points=False, **over)
        return [*model_files(sources.model_dir), *sources.paths]

    @staticmethod
    def is_scene(folder: Path) -> bool:
        return (folder / "sparse").is_dir()


@dataclass(frozen=True)
class TransformsFormat(FolderFormat):
    """A Blender / instant-ngp scene: <folder>/transforms.json (or transforms_{train,test}.json).
    ``undistort``: undistort a non-zero distortion with OpenCV; false refuses such a scene."""

    undistort: bool = True

    def load(self, request: SceneRequest) -> Scene:
        from smgs.data.transforms import load_transforms

        folder, rule, over, extra = self.source(request)
        return load_transforms(folder, rule=rule, test_every=request.test_every, undistort=self.undistort,
                               **extra, **over)

    def check(self, request: SceneRequest) -> None:
        from smgs.data.transforms import transforms_sources

        folder, rule, over, _ = self.source(request)
        transforms_sources(folder, rule=rule, test_every=request.test_every, **over)

    def inputs(self, request: SceneRequest) -> list[Path]:
        """The transforms files and every frame's image."""
        from smgs.data.transforms import transforms_sources

        folder, rule, over, _ = self.source(request)
        sources = transforms_sources(folder, rule=rule, test_every=request.test_every, **over)
        return [*sources.json_files, *(e.path for e in sources.entries)]

    @staticmethod
    def is_scene(folder: Path) -> bool:
        return (folder / "transforms.json").is_file()
