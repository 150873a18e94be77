"""Expansion of an experiment into cells (method × dataset/scene × budget × seed)."""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

PRETRAINED = "pretrained"
"""The budget of a model read from a PLY and only evaluated (``protocols.evaluate_ply``)."""


@dataclass(frozen=True)
class Cell:
    """One run of an experiment grid."""

    method: str
    dataset: str
    scene: str
    budget: str
    seed: int

    @property
    def key(self) -> str:
        """The run's directory below the experiment's out_dir."""
        return f"{self.dataset}/{self.scene}/{self.method}/{self.budget}/seed{self.seed}"

    def overrides(self) -> list[str]:
        """Hydra overrides that compose this cell's config."""
        return [f"method={self.method}", f"dataset={self.dataset}", f"budget={self.budget}",
                f"seed={self.seed}", f"scene={self.scene}"]


def expand(methods: list[str], datasets: dict[str, list[str]], budgets: list[str],
           seeds: list[int], scenes: list[str] | None = None,
           seeds_of: dict[str, list[int]] | None = None) -> list[Cell]:
    """Cells in a stable order: dataset, scene, budget, method, seed (so a partial sweep has every
    method of a scene before the next scene). ``datasets`` maps a dataset name to its scenes;
    ``scenes`` restricts them (a name no dataset has is an error); ``seeds_of`` gives the methods it
    names their own seeds instead of ``seeds``."""
    if scenes is not None:
        known = {s for ss in datasets.values() for s in ss}
        unknown = [s for s in scenes if s not in known]
        if unknown:
            raise ValueError(f"grid.scenes names {unknown}, which no dataset of the grid has "
                             f"(scenes: {sorted(known)})")
    cells = []
    for ds, ds_scenes in datasets.items():
        for sc in ds_scenes:
            if scenes is not None and sc not in scenes:
                continue
            for b in budgets:
                for m in methods:
                    for s in (seeds_of or {}).get(m, seeds):
                        cells.append(Cell(m, ds, sc, b, int(s)))
    if len(set(cells)) != len(cells):
        raise ValueError("the grid lists a method, dataset, budget or seed twice")
    return cells


NAME_MAX = 255
"""The longest file or folder name (bytes) of Linux, macOS and Windows file systems."""


def path_name_problem(key: str, name: str) -> str | None:
    """Why ``name`` (the value of ``key``) cannot be one folder name below the output root (None
    when it can): a name that becomes a path must not climb out of it or split into folders."""
    if name in ("", ".", ".."):
        return f"{key}={name!r} cannot name a folder"
    bad = [c for c in ("/", "\\", "\0") if c in name]
    if bad:
        return f"{key}={name!r} contains {' and '.join(map(repr, bad))}: it must be one folder name"
    if len(name.encode()) > NAME_MAX:
        return f"{key}={name[:40]!r}… is {len(name.encode())} bytes long: a folder name takes at most {NAME_MAX}"
    return None


def check_path_names(experiment_name: str, cells: list[Cell]) -> None:
    """Every name that becomes a path (the experiment's folder, each cell's dataset, scene, method
    and budget folders) stays one folder name below the output root; ValueError naming the key."""
    problems = [path_name_problem("experiment_name", experiment_name)]
    for c in cells:
        problems += [path_name_problem(k, getattr(c, k)) for k in ("dataset", "scene", "method", "budget")]
    problems = list(dict.fromkeys(p for p in problems if p))
    if problems:
        raise ValueError("; ".join(problems) + " (names become folders below out_dir; set out_dir=PATH to "
                         "write elsewhere)")


def own_budget_name(ply: Path) -> str:
    """A budget name for ``ply``'s own cell, from its name (its folder's for a file named like
    every 3DGS output, ``point_cloud.ply``)."""
    stem = ply.parent.name if ply.stem == "point_cloud" and ply.parent.name else ply.stem
    return f"{PRETRAINED}-" + (re.sub(r"[^A-Za-z0-9_.-]+", "_", stem).strip("._") or "other")
