"""The Softmax-GS paper's numbers (reports/paper_tables/*.csv) and its naming.

Everything a report needs to put the paper's figure beside ours: display names of methods,
datasets and budgets, the paper's key for a (method, budget) pair, the paper's grouping of budgets,
the scene lists, and one lookup per table that returns the paper's value or ``None``.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass, field
from pathlib import Path

PAPER_DIR = Path(__file__).resolve().parent / "paper_tables"

METHOD_ORDER = ["3dgs", "stopthepop", "gef_only", "softmax_only", "softmax_gs"]
METHOD_LABELS = {
    "3dgs": "3D GS", "gef_only": "Sharp edge only", "softmax_only": "Softmax only",
    "softmax_gs": "Softmax-GS", "ges": "GES", "3dcs": "3DCS", "3d_hgs": "3D-HGS",
    "stopthepop": "StopThePop", "ever": "EVER", "lc_wsr": "LC-WSR", "gs_mcmc": "GS-MCMC", "sss": "SSS",
    "softmax_gs_mcmc": "Softmax-GS-MCMC",
}
BUDGET_ORDER = ["5pct", "mini", "light", "full"]
BUDGET_SUFFIX = {"full": "", "5pct": " 5%", "mini": " mini", "light": " light"}

# The paper's Table 2 grouping of densification budgets.
GROUP_OF_BUDGET = {"5pct": "extreme_sparse", "mini": "sparse", "light": "sparse", "full": "dense"}
GROUP_ORDER = ["extreme_sparse", "sparse", "dense", "other"]
GROUP_LABELS = {"extreme_sparse": "extreme sparse", "sparse": "sparse", "dense": "dense", "other": "other"}

DATASET_ORDER = ["mipnerf360", "tandt", "deepblending"]
DATASET_LABELS = {"mipnerf360": "Mip-NeRF360", "tandt": "Tanks&Temples", "deepblending": "Deep Blending",
                  "patterns": "2D patterns"}
DATASET_SCENES = {
    "mipnerf360": ["bicycle", "bonsai", "counter", "garden", "kitchen", "room", "stump"],
    "tandt": ["train", "truck"],
    "deepblending": ["drjohnson", "playroom"],
}
PATTERNS = ["circle4", "rect4", "oval4"]

# Fraction of pixels whose splats all fall within k_max (paper, supp. Sec. 12: Mip-NeRF360 indoor
# ~85%, outdoor ~70%).
KMAX_COVERAGE = {"bonsai": 0.85, "counter": 0.85, "kitchen": 0.85, "room": 0.85,
                 "bicycle": 0.70, "garden": 0.70, "stump": 0.70}
KMAX_COVERAGE_RANGE = (0.70, 0.85)


# MCMC budgets (``mcmc_<cap>``) map to the paper's Table 2 MCMC rows, whose cap on each dataset is
# the 3DGS count there (2593000 / 1900000 / 2536000).
MCMC_PAPER_KEYS = {"3dgs": "gs_mcmc", "softmax_gs": "softmax_gs_mcmc"}


def mcmc_cap(budget: str) -> int | None:
    """The cap of an MCMC budget (``mcmc_2593000`` -> 2593000), else None."""
    head, _, tail = budget.partition("_")
    return int(tail) if head == "mcmc" and tail.isdigit() else None


def method_label(method: str) -> str:
    return METHOD_LABELS.get(method, method)


def dataset_label(dataset: str) -> str:
    return DATASET_LABELS.get(dataset, dataset)


def budget_group(budget: str) -> str:
    if mcmc_cap(budget) is not None:
        return "dense"       # the paper lists its MCMC rows in the dense group
    return GROUP_OF_BUDGET.get(budget, "other")


def row_label(method: str, budget: str) -> str:
    """The paper's name for a method at a budget: "Softmax-GS 5%", "3D GS", "Softmax-GS mini"."""
    if budget in BUDGET_SUFFIX:
        return method_label(method) + BUDGET_SUFFIX[budget]
    cap = mcmc_cap(budget)
    if cap is not None:
        return f"{method_label(method)}-MCMC (cap {cap:,})"
    return f"{method_label(method)} ({budget})"


def paper_key(method: str, budget: str) -> str | None:
    """The paper tables' row key (``softmax_gs_5pct``, ``3dgs``), or None for a budget the paper
    does not use."""
    if budget == "full":
        return method
    if budget in ("5pct", "mini", "light"):
        return f"{method}_{budget}"
    if mcmc_cap(budget) is not None:
        return MCMC_PAPER_KEYS.get(method)
    return None


