"""Checks of every cell's resolved config before any cell runs: an impossible setting (a step count
of 0, a word where a number belongs, an unknown hyperparameter set or backend) stops the sweep
naming the key, instead of being recorded as a run."""

from __future__ import annotations

import math
from typing import Any

# (dotted key, kind, minimum); kind "int" or "number"; a key that is absent or null is not checked
NUMBERS: tuple[tuple[str, str, float], ...] = (
    ("protocol.steps", "int", 1),
    ("dataset.steps", "int", 1),
    ("seed", "int", 0),
    ("checkpoint_every", "int", 0),
    ("eval.fps_repeats", "int", 1),
    ("eval.fps_warmup", "int", 0),
    ("eval.consistency_max_width", "int", 0),
    ("budget.cap", "int", 1),
    ("budget.densify_grad_threshold", "number", 0),
)

POPPING_RATIO: tuple[str, ...] = ("auto", "on", "off")


def _get(cfg: dict, key: str) -> Any:
    for part in key.split("."):
        if not isinstance(cfg, dict) or part not in cfg:
            return None
        cfg = cfg[part]
    return cfg


def number_problem(key: str, value: Any, kind: str, minimum: float) -> str | None:
    """Why ``value`` is not a valid setting for ``key`` (None when it is)."""
    is_int = isinstance(value, int) and not isinstance(value, bool)
    is_num = is_int or (isinstance(value, float) and math.isfinite(value))
    if kind == "int" and not is_int:
        return f"{key}={value!r} is not an integer"
    if kind == "number" and not is_num:
        return f"{key}={value!r} is not a finite number"
    if value < minimum:
        return f"{key}={value!r}: must be at least {minimum:g}"
    return None


def config_problems(cfg: dict) -> list[str]:
    """Every problem of one cell's resolved config (empty when it can run)."""
    problems = []
    for key, kind, minimum in NUMBERS:
        value = _get(cfg, key)
        if value is not None:
            problem = number_problem(key, value, kind, minimum)
            if problem:
                problems.append(problem)
    fractions = _get(cfg, "eval.fractions") or []
    if not all(number_problem("f", f, "number", 0) is None and 0 < f <= 1 for f in fractions):
        problems.append(f"eval.fractions={fractions!r}: each must be a number in (0, 1]")
    popping = _get(cfg, "eval.popping_ratio")
    if popping is not None and popping not in POPPING_RATIO:
        problems.append(f"eval.popping_ratio={popping!r}: must be one of {', '.join(POPPING_RATIO)}")
    from protocols.cell_lock import ON_BUSY

    if cfg.get("on_busy", "skip") not in ON_BUSY:
        problems.append(f"on_busy={cfg.get('on_busy')!r}: must be one of {', '.join(ON_BUSY)}")
    backend = cfg.get("backend", "auto")
    from smgs.raster.api import BACKEND_NAMES

    if backend != "auto" and backend not in BACKEND_NAMES:
        problems.append(f"backend={backend!r} is not a renderer backend; expected auto, {', '.join(BACKEND_NAMES)}")
    if not problems:
        from protocols.sections import BudgetConfig, EvalConfig, ProtocolConfig

        for section in (EvalConfig, ProtocolConfig, BudgetConfig):
            try:
                section.of(cfg)
            except (ValueError, TypeError) as e:
                problems.append(str(e))
    if not problems:
        problems += _method_problems(cfg)
    return problems


def _method_problems(cfg: dict) -> list[str]:
    """The method's training config, built as the cell will build it (types, hyperparameter-set and
    budget names), for the methods trained by ``smgs.train``."""
    from baselines.registry import method_class, resolve_config
    from baselines.splatting import GaussianSplatting
    from baselines.trainer_settings import train_config
    from protocols.run_settings import method_settings, run_settings
    from smgs.train.config import TrainConfig, from_dict

    name = cfg["method"]["name"]
    if not issubclass(method_class(name), GaussianSplatting):
        return []  # another method checks its own config when it is set up
    try:
        from_dict(TrainConfig, train_config(resolve_config(name, method_settings(cfg)), run_settings(cfg)))
    except (ValueError, TypeError, KeyError) as e:
        return [f"method {name}: {e} (method.train, dataset.train and budget settings)"]
    return []


def validate_payloads(payloads: list[dict]) -> None:
    """Stop (SystemExit naming every problem and its cells) if any cell's config cannot run."""
    found: dict[str, list[str]] = {}
    for p in payloads:
        for problem in config_problems(p["config"]):
            found.setdefault(problem, []).append(p["key"])
    if found:
        lines = [f"{problem} (in {len(keys)} cell(s), e.g. {keys[0]})" for problem, keys in found.items()]
        raise SystemExit("invalid config, nothing was run:\n  " + "\n  ".join(lines))
