"""What a scene format is, and what the harness asks of it (docs/adding-a-scene-format.md).

A scene format is a dataclass that is its own config: its fields are the keys of a run's ``dataset``
section besides the harness's own (``HARNESS_KEYS``), with their defaults, types and ``RANGES``
(``smgs.ranges``), so a wrong value is refused naming ``dataset.KEY`` before anything runs. It
makes a scene from a ``SceneRequest``, the run's neutral terms (the scene's name, the data root, the
protocol's resolution rule and hold-out), as a method reads ``RunSettings``. Formats register by name
(``smgs.data.registry``; plugins through the entry-point group ``smgs.datasets``).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol, Sequence, runtime_checkable

from smgs.data.datasets import DatasetSpec

if TYPE_CHECKING:   # a type only: importing the scene (torch) is left to the loaders
    from smgs.data.scene import Scene

HARNESS_KEYS: tuple[str, ...] = ("name", "kind", "scenes", "steps", "train")
"""The keys of a ``dataset`` section the harness reads itself: the dataset's name, its format
(``kind``), its scenes, its own step count and its overrides of the method's settings. Every other
key is the format's."""


@dataclass(frozen=True)
class SceneRequest:
    """What a run asks of a scene format, in terms every format reads the same way.

    dataset: the dataset's name (``configs/dataset/<name>.yaml``, or the format's own name).
    scene: the scene's name: one of the dataset's scenes, or the folder's name for a scene given
        by its folder.
    data_root: the folder that holds the benchmark datasets (None: ``$SMGS_DATA_ROOT``).
    rule: the protocol's resolution rule (paper, 3dgs, gsplat, cpu, native); None: the format's own.
    max_width: the width the ``cpu`` rule caps images at (``protocol.max_width``).
    test_every: every n-th name-sorted image is held out for testing (None or 0: none).
    layout: the benchmark dataset of that name where one is registered (``DatasetSpec``: where its
        scenes lie under the data root and its resolution rules), else None.
    """

    dataset: str
    scene: str
    data_root: str | None = None
    rule: str | None = None
    max_width: int | None = None
    test_every: int | None = 8
    layout: DatasetSpec | None = None

    def resolution(self, own: str | None) -> tuple[str | None, int | None]:
        """The rule a format applies (its own setting where it has one, else the protocol's) and the
        width that rule caps images at when it is ``cpu`` (None otherwise)."""
        rule = own or self.rule
        return rule, (self.max_width if rule == "cpu" and self.max_width else None)


@runtime_checkable
class SceneFormat(Protocol):
    """A scene format (a dataclass: its fields are its config). Only ``load`` is required."""

    def load(self, request: SceneRequest) -> Scene:
        """The scene ``request`` names, train and test views split by ``request.test_every``."""
        ...


@runtime_checkable
class ChecksScenes(Protocol):
    """Optional, beside ``SceneFormat``: the runner checks every scene of a sweep before any cell
    runs. ``check`` raises what ``load`` would raise about the scene's files (a
    ``smgs.data.SceneFormatError`` or ValueError naming the file and the fix), without decoding an
    image; ``missing`` says where the scene was looked for when it is not there (None when it is),
    which ``on_missing=skip`` may skip."""

    def check(self, request: SceneRequest) -> None:
        ...

    def missing(self, request: SceneRequest) -> str | None:
        ...


@runtime_checkable
class ListsInputs(Protocol):
    """Optional, beside ``SceneFormat``: the files ``load(request)`` reads (images, camera model,
    points), without decoding an image; the harness fingerprints them (``smgs.data.fingerprint``) to
    notice a scene changed on disk. A format that makes its scenes returns none."""

    def inputs(self, request: SceneRequest) -> Sequence[Path]:
        ...


def scene_inputs(fmt: SceneFormat, request: SceneRequest) -> dict[str, Any]:
    """The fingerprint of the files the format reads for ``request`` (``ListsInputs``); for a format
    that does not list them, a record saying its scenes are not fingerprinted."""
    from smgs.data.fingerprint import fingerprint, not_listed

    inputs = getattr(fmt, "inputs", None)
    if not callable(inputs):
        cls = type(fmt)
        return not_listed(f"scene format {cls.__module__}.{cls.__qualname__} lists no input files (inputs(request), "
                          "docs/adding-a-scene-format.md): a change on disk goes unnoticed")
    return fingerprint(inputs(request))


def make_scene(fmt: SceneFormat, request: SceneRequest, trajectory_between: int | None = None,
               where: str | None = None) -> Scene:
    """The format's scene, checked against the scene contract (``smgs.data.contract``: whatever the
    format, a ``SceneContractError`` naming ``where``, default ``describe_request``), with a video
    trajectory when ``trajectory_between`` is set: the scene's own where its format made one (the
    procedural scene's ring), else ``trajectory_between`` frames between consecutive test cameras (a
    flat scene, one fixed camera, has none)."""
    from smgs.data.contract import check_scene_contract

    scene = check_scene_contract(fmt.load(request), where or describe_request(fmt, request),
                                 needs_test=bool(request.test_every))
    if trajectory_between is not None and not scene.flat and not scene.trajectory:
        with_trajectory(scene, trajectory_between)
    return scene


def describe_request(fmt: SceneFormat, request: SceneRequest) -> str:
    """The scene ``request`` asks of ``fmt``, for an error: its name, dataset and format class."""
    cls = type(fmt)
    return f"scene {request.scene!r} of {request.dataset!r} (scene format {cls.__module__}.{cls.__qualname__})"


def with_trajectory(scene: Scene, between: int) -> None:
    """A trajectory of ``between`` frames between consecutive test cameras (train cameras where the
    scene tests fewer than 2): the consistency protocol's own interpolation (slerp, near-static
    frames dropped), so a scene's trajectory and the Table 4 scoring agree frame for frame."""
    from smgs.data.trajectory import interpolate_trajectory

    keys = [v.camera for v in (scene.test if len(scene.test) >= 2 else scene.train)]
    traj = interpolate_trajectory(keys, between)
    scene.trajectory = traj.cameras()
    scene.meta["trajectory"] = (f"{between} frames between consecutive {'test' if len(scene.test) >= 2 else 'train'} "
                                f"cameras, {len(traj.dropped)} near-static frames dropped: {len(scene.trajectory)} frames")


def check_scene_with(fmt: SceneFormat, request: SceneRequest) -> None:
    """``fmt.check(request)`` where the format checks its scenes (``ChecksScenes``)."""
    check = getattr(fmt, "check", None)
    if callable(check):
        check(request)


def missing_scene(fmt: SceneFormat, request: SceneRequest) -> str | None:
    """``fmt.missing(request)`` where the format can say so (a format that makes its scenes is never
    missing them)."""
    missing = getattr(fmt, "missing", None)
    return missing(request) if callable(missing) else None


def format_fields(cls: type) -> tuple[str, ...]:
    """The config keys of a format class (its dataclass fields)."""
    return tuple(f.name for f in dataclasses.fields(cls))
