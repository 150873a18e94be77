"""Densification strategies: each a dataclass that is its own config (the densify section's keys),
with the hooks the trainer calls around each step, as gsplat's strategies are
(``step_pre_backward`` / ``step_post_backward``); docs/adding-a-strategy.md.

``base.py`` has the interface (``Strategy``, ``StrategyRun``, ``RefineEvent``), ``registry.py`` the
strategies by name (the built-ins "default", 3DGS adaptive density control in ``default.py``, and
"mcmc", 3DGS-MCMC in ``mcmc.py``; plugins through the entry-point group ``smgs.strategies``).
``densify.strategy`` picks one (else the budget's kind).
"""

from __future__ import annotations

from smgs.lazy import lazy_names

# on first use: the registry lists the strategies without importing them (nor torch)
__getattr__ = lazy_names("smgs.train.strategies", {
    **dict.fromkeys(("FixedCount", "RefineEvent", "Strategy", "StrategyRun"), "base"),
    **dict.fromkeys(("SIZE_PRUNE_3DGS", "SIZE_PRUNE_SOFTMAX_GS", "DefaultStrategy"), "default"),
    "MCMCStrategy": "mcmc",
    **dict.fromkeys(("list_strategies", "register", "start_strategy", "strategy_class", "unregister"), "registry")})

__all__ = ["Strategy", "StrategyRun", "RefineEvent", "FixedCount", "DefaultStrategy", "MCMCStrategy",
           "SIZE_PRUNE_3DGS", "SIZE_PRUNE_SOFTMAX_GS", "list_strategies", "register", "unregister",
           "start_strategy", "strategy_class"]
