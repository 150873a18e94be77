"""From a cell's config to a Scene: the one place the runner turns its dataset section into a scene
format and a request (``smgs.data.formats``), whatever the format."""

from __future__ import annotations

from protocols.sections import EvalConfig, ProtocolConfig
from smgs.data.formats import (HARNESS_KEYS, SceneFormat, SceneRequest, check_scene_with, make_scene,
                               missing_scene, scene_inputs)
from smgs.data.scene import DatasetNotFoundError, Scene

DatasetMissing = DatasetNotFoundError

# frames between consecutive test cameras in the consistency video (paper supp. Sec. 7)
TRAJECTORY_BETWEEN = 128


def scene_format(cfg: dict) -> tuple[SceneFormat, SceneRequest]:
    """The cell's scene format, set up from its ``dataset`` section (every key but the harness's own,
    ``smgs.data.formats.HARNESS_KEYS``, is the format's: a wrong one is refused naming
    ``dataset.KEY``), and what the cell asks of it: the scene, the data root, the protocol's
    resolution rule and hold-out, and the benchmark layout of the dataset's name where one is
    registered (``smgs.data.registry``)."""
    from smgs.data.registry import dataset_layout, format_class
    from smgs.train.config import from_dict

    ds = cfg["dataset"]
    own = {k: v for k, v in ds.items() if k not in HARNESS_KEYS}
    fmt = from_dict(format_class(str(ds["kind"])), own, _where="dataset")
    proto = ProtocolConfig.of(cfg)
    request = SceneRequest(dataset=str(ds["name"]), scene=str(cfg["scene"]), data_root=cfg.get("data_root"),
                           rule=proto.resolution, max_width=proto.max_width, test_every=proto.test_every,
                           layout=dataset_layout(str(ds["name"])))
    return fmt, request


def load_scene_for(cfg: dict) -> Scene:
    """The scene of a cell (dataset section + the cell's scene name + protocol), with the video
    trajectory the consistency metrics follow when they are on."""
    fmt, request = scene_format(cfg)
    return make_scene(fmt, request, TRAJECTORY_BETWEEN if EvalConfig.of(cfg).consistency else None,
                      where=scene_origin(cfg, fmt))


def scene_origin(cfg: dict, fmt: SceneFormat) -> str:
    """The cell's scene as the config names it, for an error: ``dataset.path=...`` (or the dataset
    and scene), the format's kind and, for a plug-in's, its distribution."""
    from smgs.data.registry import plugin_source

    kind = str(cfg["dataset"]["kind"])
    source = plugin_source(kind)
    return f"{_scene_key(cfg, fmt)} (scene format {kind!r}{', ' + source if source else ''})"


def cell_inputs(cfg: dict) -> dict | None:
    """The fingerprint of the files the cell's scene is read from (``smgs.data.formats.scene_inputs``),
    compared with a finished result's to skip it and recorded with the new one. None where they
    cannot be listed now (the scene is missing or broken: its load says why, or a finished result
    stays as it is)."""
    try:
        fmt, request = scene_format(cfg)
        return scene_inputs(fmt, request)
    except Exception:   # a plug-in's inputs() may raise anything; the cell's own load names the problem
        return None


def scene_problem(cfg: dict) -> str | None:
    """Why the cell's scene, which exists (``check_available``), cannot give a meaningful result
    (None when it can): the format's own check (``smgs.data.formats.ChecksScenes``), done without
    decoding an image, naming the file and the fix, and what a ``dataset.path`` probably meant."""
    from smgs.data.scene import SceneFormatError

    fmt, request = scene_format(cfg)
    try:
        check_scene_with(fmt, request)
    except (SceneFormatError, DatasetNotFoundError, ValueError) as e:
        suggestion = getattr(fmt, "suggestion", None)
        return f"{_scene_key(cfg, fmt)}: {e}{suggestion() if callable(suggestion) else ''}"
    return None


def _scene_key(cfg: dict, fmt: SceneFormat) -> str:
    path = getattr(fmt, "path", None)
    return f"dataset.path={path}" if path else f"{cfg['dataset']['name']} scene {cfg['scene']}"


def check_available(cfg: dict) -> str | None:
    """None if the cell's data is there, else a sentence naming where it was looked for (and, for a
    scene of the paper's datasets, the ``smgs download`` command that gets it)."""
    fmt, request = scene_format(cfg)
    missing = missing_scene(fmt, request)
    if missing is None or getattr(fmt, "path", None):
        return missing
    return missing + download_hint(request.dataset, request.scene, cfg.get("data_root"))


def download_hint(dataset: str, scene: str, data_root: str | None) -> str:
    """For a missing scene of the paper's datasets, the ``smgs download`` command that gets it."""
    import os
    from pathlib import Path

    from smgs.data.datasets import DATA_ROOT_ENV
    from smgs.data.download import SOURCES, download_command

    if dataset not in SOURCES:
        return ""
    root = data_root or os.environ.get(DATA_ROOT_ENV)
    where = Path(root).expanduser().absolute() if root else "DIR"
    return (f"; get it with: {download_command((dataset,), (scene,), where)}"
            + ("" if root else f" and set {DATA_ROOT_ENV}=DIR"))
