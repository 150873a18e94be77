"""Seed statistics of the report: mean and sd over seeds, the spread of a mean over scenes, and the
paired difference of two methods over seeds with its Student t interval.

Why t and not a bootstrap, why seeds are paired by number, and how a dataset mean's sd is propagated:
docs/reports.md ("Seeds, spread and paired differences").
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from typing import Sequence

CONFIDENCE = 0.95       # of every interval in the report
SIMPSON_STEPS = 4000    # even; the t density is smooth, so the CDF is exact to ~1e-10 up to |t| = 70


def mean_sd(xs: Sequence[float]) -> tuple[float, float | None]:
    """Mean and sample standard deviation (n − 1 in the denominator; None for one value)."""
    n = len(xs)
    if n == 0:
        raise ValueError("mean_sd of no values")
    m = sum(xs) / n
    if n == 1:
        return m, None
    return m, math.sqrt(sum((x - m) ** 2 for x in xs) / (n - 1))


def _t_cdf(t: float, df: int) -> float:
    """P(T ≤ t) for Student's t with ``df`` degrees of freedom: 1/2 + the density integrated from 0 to t
    (composite Simpson; the density is Γ((ν+1)/2) / (√(νπ) Γ(ν/2)) · (1 + x²/ν)^(−(ν+1)/2))."""
    if t < 0:
        return 1.0 - _t_cdf(-t, df)
    nu = float(df)
    log_c = math.lgamma((nu + 1) / 2) - math.lgamma(nu / 2) - 0.5 * math.log(nu * math.pi)

    def f(x: float) -> float:
        return math.exp(log_c - (nu + 1) / 2 * math.log1p(x * x / nu))

    h = t / SIMPSON_STEPS
    s = f(0.0) + f(t)
    for i in range(1, SIMPSON_STEPS):
        s += (4 if i % 2 else 2) * f(i * h)
    return 0.5 + s * h / 3


@lru_cache(maxsize=None)  # a report asks for a handful of (p, df) pairs, many times
def t_quantile(p: float, df: int) -> float:
    """The p-quantile of Student's t with ``df`` ≥ 1 degrees of freedom (bisection on the CDF; 12.706 for
    p = 0.975, df = 1; 4.303 for df = 2)."""
    if not 0 < p < 1:
        raise ValueError(f"t_quantile: p must be in (0, 1), got {p}")
    if df < 1:
        raise ValueError(f"t_quantile: df must be ≥ 1, got {df}")
    if p < 0.5:
        return -t_quantile(1 - p, df)
    lo, hi = 0.0, 1.0
    while _t_cdf(hi, df) < p:
        hi *= 2
    for _ in range(60):
        mid = (lo + hi) / 2
        lo, hi = (mid, hi) if _t_cdf(mid, df) < p else (lo, mid)
    return (lo + hi) / 2


@dataclass(frozen=True)
class Paired:
    """A − B over the seeds both ran, seed s of A with seed s of B."""

    diffs: tuple[tuple[int, float], ...]   # (seed, A − B), by seed
    mean: float
    sd: float | None                       # of the per-seed differences
    low: float | None                      # the t interval; None with one pair
    high: float | None
    t: float | None                        # the quantile used: t_{(1+CONFIDENCE)/2, n−1}
    only_a: tuple[int, ...] = ()           # seeds one side ran and the other did not (left out)
    only_b: tuple[int, ...] = ()

    @property
    def n(self) -> int:
        return len(self.diffs)

    @property
    def excludes_zero(self) -> bool:
        return self.low is not None and self.high is not None and (self.low > 0 or self.high < 0)


def paired(a: Sequence[tuple[int, float]], b: Sequence[tuple[int, float]],
           confidence: float = CONFIDENCE) -> Paired | None:
    """The paired difference of two methods' per-seed values ``(seed, value)``: d_s = a_s − b_s over the
    seeds both have; mean d̄ ± t_{(1+c)/2, n−1} · sd(d) / √n (Student t; with one pair, no interval).
    None when the two share no seed."""
    da, db = dict(a), dict(b)
    common = sorted(set(da) & set(db))
    if not common:
        return None
    diffs = tuple((s, da[s] - db[s]) for s in common)
    m, sd = mean_sd([d for _, d in diffs])
    low = high = t = None
    if sd is not None:
        t = t_quantile((1 + confidence) / 2, len(diffs) - 1)
        half = t * sd / math.sqrt(len(diffs))
        low, high = m - half, m + half
    return Paired(diffs, m, sd, low, high, t, tuple(sorted(set(da) - set(db))), tuple(sorted(set(db) - set(da))))


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
