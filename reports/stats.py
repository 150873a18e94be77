"""Seed statistics of the report, from scipy.stats: the Student t quantile and the t interval of a
mean, and the spread of a mean over scenes. The group-bys and merges that feed them (seed means,
scene means, paired differences) are in reports/aggregate.py.

Why t and not a bootstrap, why seeds are paired by number, and how a dataset mean's sd is propagated:
docs/reports.md ("Seeds, spread and paired differences").
"""

from __future__ import annotations

import math
from typing import Sequence

from scipy import stats

CONFIDENCE = 0.95       # of every interval in the report


def t_quantile(p: float, df: int) -> float:
    """The p-quantile of Student's t with ``df`` ≥ 1 degrees of freedom (12.706 for p = 0.975, df = 1;
    4.303 for df = 2)."""
    if not 0 < p < 1:
        raise ValueError(f"t_quantile: p must be in (0, 1), got {p}")
    if df < 1:
        raise ValueError(f"t_quantile: df must be ≥ 1, got {df}")
    return float(stats.t.ppf(p, df))


def t_interval(mean: float, sd: float, n: int, confidence: float = CONFIDENCE) -> tuple[float, float, float]:
    """(low, high, t) of the Student t interval of a mean of ``n`` ≥ 2 values with sample sd ``sd``:
    mean ± t_{(1+c)/2, n−1} · sd / √n."""
    t = t_quantile((1 + confidence) / 2, n - 1)
    half = t * sd / math.sqrt(n)
    return mean - half, mean + half, t


def mean_of_means(parts: Sequence[tuple[float, float | None]]) -> tuple[float, float | None]:
    """The mean over scenes of per-scene seed means, and the sd that one seed's mean over the same scenes
    would have: √(Σ sd_s²) / S, the scenes' runs being independent. None when any scene has no sd (one
    seed there)."""
    if not parts:
        raise ValueError("mean_of_means of no parts")
    m = sum(x for x, _ in parts) / len(parts)
    if any(sd is None for _, sd in parts):
        return m, None
    return m, math.sqrt(sum(sd * sd for _, sd in parts)) / len(parts)  # type: ignore[operator]
