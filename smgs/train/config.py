"""Training configuration: ``TrainConfig``, the plain dataclasses of its sections
(``smgs.train.sections``) and the densification strategy its densify section names
(``smgs.train.strategies``), buildable from nested dicts (Hydra configs at the edge turn into these
with ``from_dict``).

Two named hyperparameter sets (``HPARAMS``) pin the learning rates; the set's name is recorded with
every run. Densification budgets are kinds (``BUDGETS``: what each sets, its gradient threshold the one home of it).
"""

from __future__ import annotations

import dataclasses
import types
import typing
from dataclasses import dataclass, field
from typing import Any, Callable, ClassVar, Literal, TypeVar

from smgs.raster import constants as K
from smgs.raster.backends import AXES, Renderer, is_default
from smgs.ranges import Range, range_problems
from smgs.spelling import did_you_mean
from smgs.train.sections import (BUDGETS, CAPPED_KINDS, COUNT, FRACTION, HPARAMS, RATE, DensifyConfig,
                                 GaussianConfig, LossConfig, OptimConfig, ParamInit, hparams, strategy_name)
from smgs.train.strategies.registry import builtin_keys, strategy_class

T = TypeVar("T")

__all__ = ["TrainConfig", "GaussianConfig", "OptimConfig", "LossConfig", "DensifyConfig", "ParamInit", "HPARAMS",
           "BUDGETS", "CAPPED_KINDS", "RATE", "COUNT", "FRACTION", "hparams", "budget_threshold", "densify_start",
           "densify_config", "pattern_config", "from_dict", "to_dict", "current_keys", "current_train_keys",
           "earlier_train_keys"]


# --------------------------------------------------------------------------------------------
# Densification: the section as its strategy
# --------------------------------------------------------------------------------------------

def densify_class(data: dict[str, Any]) -> type:
    """The strategy class a densify section's dict is an instance of: the one it names
    (``strategy``), else its budget kind's."""
    return strategy_class(strategy_name(data.get("budget_kind"), data.get("strategy")))


def densify_earlier_form(section: dict[str, Any]) -> dict[str, Any]:
    """The section as results were hashed before strategies had their own configs: every key of the
    built-in strategies, those the section's strategy lacks at their defaults."""
    return {**builtin_keys(), **section}


def densify_current_form(section: dict[str, Any]) -> dict[str, Any]:
    """A section as an earlier checkpoint wrote it (``densify_earlier_form``) with only its strategy's keys."""
    own = {f.name for f in dataclasses.fields(densify_class(section))}
    builtin = builtin_keys()
    return {k: v for k, v in section.items() if k in own or k not in builtin}


def budget_threshold(kind: str) -> float | None:
    """The densification gradient threshold that defines budget ``kind`` (None where the kind's
    strategy has none: MCMC refines by opacity)."""
    threshold = densify_start(kind)[1].get("grad_threshold")
    return None if threshold is None else float(threshold)


def densify_start(budget_kind: str = "full", strategy: str | None = None) -> tuple[type, dict[str, Any]]:
    """The strategy class a densify section of ``budget_kind`` runs (``strategy``, else the kind's)
    and the values it starts from: the strategy's defaults, then the kind's settings it has."""
    if budget_kind not in BUDGETS:
        raise ValueError(f"unknown budget kind {budget_kind!r}; known: {', '.join(BUDGETS)}")
    name = strategy_name(budget_kind, strategy)
    cls = strategy_class(name)
    values = dataclasses.asdict(cls())
    values.update({k: v for k, v in BUDGETS[budget_kind].items() if k in values})
    return cls, {**values, "budget_kind": budget_kind, "strategy": name}


def densify_config(budget_kind: str = "full", **overrides: Any) -> DensifyConfig:
    """A budget kind's settings (``BUDGETS``) with overrides, as the strategy they name (``strategy``,
    else the kind's); ``cap`` requires a count. A key the strategy does not have is refused naming
    its keys."""
    cls, values = densify_start(budget_kind, overrides.get("strategy"))
    unknown = sorted(set(overrides) - set(values))
    if unknown:
        raise ValueError(f"densify: the {values['strategy']!r} strategy has no {', '.join(unknown)}; its keys: "
                         f"{', '.join(values)} (docs/densification.md)")
    cfg = cls(**{**values, **overrides, "strategy": values["strategy"]})
    if budget_kind in CAPPED_KINDS and not cfg.cap:
        raise ValueError(f"budget {budget_kind!r} needs cap=<maximum number of Gaussians>")
    return cfg