def method_rank(method: str) -> tuple[int, str]:
    return (METHOD_ORDER.index(method) if method in METHOD_ORDER else len(METHOD_ORDER), method)


def budget_rank(budget: str) -> tuple[int, int, str]:
    if budget in BUDGET_ORDER:
        return (BUDGET_ORDER.index(budget), 0, budget)
    digits = "".join(c for c in budget if c.isdigit())
    return (len(BUDGET_ORDER), int(digits) if digits else 0, budget)


def dataset_rank(dataset: str) -> tuple[int, str]:
    return (DATASET_ORDER.index(dataset) if dataset in DATASET_ORDER else len(DATASET_ORDER), dataset)


def scene_rank(dataset: str, scene: str) -> tuple[int, str]:
    scenes = DATASET_SCENES.get(dataset, PATTERNS if dataset == "patterns" else [])
    return (scenes.index(scene) if scene in scenes else len(scenes), scene)


@dataclass
class PaperTables:
    """The paper's values, keyed as the CSVs are. ``error`` says why a table could not be read
    (then lookups return None and reports print the reason)."""

    table1: dict[tuple[str, str, int], float] = field(default_factory=dict)    # (pattern, method, n) -> PSNR
    table2: dict[tuple[str, str], dict[str, float]] = field(default_factory=dict)  # (key, dataset)
    table3: dict[tuple[str, str], dict[str, float]] = field(default_factory=dict)  # (key, scene)
    table4: dict[tuple[str, str], dict[str, float]] = field(default_factory=dict)  # (key, scene)
    table5: dict[tuple[str, str], dict[str, float]] = field(default_factory=dict)  # (key, scene)
    table2_rows: list[str] = field(default_factory=list)  # row keys in the paper's order
    source: str = str(PAPER_DIR)
    error: str | None = None

    def t1(self, pattern: str, method: str, n: int) -> float | None:
        return self.table1.get((pattern, method, int(n)))

    def t2(self, method: str, budget: str, dataset: str, metric: str) -> float | None:
        key, cap = paper_key(method, budget), mcmc_cap(budget)
        if cap is not None and _get(self.table2, key, dataset, "num_gaussians") != cap:
            return None      # the paper's MCMC row on this dataset is at another cap
        return _get(self.table2, key, dataset, metric)

    def t3(self, method: str, budget: str, scene: str, metric: str) -> float | None:
        return _get(self.table3, paper_key(method, budget), scene, metric)

    def t4(self, method: str, budget: str, scene: str, metric: str) -> float | None:
        return _get(self.table4, paper_key(method, budget), scene, metric)

    def t5(self, method: str, budget: str, scene: str, metric: str) -> float | None:
        return _get(self.table5, paper_key(method, budget), scene, metric)


def _get(table: dict, key: str | None, where: str, metric: str) -> float | None:
    if key is None:
        return None
    return table.get((key, where), {}).get(metric)


def _read(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as f:
        return list(csv.DictReader(f))


def _numbers(row: dict[str, str], keys: list[str]) -> dict[str, float]:
    """The row's numbers under the report's metric names (``n_gaussians`` -> ``num_gaussians``)."""
    rename = {"n_gaussians": "num_gaussians", "flip7": "flip"}
    return {rename.get(k, k): float(row[k]) for k in keys if row.get(k, "") != ""}


def load_paper(folder: Path | str = PAPER_DIR) -> PaperTables:
    folder = Path(folder)
    p = PaperTables(source=str(folder))
    try:
        for r in _read(folder / "table1_patterns.csv"):
            p.table1[(r["pattern"], r["method"], int(r["n_gaussians"]))] = float(r["psnr"])
        for r in _read(folder / "table2_realworld.csv"):
            p.table2[(r["method"], r["dataset"])] = _numbers(r, ["psnr", "ssim", "lpips", "n_gaussians"])
            if r["method"] not in p.table2_rows:
                p.table2_rows.append(r["method"])
        for r in _read(folder / "table3_speed.csv"):
            p.table3[(r["method"], r["scene"])] = _numbers(r, ["train_minutes", "render_fps"])
        for r in _read(folder / "table4_consistency.csv"):
            p.table4[(r["method"], r["scene"])] = _numbers(r, ["psnr", "mse", "flip7"])
        for r in _read(folder / "table5_per_scene.csv"):
            p.table5[(r["method"], r["scene"])] = _numbers(r, ["psnr", "n_gaussians"])
    except (OSError, KeyError, ValueError) as e:
        return PaperTables(source=str(folder), error=f"paper tables not readable at {folder}: {e}")
    return p
