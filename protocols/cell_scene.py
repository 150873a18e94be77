"""From a cell's config to a Scene: the one place the runner turns dataset config into a loader call."""

from __future__ import annotations

from protocols.sections import EvalConfig, ProtocolConfig
from smgs.data.scene import DatasetNotFoundError, Scene

DatasetMissing = DatasetNotFoundError

# frames between consecutive test cameras in the consistency video (paper supp. Sec. 7)
TRAJECTORY_BETWEEN = 128


def _rule(cfg: dict) -> tuple[str, int | None]:
    """The resolution rule name and, for the cpu preset, its maximum width."""
    proto = ProtocolConfig.of(cfg)
    rule = cfg["dataset"].get("rule") or proto.resolution
    return str(rule), (proto.max_width if rule == "cpu" and proto.max_width else None)


def _scene_args(cfg: dict) -> dict:
    """The arguments of ``smgs.data.load_scene`` (and ``check_scene``) for a cell's scene: its kind
    first, then keywords."""
    ds = cfg["dataset"]
    kind = ds["kind"]
    test_every = ProtocolConfig.of(cfg).test_every
    if kind == "procedural":
        return dict(kind="procedural", n_views=int(ds["n_views"]), size=(int(ds["width"]), int(ds["height"])),
                    test_every=test_every)
    rule, max_width = _rule(cfg)
    traj = TRAJECTORY_BETWEEN if EvalConfig.of(cfg).consistency else None
    common = dict(rule=rule, max_width=max_width, test_every=test_every, trajectory_between=traj)
    if ds.get("path"):
        return dict(kind=kind, path=ds["path"], **common)
    return dict(kind=ds["name"], scene=str(cfg["scene"]), data_root=cfg.get("data_root"), **common)


def load_scene_for(cfg: dict) -> Scene:
    """The scene of a cell (dataset group config + the cell's scene name + protocol)."""
    from smgs.data.datasets import load_scene

    ds = cfg["dataset"]
    if ds["kind"] == "pattern":
        from smgs.data.patterns import pattern_scene

        return pattern_scene(str(cfg["scene"]), int(ds.get("size", 128)))
    args = _scene_args(cfg)
    return load_scene(args.pop("kind"), **args)


def scene_problem(cfg: dict) -> str | None:
    """Why the cell's scene, which exists (``check_available``), cannot give a meaningful result
    (None when it can): the loader's own error, found without decoding an image, naming the file
    and the fix, and the folder a ``dataset.path`` probably meant."""
    from smgs.data.datasets import check_scene
    from smgs.data.scene import SceneFormatError

    if cfg["dataset"]["kind"] == "pattern":
        return None
    args = _scene_args(cfg)
    try:
        check_scene(args.pop("kind"), **args)
    except (SceneFormatError, DatasetNotFoundError, ValueError) as e:
        return f"{_scene_key(cfg)}: {e}{_meant(cfg)}"
    return None


def _scene_key(cfg: dict) -> str:
    ds = cfg["dataset"]
    return f"dataset.path={ds['path']}" if ds.get("path") else f"{ds['name']} scene {cfg['scene']}"


def _meant(cfg: dict) -> str:
    """For a ``dataset.path`` inside a scene (its images/ or sparse/ folder): the scene it is in."""
    from pathlib import Path

    def is_scene(folder: Path) -> bool:
        return (folder / "sparse").is_dir() or (folder / "transforms.json").is_file()

    path = cfg["dataset"].get("path")
    if not path or is_scene(Path(path)):
        return ""
    for up in Path(path).resolve().parents[:2]:
        if is_scene(up):
            return f" (did you mean dataset.path={up}?)"
    return ""


def check_available(cfg: dict) -> str | None:
    """None if the cell's data is there, else a sentence naming the folder looked in and the layout."""
    ds = cfg["dataset"]
    if ds["kind"] in ("pattern", "procedural"):
        return None
    from pathlib import Path

    if ds.get("path"):
        p = Path(ds["path"])
        return None if p.exists() else f"{ds['name']}: {p} does not exist"
    from smgs.data.datasets import get_dataset, resolve_data_root

    try:
        get_dataset(ds["name"]).scene_dir(resolve_data_root(cfg.get("data_root")), str(cfg["scene"]))
    except DatasetNotFoundError as e:
        return str(e) + download_hint(ds["name"], str(cfg["scene"]), cfg.get("data_root"))
    return None


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