# --------------------------------------------------------------------------------------------
# Top level
# --------------------------------------------------------------------------------------------

@dataclass
class TrainConfig:
    """Everything one run of the splatting trainer needs. ``mode`` is the renderer mode
    (3dgs / gef_only / softmax_only / softmax_gs). ``t_min``: the renderer's early-stop threshold
    on the transmittance (default 1e-4, the 3DGS rule; it applies to vanilla steps only, so in
    softmax modes never inside the softmax head; 0 turns it off everywhere,
    ``smgs.raster.constants.T_MIN``). ``k_max_scope``: what the softmax head is, each pixel's first
    k_max composited splats (``pixel``) or its tile list's first k_max entries (``patch``).
    ``backend``, ``kernels``, ``glue``: the renderer and its variants (``renderer``)."""

    mode: str = "softmax_gs"
    steps: int = 30_000
    seed: int = 0
    k_max: int = K.DEFAULT_K_MAX
    k_max_scope: Literal["pixel", "patch"] = K.DEFAULT_K_MAX_SCOPE   # docs/kmax-scope.md
    eq15: Literal["solved", "printed"] = "solved"
    backend: str = "auto"
    kernels: str | None = None   # the backend's variants (smgs.raster.backends): None, the environment's
    glue: str | None = None      # (SMGS_CUDA_KERNELS, SMGS_CUDA_GLUE), else the backend's default
    t_min: float = K.T_MIN
    sort: str = "global"    # or "per_pixel" (StopThePop's order; smgs.raster.rasterize)
    sh_degree_interval: int = 1000
    random_background: bool = False
    check_finite_every: int = 1
    gaussians: GaussianConfig = field(default_factory=GaussianConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    densify: DensifyConfig = field(default_factory=lambda: densify_config("full"))   # the default strategy

    def __post_init__(self) -> None:
        Renderer(self.backend, self.kernels, self.glue)   # refuses an unknown backend or variant, naming it

    @property
    def renderer(self) -> Renderer:
        """What the trainer renders with: the backend and its variants."""
        return Renderer(self.backend, self.kernels, self.glue)

    RANGES: ClassVar[dict[str, Range]] = {
        "steps": Range(0, integer=True), "seed": Range(0, integer=True), "k_max": Range(0, integer=True),
        "t_min": Range(0, 1, hi_open=True), "check_finite_every": Range(0, integer=True),
        "sh_degree_interval": Range(0, integer=True),    # 0: every degree from the start (a model trained elsewhere)
    }


def pattern_config(mode: str, cap: int, steps: int = 10_000, seed: int = 0) -> TrainConfig:
    """The Table 1 set-up (paper Sec. 4.1, supp. Sec. 6): 4 black identical Gaussians at depth 1,
    densification capped at ``cap``, no opacity reset (hence no size pruning), the pattern
    learning rates, colours not clamped at 0 (a clamp left a dead opaque black splat,
    docs/studies/beta-init.md), SH degree 0."""
    return TrainConfig(
        mode=mode, steps=steps, seed=seed,
        gaussians=GaussianConfig(init="flat", max_sh_degree=0, clamp_colors=False, beta=ParamInit(20.0),
                                 gamma=ParamInit(1.0), gamma_unit="extent"),
        optim=hparams("3dgs2023+softmaxgs_patterns"),
        densify=densify_config("cap", cap=cap, reset_every=None, refine_stop=steps),
    )


# --------------------------------------------------------------------------------------------
# dict <-> dataclass
# --------------------------------------------------------------------------------------------

def _is_dataclass_type(tp: Any) -> bool:
    return isinstance(tp, type) and dataclasses.is_dataclass(tp)


def _convert(tp: Any, value: Any, where: str) -> Any:
    origin = typing.get_origin(tp)
    if _is_dataclass_type(tp):
        if isinstance(value, tp):
            return value
        if not isinstance(value, dict) and not (isinstance(value, str) and _preset(tp)):
            raise TypeError(f"{where}: expected a mapping for {tp.__name__}, got {type(value).__name__}")
        return from_dict(tp, value, _where=where)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if value is None:
            return None
        if len(args) == 1:
            return _convert(args[0], value, where)
        return value
    if origin is tuple and isinstance(value, (list, tuple)):
        return tuple(value)
    if origin is Literal and value not in typing.get_args(tp):
        raise ValueError(f"{where}={value!r}: expected one of {', '.join(map(repr, typing.get_args(tp)))}")
    return _scalar(tp, value, where)


def _scalar(tp: Any, value: Any, where: str) -> Any:
    """A scalar setting of the declared type (an int may stand for a float, an integral float for an
    int); anything else is an error naming the key, not a value that fails later."""
    is_int = isinstance(value, int) and not isinstance(value, bool)
    if tp is float:
        if not (is_int or isinstance(value, float)):
            raise TypeError(f"{where}={value!r}: expected a number")
        return float(value)
    if tp is int:
        if isinstance(value, float) and value.is_integer():
            return int(value)
        if not is_int:
            raise TypeError(f"{where}={value!r}: expected an int")
    if tp is bool and not isinstance(value, bool):
        raise TypeError(f"{where}={value!r}: expected true or false")
    if tp is str and not isinstance(value, str):
        raise TypeError(f"{where}={value!r}: expected a string")
    return value


def _optim_preset(name: str | None, **overrides: Any) -> OptimConfig:
    base = hparams(name) if name is not None else OptimConfig()   # an unknown name is an error
    return dataclasses.replace(base, **overrides)


def _densify_preset(budget_kind: str | None, **overrides: Any) -> DensifyConfig:
    return densify_config(budget_kind if budget_kind is not None else "full", **overrides)


# Sections built from a named preset: the dict (or a bare string) names it under the key, the other
# keys then override the preset's values.
# A section whose class depends on its keys (the densify section is its strategy's), and the forms of
# a section that earlier results were hashed (and checkpoints written) with.
SECTION_CLASS: dict[type, Callable[[dict[str, Any]], type]] = {DensifyConfig: densify_class}
EARLIER_FORM: dict[type, Callable[[dict[str, Any]], dict[str, Any]]] = {DensifyConfig: densify_earlier_form}
CURRENT_FORM: dict[type, Callable[[dict[str, Any]], dict[str, Any]]] = {DensifyConfig: densify_current_form}

PRESETS: dict[type, tuple[str, Callable[..., Any]]] = {
    OptimConfig: ("name", _optim_preset),
    DensifyConfig: ("budget_kind", _densify_preset),
}

def current_keys(cls: type, data: dict[str, Any], where: str = "") -> dict[str, Any]:
    """``data`` (a section of type ``cls``) with its earlier key names (the section's ``RENAMED``) as
    today's; one given under both names is an error that names them."""
    renamed = {old: new for old, new in getattr(cls, "RENAMED", {}).items() if old in data}
    for old, new in renamed.items():
        if new in data:
            raise ValueError(f"{cls.__name__}{' at ' + where if where else ''}: {old!r} is the earlier name of "
                             f"{new!r}; give it once, as {new!r}")
    return {renamed.get(k, k): v for k, v in data.items()}


def current_train_keys(data: dict[str, Any]) -> dict[str, Any]:
    """A TrainConfig dict (e.g. a checkpoint's) with every section's earlier key names as today's, in
    today's form (``CURRENT_FORM``: the densify section with its strategy's keys only; the renderer's
    variants, unset where written before they were settings)."""
    def current(cls: type, section: dict[str, Any]) -> dict[str, Any]:
        section = current_keys(cls, section)
        return CURRENT_FORM[cls](section) if cls in CURRENT_FORM else section

    return _rename_sections({**dict.fromkeys(AXES), **data}, current)


def without_default_variants(data: dict[str, Any]) -> dict[str, Any]:
    """A TrainConfig dict without ``kernels`` and ``glue`` where they are unset or every backend's
    default: results hashed and checkpoints written before they were settings keep their identity
    (``earlier_train_keys``; a checkpoint's config is compared with a run's so)."""
    return {k: v for k, v in data.items() if not (k in AXES and is_default(k, v))}


def earlier_train_keys(data: dict[str, Any]) -> dict[str, Any]:
    """A TrainConfig dict in the form in which finished results were hashed (protocols.cell.result_hash):
    each section in its earlier form (``EARLIER_FORM``: the densify section with every built-in
    strategy's keys), each renamed key under its earlier name (``RENAMED``), the renderer's variants
    left out where they ask for what their absence meant (``without_default_variants``)."""
    def earlier(cls: type, section: dict[str, Any]) -> dict[str, Any]:
        section = EARLIER_FORM[cls](section) if cls in EARLIER_FORM else section
        back = {new: old for old, new in getattr(cls, "RENAMED", {}).items()}
        return {back.get(k, k): v for k, v in section.items()}

    return _rename_sections(without_default_variants(data), earlier)


def _rename_sections(data: dict[str, Any], rename: Callable[[type, dict[str, Any]], dict[str, Any]]) -> dict[str, Any]:
    hints = typing.get_type_hints(TrainConfig)
    out = dict(data)
    for f in dataclasses.fields(TrainConfig):
        cls = hints[f.name]
        if isinstance(out.get(f.name), dict) and (hasattr(cls, "RENAMED") or cls in EARLIER_FORM):
            out[f.name] = rename(cls, out[f.name])
    return out


def _preset(cls: type) -> tuple[str, Callable[..., Any]] | None:
    """The section's preset (``PRESETS``), also for a subclass (a strategy's densify section)."""
    return next((PRESETS[c] for c in cls.__mro__ if c in PRESETS), None)


def from_dict(cls: type[T], data: dict[str, Any] | str | None, _where: str = "") -> T:
    """Build a (nested) config dataclass from a plain dict (e.g. ``OmegaConf.to_container``).
    Unknown keys are an error that lists the known ones; missing keys keep their defaults (a field
    without a default is an error naming it). A section with a preset (``PRESETS``: ``optim`` by
    hyperparameter-set name, ``densify`` by ``budget_kind``) may be given as that name alone; the
    preset is applied first, then the other keys. A key's earlier name (``RENAMED``) reads as today's.
    A section whose class depends on its keys (``SECTION_CLASS``: the densify section is its
    strategy's) is built as that class, its fields the known keys."""
    preset = _preset(cls)
    if isinstance(data, str) and preset:
        data = {preset[0]: data}
    data = current_keys(cls, dict(data or {}), _where)
    if cls in SECTION_CLASS:
        cls = SECTION_CLASS[cls](data)
    hints = typing.get_type_hints(cls)
    fields = dataclasses.fields(cls)
    names = {f.name for f in fields}
    unknown = set(data) - names
    if unknown:
        raise ValueError(f"{cls.__name__}{' at ' + _where if _where else ''}: unknown key(s) "
                         f"{sorted(unknown)}{did_you_mean(unknown, names, _where)}; known: {sorted(names)}")
    kwargs = {k: _convert(hints[k], v, f"{_where}.{k}" if _where else k) for k, v in data.items()}
    if preset:
        key, make = preset
        return _in_range(make(kwargs.pop(key, None), **kwargs), _where)
    required = [f.name for f in fields if f.name not in kwargs and f.default is dataclasses.MISSING
                and f.default_factory is dataclasses.MISSING]
    if required:
        raise ValueError(f"{cls.__name__}{' at ' + _where if _where else ''}: missing key(s) {required}")
    return _in_range(cls(**kwargs), _where)


def _in_range(obj: T, where: str) -> T:
    problems = range_problems(obj, where)
    if problems:
        raise ValueError("; ".join(problems))
    return obj


def to_dict(cfg: Any) -> dict[str, Any]:
    """Plain nested dict (JSON-serialisable) of a config dataclass."""
    return dataclasses.asdict(cfg)
