"""Scene formats and benchmark datasets by name, imported lazily (the way methods register,
``baselines.registry``); docs/adding-a-scene-format.md.

An entry is of one of two kinds: a scene format (a dataclass with ``load(request) -> Scene``,
``smgs.data.formats``: colmap, transforms, procedural, pattern), named by a dataset's ``kind``; or a
benchmark dataset (a ``DatasetSpec``: its scenes under the data root in one format, and its
resolution rules: mipnerf360, tandt, deepblending), named by a dataset's ``name``. Lookup order:
entries registered in this process (``register``), the built-ins, then third-party plugins from the
entry-point group ``smgs.datasets``, declared in their own package metadata::

    [project.entry-points."smgs.datasets"]
    my_format = "my_pkg.scenes:MyFormat"          # a scene format class
    my_benchmark = "my_pkg.scenes:MY_BENCHMARK"   # a DatasetSpec

Listing never imports an entry's module; it is imported when the entry is used.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import TYPE_CHECKING, Any

from smgs.data.datasets import DatasetSpec
from smgs.data.formats import SceneFormat, SceneRequest, check_scene_with, format_fields, make_scene
from smgs.plugins import Registry
from smgs.spelling import did_you_mean

if TYPE_CHECKING:   # a type only: importing the scene (torch) is left to the loaders
    from smgs.data.scene import Scene

ENTRY_POINT_GROUP = "smgs.datasets"

BUILTIN_FORMATS: dict[str, str] = {
    "colmap": "smgs.data.folder_formats:ColmapFormat",
    "transforms": "smgs.data.folder_formats:TransformsFormat",
    "procedural": "smgs.data.procedural:ProceduralFormat",
    "pattern": "smgs.data.patterns:PatternFormat",
}
BUILTIN_DATASETS: dict[str, str] = {
    "mipnerf360": "smgs.data.datasets:MIPNERF360",
    "tandt": "smgs.data.datasets:TANDT",
    "deepblending": "smgs.data.datasets:DEEPBLENDING",
}
BUILTINS: dict[str, str] = {**BUILTIN_FORMATS, **BUILTIN_DATASETS}

_REGISTRY = Registry(ENTRY_POINT_GROUP, BUILTINS, "scene format or dataset")


def register(name: str, entry: type | DatasetSpec, overwrite: bool = False) -> None:
    """Register a scene format class or a benchmark dataset in this process (tests, notebooks);
    it overrides a built-in or plugin of that name."""
    _REGISTRY.register(name, entry, overwrite)


def unregister(name: str) -> None:
    _REGISTRY.unregister(name)


def list_names() -> list[str]:
    """Every scene format and benchmark dataset name known here (built-ins, registered, plugins)."""
    return _REGISTRY.names()


def plugin_source(name: str) -> str | None:
    """``plugin <distribution>`` for an entry from the entry-point group, None for the others."""
    return _REGISTRY.plugin_source(name)


def get(name: str) -> Any:
    """The entry registered as ``name`` (imported now); a KeyError lists the known names."""
    try:
        return _REGISTRY.get(name)
    except KeyError:
        raise KeyError(f"unknown scene format or dataset {name!r}; known: {', '.join(list_names())}") from None


def get_dataset(name: str) -> DatasetSpec:
    """The benchmark dataset ``name``; a ValueError lists the known ones."""
    try:
        entry = _REGISTRY.get(name)
    except KeyError:
        entry = None
    if not isinstance(entry, DatasetSpec):
        raise ValueError(f"unknown dataset {name!r}; the built-in benchmark datasets: {', '.join(BUILTIN_DATASETS)}"
                         + (" (and plugins: smgs list datasets)" if set(list_names()) - set(BUILTINS) else ""))
    return entry


def dataset_layout(name: str) -> DatasetSpec | None:
    """The benchmark dataset registered as ``name``, None where there is none (a user's own scene,
    a format's generated scenes)."""
    try:
        return get_dataset(name)
    except ValueError:
        return None


def default_scenes(kind: str, name: str) -> tuple[str, ...]:
    """The scenes a dataset runs when its config lists none and names no folder: a benchmark's
    paper scenes, or those its format makes (a class attribute ``SCENES``)."""
    layout = dataset_layout(name)
    return layout.scenes if layout is not None else tuple(getattr(format_class(kind), "SCENES", ()))


def format_class(kind: str) -> type:
    """The scene format class of ``kind`` (a benchmark dataset's name gives its format), checked to
    be a dataclass with ``load``."""
    try:
        entry = get(kind)
    except KeyError as e:
        raise ValueError(f"unknown scene kind {kind!r}; known: {', '.join(list_names())} "
                         "(docs/adding-a-scene-format.md)") from e
    if isinstance(entry, DatasetSpec):
        return format_class(entry.format)
    if not (isinstance(entry, type) and dataclasses.is_dataclass(entry) and callable(getattr(entry, "load", None))):
        raise _REGISTRY.wrong_kind(kind, entry, "a dataclass with load(request) -> Scene (its fields are its config)",
                                   "docs/adding-a-scene-format.md")
    return entry


def scene_format(kind: str, dataset: str | None = None, scene: str | None = None, *,
                 data_root: str | Path | None = None, test_every: int | None = 8,
                 **settings: Any) -> tuple[SceneFormat, SceneRequest]:
    """The format of ``kind`` set up with its own ``settings`` (its fields: path, rule, n_views, ...)
    and the request for ``scene`` of ``dataset`` (default: ``kind``; a benchmark dataset's name as
    ``kind`` is that dataset in its format)."""
    cls = format_class(kind)
    unknown = sorted(set(settings) - set(format_fields(cls)))
    if unknown:
        raise ValueError(f"scene format {kind!r} takes no {', '.join(unknown)}"
                         f"{did_you_mean(unknown, format_fields(cls), 'dataset')}; its settings: "
                         f"{', '.join(format_fields(cls))}")
    dataset = dataset or kind
    layout = dataset_layout(dataset)
    if scene is None and layout is not None:
        raise ValueError(f"dataset {dataset!r} needs a scene: one of {', '.join(layout.scenes + layout.extra_scenes)}")
    request = SceneRequest(dataset=dataset, scene=scene or dataset, data_root=None if data_root is None else str(data_root),
                           test_every=test_every, layout=layout)
    return cls(**settings), request


def load_scene(kind: str, scene: str | None = None, *, dataset: str | None = None, data_root: str | Path | None = None,
               test_every: int | None = 8, trajectory_between: int | None = None, **settings: Any) -> Scene:
    """A scene from plain values (``scene_format`` says which go where): e.g.
    ``load_scene("colmap", path="/my/scene", rule="cpu")``, ``load_scene("procedural", n_views=8)``,
    ``load_scene("tandt", "truck", data_root=ROOT, rule="3dgs")``. ``trajectory_between``: a video
    trajectory through the test cameras with that many frames between consecutive ones (the
    paper's consistency protocol uses 128)."""
    fmt, request = scene_format(kind, dataset, scene, data_root=data_root, test_every=test_every, **settings)
    return make_scene(fmt, request, trajectory_between)


def check_scene(kind: str, scene: str | None = None, *, dataset: str | None = None,
                data_root: str | Path | None = None, test_every: int | None = 8, **settings: Any) -> None:
    """Raise what ``load_scene`` with the same arguments would raise about the scene's files,
    without decoding an image, where the format checks its scenes (``smgs.data.formats.ChecksScenes``)."""
    fmt, request = scene_format(kind, dataset, scene, data_root=data_root, test_every=test_every, **settings)
    check_scene_with(fmt, request)
