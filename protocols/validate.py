"""Checks of every cell's resolved config before any cell runs: an impossible setting (a step count
of 0, a word where a number belongs, an unknown hyperparameter set, backend, executor or flow
estimator, a learning rate of nan, images too small to score) stops the sweep naming the key,
instead of being recorded as a run or failing after training."""

from __future__ import annotations

import math
from typing import Any

from protocols.run_settings import CellSettings, cell_settings
from smgs.data.images import MIN_SIDE

# (dotted key, kind, minimum); kind "int" or "number"; a key that is absent or null is not checked
NUMBERS: tuple[tuple[str, str, float], ...] = (
    ("protocol.steps", "int", 1),
    ("protocol.test_every", "int", 1),         # 0 would leave no test view to score
    ("protocol.schedule_steps", "int", 1),     # null: the schedule is not scaled
    ("protocol.max_width", "int", MIN_SIDE),
    ("dataset.steps", "int", 1),               # the dataset's other keys are its format's (their RANGES)
    ("seed", "int", 0),
    ("checkpoint_every", "int", 0),
    ("eval.fps_repeats", "int", 1),
    ("eval.fps_warmup", "int", 0),
    ("eval.viewer_views", "int", 0),
    ("eval.consistency_max_width", "int", 0),
    ("budget.cap", "int", 1),
    ("budget.grad_threshold", "number", 0),
    ("executor.workers", "int", 1),
)

POPPING_RATIO: tuple[str, ...] = ("auto", "on", "off")


def renderer_problems(cfg: dict) -> list[str]:
    """An unknown renderer backend or variant (``backend``, ``renderer.kernels``, ``renderer.glue``)."""
    from smgs.raster.backends import AXES, BACKEND_NAMES, check_choice

    backend = cfg.get("backend", "auto")
    if backend != "auto" and backend not in BACKEND_NAMES:
        return [f"backend={backend!r} is not a renderer backend; expected auto, {', '.join(BACKEND_NAMES)}"]
    section = cfg.get("renderer") or {}
    if not isinstance(section, dict):
        return [f"renderer={section!r}: expected a section with {', '.join(AXES)}"]
    problems = [f"renderer.{k}: not a renderer setting; known: {', '.join(AXES)}" for k in section if k not in AXES]
    for axis in AXES:
        try:
            check_choice(axis, section.get(axis), f"renderer.{axis}")
        except ValueError as e:
            problems.append(str(e))
    return problems + cpu_isa_problems(cfg)


def cpu_isa_problems(cfg: dict) -> list[str]:
    """``$SMGS_CPU_ISA`` naming no SIMD path of the compiled CPU kernels, refused as an unknown
    ``renderer.kernels`` is (it would otherwise leave the renderer to the 100-1000x slower reference);
    one this CPU cannot run, too, where the cells run on this machine (not on a SLURM cluster's)."""
    from smgs.raster.cpu_build import select_isa

    try:
        select_isa()
    except ValueError as e:
        return [str(e)]
    except RuntimeError as e:
        return [] if _get(cfg, "executor.kind") == "slurm" else [str(e)]
    return []


def _choices() -> tuple[tuple[str, tuple[str, ...]], ...]:
    """(dotted key, the values it may take) of the settings that name one of a few things."""
    from protocols.cell_lock import ON_BUSY
    from protocols.executors import KINDS
    from smgs.metrics.consistency.flow import ESTIMATORS
    from smgs.metrics.lpips import NETS

    return (("eval.popping_ratio", POPPING_RATIO), ("eval.flow", ESTIMATORS), ("eval.lpips_net", NETS),
            ("eval.lpips_input", ("3dgs", "lpips")), ("on_busy", ON_BUSY), ("on_missing", ("error", "skip")),
            ("executor.kind", KINDS))


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


