"""Scenes, their formats and their loaders.

Scene formats and benchmark datasets register by name (``smgs.data.registry``; plugins through the
entry-point group ``smgs.datasets``, docs/adding-a-scene-format.md); ``load_scene`` makes a scene
from plain values. The loaders are importable on their own (``smgs.data.colmap.load_colmap``,
``smgs.data.transforms.load_transforms``, ``smgs.data.procedural.make_procedural_scene``). Heavy
imports (pycolmap, OpenCV) happen on use.
"""

from smgs.data.datasets import DATA_ROOT_ENV, DatasetSpec, resolve_data_root
from smgs.data.formats import SceneFormat, SceneRequest
from smgs.data.registry import check_scene, get_dataset, load_scene
from smgs.data.rules import GENERIC_RULES
from smgs.data.images import ResolutionRule
from smgs.data.errors import DatasetNotFoundError, MissingImageError, SceneContractError, SceneFormatError
from smgs.lazy import lazy_names

# Lazy re-exports so that ``import smgs.data`` does not import pycolmap or OpenCV, nor torch (the
# scene's tensors) for what only names datasets and formats (``smgs list``, ``--help``).
__getattr__ = lazy_names("smgs.data", {
    **dict.fromkeys(("Scene", "View", "camera_extent", "split_every"), "scene"),
    "check_scene_contract": "contract", "load_colmap": "colmap", "load_transforms": "transforms",
    "make_procedural_scene": "procedural"})

__all__ = ["Scene", "View", "camera_extent", "split_every", "ResolutionRule", "SceneFormat", "SceneRequest",
           "DatasetSpec", "GENERIC_RULES", "DATA_ROOT_ENV", "get_dataset", "resolve_data_root",
           "load_scene", "check_scene", "load_colmap", "load_transforms", "make_procedural_scene",
           "DatasetNotFoundError", "SceneFormatError", "MissingImageError", "SceneContractError",
           "check_scene_contract"]