def config_problems(cfg: dict, settings: CellSettings | None = None) -> list[str]:
    """Every problem of one cell's resolved config (empty when it can run); ``settings``: the cell's
    (``protocols.run_settings.cell_settings``), made here when not given."""
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
    for key, allowed in _choices():
        value = _get(cfg, key)
        if value is not None and value not in allowed:
            problems.append(f"{key}={value!r}: must be one of {', '.join(allowed)}")
    problems += renderer_problems(cfg)
    if not problems:
        from protocols.sections import BudgetConfig, EvalConfig, ProtocolConfig

        from protocols.cell_scene import scene_format

        for section in (EvalConfig.of, ProtocolConfig.of, BudgetConfig.of, scene_format):
            try:
                section(cfg)
            except (ValueError, TypeError) as e:
                problems.append(str(e))
    if not problems:
        error = (settings if settings is not None else cell_settings(cfg)).error
        if error is not None:   # the method's settings as the cell will make them (types, values, names)
            problems.append(f"method {cfg['method']['name']}: {error} (keys below method.train; dataset.train and "
                            "the budget set some too)")
    return problems


def train_settings(settings: CellSettings):
    """The cell's ``smgs.train.TrainConfig`` (None for a method that ``smgs.train`` does not train,
    or settings that could not be made)."""
    from smgs.train.config import TrainConfig

    made = settings.method.settings if settings.method is not None else None
    return made if isinstance(made, TrainConfig) else None


def validate_payloads(payloads: list[dict]) -> None:
    """Stop (``Refused``, naming every problem and its cells) if any cell's config cannot run."""
    from protocols.refused import Refused

    found: dict[str, list[str]] = {}
    for p in payloads:
        for problem in config_problems(p["config"], p.get("settings")):
            found.setdefault(problem, []).append(p["key"])
    if found:
        lines = [f"{problem} (in {len(keys)} cell(s), e.g. {keys[0]})" for problem, keys in found.items()]
        raise Refused("invalid config, nothing was run:\n  " + "\n  ".join(lines))


MIN_REFINE_EVERY = 10
"""Fewest steps between two densification refinements before a scaled schedule is called degenerate:
each refinement decides clones and splits on the view-space gradient averaged since the last one
(3DGS: over 100 steps); over fewer than 10 it follows a few views' noise."""


def schedule_warning(cfg: dict, settings: CellSettings | None = None) -> str | None:
    """Why the 3DGS schedule, scaled to this cell's step count (``protocol.schedule_steps``), no longer
    does what it is for (None when it does): refinement every few steps, or opacity resets closer than
    the steps the opacities need to climb back (``reset_every`` < (logit 0.5 − logit reset_value) /
    opacity lr: 92 steps for 3DGS's values). Names the numbers and the fixes."""
    settings = settings if settings is not None else cell_settings(cfg)
    run = settings.run
    scaled = run is not None and run.schedule_steps and run.steps != run.schedule_steps
    tc = train_settings(settings) if scaled else None
    if tc is None or not tc.densify.enabled or tc.densify.refine_start >= run.steps:
        return None
    d = tc.densify
    reset, lr = getattr(d, "reset_value", None), tc.optim.opacities_lr   # a strategy that resets opacities to it
    recover = math.ceil(-math.log(reset / (1 - reset)) / lr) if reset and lr > 0 else 0
    bad = []
    if d.refine_every < MIN_REFINE_EVERY:
        bad.append(f"refines every {d.refine_every} step(s)")
    if d.reset_every and d.reset_every < recover:
        bad.append(f"resets every opacity to {reset:g} every {d.reset_every} steps (they need about {recover} to "
                   "climb back)")
    if not bad:
        return None
    return (f"protocol.steps={run.steps} scales the 3DGS schedule (written for protocol.schedule_steps="
            f"{run.schedule_steps}) by {run.steps / run.schedule_steps:g}: it {' and '.join(bad)}, so the run measures "
            "the squeezed schedule, not the method. For a short run set protocol.schedule_steps=null (the "
            "schedule unscaled: a run shorter than its refinement start trains its initial points, as "
            "+experiment=smoke does), or run longer (docs/usage.md, \"Short runs\")")
