"""Training configuration: plain dataclasses, buildable from nested dicts (Hydra configs at the edge
turn into these with ``from_dict``).

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
from smgs.ranges import Range, range_problems

T = TypeVar("T")


RATE = Range(0)                      # a learning rate (0 freezes the parameter)
COUNT = Range(1, integer=True)       # an interval or a count of steps or things
FRACTION = Range(0, 1, lo_open=True, hi_open=True)


# --------------------------------------------------------------------------------------------
# Per-Gaussian parameters
# --------------------------------------------------------------------------------------------

@dataclass
class ParamInit:
    """Activation and initial (activated) value of one of the Softmax-GS parameters α, β, γ.

    ``exp``: value = exp(raw) (> 0; Adam then moves the value by a roughly constant *ratio* per
    step, so one learning rate serves values of any size). ``softplus``: value = log(1 + e^raw)
    (>= 0 in the limit, additive steps once the value is large).
    """

    init: float
    activation: Literal["exp", "softplus"] = "exp"

    # both activations reach 0 only in the limit: the raw value of 0 would be -inf
    RANGES: ClassVar[dict[str, Range]] = {"init": Range(0, lo_open=True)}


@dataclass
class GaussianConfig:
    """How Gaussians are created. The paper gives neither activations nor initial values of α, β,
    γ; these defaults are our choice:

    * α (GEF sharpness) = exp(raw), init 1: the Gaussian kernel itself, i.e. vanilla 3DGS.
    * β (softmax strength) = exp(raw), init 1 (real scenes), 20 (the 2D patterns). Where splats
      at different depths compete (γ 0.3, the earlier default) the softmax term's gradient on a
      splat's 2D mean grows with β, and 3DGS's densifier reads that gradient: from β = 20
      Softmax-GS cloned and split 3x as many Gaussians as 3DGS at the full budget and fell 6 dB
      behind; from 1 the gradient was 3DGS's at initialisation (tools/densify_gradients.py), and
      the real-scene rate (8e-3 on log β) moves β where the scene wants within a few hundred
      steps. At γ 3 the gradient no longer depends on β; 1 was chosen at γ 0.3, by measurement
      among 1, 5 and 20 (docs/studies/beta-init.md). The 2D fits differ: at their rate 3e-4 β can only grow ~x20 in 10K steps,
      so from 1 or 5 it ends too weak (20-21 dB on circle4), from 1000 it locks in a poor partition
      (18 dB), from 20 Softmax-GS reaches ~28 dB (docs/studies/beta-init.md).
    * γ (depth decay) is stored relative to the scene: the renderer receives
      γ_world = γ / extent, so s = exp(-γ·|Δd| / extent) whatever the scene's units.
      ``gamma_unit`` says what its initial value is measured against. "splat" (default): each
      Gaussian starts at γ_world = gamma.init / σ_i, σ_i its initial size (the kNN scale): the
      paper's Fig. 3 has two overlapping Gaussians' competition fade with their depth gap.
      Init 3 (decay length 1/3 of a splat size): splats on one surface compete, splats a surface
      apart composite as in 3DGS. Longer decays (0.3: 3.3 sizes, the earlier default) let splats
      at different depths trade pixels from view to view: the training residual stays high, 3DGS's
      densifier clones on it (1.8x 3DGS's Gaussians at the full budget) and the test views lose
      3-4 dB. Chosen by measurement among 0.1, 0.3, 1 and 3 (docs/studies/gamma-init.md). "extent": γ_world = gamma.init / extent for
      all; with init 1 (the earlier default) the decay length is one scene extent, the front and
      back of an object compete and the back shows through as speckle, and γ's rate (4e-4 on
      log γ) cannot undo that in a 3000-step run. The 2D patterns keep "extent" with init 1
      (extent 1, every splat at one depth; Table 1 was measured so).

    ``init``: "auto" takes SfM points if the scene has them, else the 2D-pattern layout for a flat
    scene, else ``n_random`` random points in a cube of side ``random_extent`` × extent (3DGS's
    synthetic-scene init).
    """

    alpha: ParamInit = field(default_factory=lambda: ParamInit(1.0))
    beta: ParamInit = field(default_factory=lambda: ParamInit(1.0))
    gamma: ParamInit = field(default_factory=lambda: ParamInit(3.0))
    gamma_unit: Literal["splat", "extent"] = "splat"
    init: Literal["auto", "sfm", "flat", "random"] = "auto"
    init_opacity: float = 0.1            # 3DGS inverse_sigmoid(0.1)
    max_sh_degree: int = 3               # flat scenes use 0 whatever this says
    clamp_colors: bool = True            # 3DGS clamps SH colours at 0; see PATTERN preset
    # 2D patterns: n_flat identical black Gaussians on a square grid `flat_spacing` apart (world
    # units at depth `flat_depth`; the image is 1 unit across there), each moved in x, y by a seeded
    # uniform jitter of ±flat_jitter × spacing (the seed's only effect on a 4-Gaussian fit),
    # isotropic scale `flat_scale`. Our choice (docs/table1): small splats that barely overlap
    # (centres ±0.15, about the quadrant centroids; σ = 0.05). With the earlier σ = 0.1 at
    # spacing 0.05 one splat grew in front of the others and hid them (circle4 Softmax-GS 16.4 dB
    # vs 18.3 under the earlier stop rule; with no stop in the softmax head, 25.1 vs 28.1).
    n_flat: int = 4
    flat_depth: float = 1.0
    flat_spacing: float = 0.3
    flat_jitter: float = 0.25
    flat_scale: float = 0.05
    flat_color: tuple[float, float, float] = (0.0, 0.0, 0.0)
    n_random: int = 100_000
    # 3DGS draws its synthetic-scene points in [-1.3, 1.3]^3 world units, where the cameras' extent
    # (1.1 x the largest distance of a camera from their mean) is about 4.9: a side of 2.6 / 4.9
    # extents. Reading 2.6 as extents (the earlier default) put a third of the cube outside the
    # cameras, thousands of points right in front of every lens: 3dgs on the fox scene learned
    # nothing (test PSNR 5 dB).
    random_extent: float = 0.53

    RANGES: ClassVar[dict[str, Range]] = {
        "init_opacity": FRACTION,         # stored as its logit: ±inf at 0 and 1
        "max_sh_degree": Range(0, K.MAX_SH_DEGREE, integer=True),
        "n_flat": COUNT, "n_random": COUNT, "flat_scale": Range(0, lo_open=True),
        "random_extent": Range(0, lo_open=True), "flat_spacing": Range(0), "flat_jitter": Range(0),
    }


# --------------------------------------------------------------------------------------------
# Optimiser
# --------------------------------------------------------------------------------------------

@dataclass
class OptimConfig:
    """Adam per parameter group (eps 1e-15, 3DGS). Position lr is × scene extent and decays
    log-linearly from ``means_lr`` to ``means_lr_final`` over ``means_lr_steps`` (None: the run's
    step count)."""

    name: str = "3dgs2023+softmaxgs_real"
    means_lr: float = 1.6e-4
    means_lr_final: float = 1.6e-6
    means_lr_delay_mult: float = 0.01     # 3DGS passes no delay steps, so inactive by default
    means_lr_delay_steps: int = 0
    means_lr_steps: int | None = 30_000
    sh0_lr: float = 2.5e-3
    shN_lr: float = 2.5e-3 / 20
    opacities_lr: float = 0.05            # the 2023 release (later releases: 0.025)
    scales_lr: float = 5e-3
    quats_lr: float = 1e-3
    alpha_lr: float = 8e-4                # paper supp. Sec. 6, real scenes
    beta_lr: float = 8e-3
    gamma_lr: float = 4e-4
    eps: float = 1e-15
    betas: tuple[float, float] = (0.9, 0.999)

    RANGES: ClassVar[dict[str, Range]] = {
        **{f: RATE for f in ("means_lr", "means_lr_final", "sh0_lr", "shN_lr", "opacities_lr", "scales_lr",
                             "quats_lr", "alpha_lr", "beta_lr", "gamma_lr")},
        "means_lr_delay_mult": Range(0), "means_lr_delay_steps": Range(0, integer=True),
        "means_lr_steps": Range(1, integer=True, optional=True), "eps": Range(0, lo_open=True),
    }


HPARAMS: dict[str, OptimConfig] = {
    # 3DGS 2023 (arguments/__init__.py@82bc469) + Softmax-GS supp. Sec. 6 rates for α, β, γ.
    "3dgs2023+softmaxgs_real": OptimConfig(name="3dgs2023+softmaxgs_real"),
    "3dgs2023+softmaxgs_patterns": OptimConfig(name="3dgs2023+softmaxgs_patterns", alpha_lr=3e-4,
                                               beta_lr=3e-4, gamma_lr=2e-4, means_lr_steps=None),
}


def hparams(name: str) -> OptimConfig:
    if name not in HPARAMS:
        raise ValueError(f"unknown hyperparameter set {name!r}; known: {', '.join(HPARAMS)}")
    return dataclasses.replace(HPARAMS[name])


# --------------------------------------------------------------------------------------------
# Loss
# --------------------------------------------------------------------------------------------

@dataclass
class LossConfig:
    """(1 − λ)·L1 + λ·(1 − SSIM) + λβ·Var_ray(β) + λγ·Var_ray(γ) (supp. Sec. 6).

    The variances are taken per pixel over its softmax head (the first k_max splats, ``k_max_scope``), each weighted by
    w = 1 / (1 + (d − d_front) / reg_depth_scale), our bounded form of the paper's "inverse
    distance to the front-most Gaussian"; reg_depth_scale = ``reg_depth_scale_rel`` × extent, so a
    splat 1% of the scene extent behind the front one counts half (default). ``reg_space="log"``
    regularises log β and log γ (ratios: a β spread of 10..40 is as costly as 1..4, and the
    term stays comparable to the photometric loss); "value" uses the activated values.
    """

    lambda_dssim: float = 0.2
    lambda_beta_var: float = 0.01
    lambda_gamma_var: float = 0.01
    reg_depth_scale_rel: float = 0.01
    reg_space: Literal["log", "value"] = "log"

    RANGES: ClassVar[dict[str, Range]] = {"lambda_dssim": Range(0, 1), "lambda_beta_var": Range(0),
                                          "lambda_gamma_var": Range(0), "reg_depth_scale_rel": Range(0, lo_open=True)}


# --------------------------------------------------------------------------------------------
# Densification
# --------------------------------------------------------------------------------------------

@dataclass
class DensifyConfig:
    """3DGS default densification (train.py / gaussian_model.py @82bc469; gsplat DefaultStrategy).

    Steps are 1-based iteration numbers as in 3DGS. ``size_prune``: world-space pruning of
    Gaussians whose largest scale exceeds size_prune × extent, only after the first opacity reset
    (3DGS 0.1). ``prune_screen_px``: also prune, after the first reset, Gaussians whose largest
    screen radius exceeds this many pixels of the training image; None (default) prunes none so.
    3DGS's code names 20 px, but its densification zeroes every Gaussian's max_radii2D before the
    test, so the released code and the paper's evaluation never pruned by screen size (its authors
    in graphdeco-inria/gaussian-splatting#123 and #643: the world-space rule "suffices"; gsplat's
    DefaultStrategy leaves it off too). With it on, a 3000-step run from random points at the 5 %
    budget lost 70 % of its Gaussians to it within 100 steps of the first reset and collapsed
    (docs/studies/fox-collapse.md). The
    Softmax-GS paper (Sec. 4.2) raises "the Gaussian size pruning threshold to 0.4": we read it as
    this world-space 0.1 → 0.4 (relative to the scene extent), since GEF sharpening shrinks a
    splat's effective size. ``size_prune=None`` takes the method's default (0.1 for 3dgs, 0.4 for
    the Softmax-GS variants).

    ``strategy`` picks the densification strategy (``smgs.train.strategies``): "default" (the
    above) or "mcmc" (Kheradmand et al. 2024, ``smgs.train.strategies.mcmc``), which reads ``cap`` as its
    ``cap_max``, the refinement schedule, ``prune_opacity`` as the dead-Gaussian threshold and the
    ``mcmc_*`` fields; it ignores the gradient, clone/split, pruning and reset fields.
    ``budget_kind`` names the budget's kind (``BUDGETS``), whose settings the section starts from
    (``densify_config``); ``budget`` is its earlier name (``RENAMED``). ``grad_threshold``: clone or
    split where a Gaussian's mean view-space gradient reaches it (3DGS's densify_grad_threshold,
    gsplat's grow_grad2d, this section's own earlier name); the budget's kind sets it.
    """

    budget_kind: str = "full"
    enabled: bool = True
    strategy: Literal["default", "mcmc"] = "default"
    grad_threshold: float = 2e-4
    cap: int | None = None
    percent_dense: float = 0.01
    split_n: int = 2
    prune_opacity: float = 0.005
    size_prune: float | None = None
    prune_screen_px: float | None = None   # 3DGS as released (see above); 20 = the rule 3DGS's code names
    refine_start: int = 500
    refine_stop: int = 15_000
    refine_every: int = 100
    reset_every: int | None = 3000       # None: no opacity reset (2D patterns)
    reset_value: float = 0.01
    # MCMC (3DGS-MCMC / gsplat MCMCStrategy defaults): growth per refinement, noise scale (× the
    # position lr), noise gate sigmoid(-k (o - t)), L1 weights on opacities and scales.
    mcmc_grow_rate: float = 0.05
    mcmc_noise_lr: float = 5e5
    mcmc_gate_k: float = 100.0
    mcmc_gate_t: float = 0.005
    mcmc_opacity_reg: float = 0.01
    mcmc_scale_reg: float = 0.01

    RANGES: ClassVar[dict[str, Range]] = {
        "grad_threshold": Range(0), "cap": Range(1, integer=True, optional=True), "percent_dense": Range(0, lo_open=True),
        "split_n": COUNT, "prune_opacity": Range(0, 1, hi_open=True),
        "size_prune": Range(0, lo_open=True, optional=True), "prune_screen_px": Range(0, lo_open=True, optional=True),
        "refine_start": Range(0, integer=True), "refine_stop": Range(0, integer=True), "refine_every": COUNT,
        "reset_every": Range(1, integer=True, optional=True), "reset_value": FRACTION,
        **{f: Range(0) for f in ("mcmc_grow_rate", "mcmc_noise_lr", "mcmc_gate_k", "mcmc_gate_t",
                                 "mcmc_opacity_reg", "mcmc_scale_reg")},
    }
    # Keys renamed since configs, checkpoints and result hashes were written with them (earlier name:
    # name now). A dict with an earlier name reads as if it had today's (``current_keys``); a result's
    # hash keeps the earlier form (protocols.cell), so no finished run retrains for a rename.
    RENAMED: ClassVar[dict[str, str]] = {"budget": "budget_kind", "grow_grad2d": "grad_threshold"}


# The budget kinds and what each sets: the one home of the paper's gradient thresholds (configs/budget/
# names a kind; protocols read the threshold here).
BUDGETS: dict[str, dict[str, Any]] = {
    "full": dict(grad_threshold=2e-4),       # 3DGS default
    "light": dict(grad_threshold=3e-4),      # Softmax-GS_light
    "mini": dict(grad_threshold=5e-4),       # Softmax-GS_mini
    "5pct": dict(grad_threshold=4e-3),       # 3DGS_5% / Softmax-GS_5%
    "cap": dict(grad_threshold=2e-4),        # a hard maximum count (set ``cap``)
    # 3DGS-MCMC at a hard cap (set ``cap``): refinement 500..25K every 100 (paper, gsplat), no reset.
    "mcmc": dict(strategy="mcmc", refine_stop=25_000, reset_every=None),
}


def budget_threshold(kind: str) -> float | None:
    """The densification gradient threshold that defines budget ``kind`` (None for MCMC, which
    refines by opacity)."""
    if kind not in BUDGETS:
        raise ValueError(f"unknown budget kind {kind!r}; known: {', '.join(BUDGETS)}")
    spec = BUDGETS[kind]
    return None if spec.get("strategy") == "mcmc" else float(spec.get("grad_threshold", DensifyConfig.grad_threshold))


def densify_config(budget_kind: str = "full", **overrides: Any) -> DensifyConfig:
    """A budget kind's settings (``BUDGETS``) with overrides; ``cap`` requires a count."""
    if budget_kind not in BUDGETS:
        raise ValueError(f"unknown budget {budget_kind!r}; known: {', '.join(BUDGETS)}")
    cfg = DensifyConfig(budget_kind=budget_kind, **{**BUDGETS[budget_kind], **overrides})
    if budget_kind in ("cap", "mcmc") and not cfg.cap:
        raise ValueError(f"budget {budget_kind!r} needs cap=<maximum number of Gaussians>")
    if cfg.strategy not in ("default", "mcmc"):
        raise ValueError(f"unknown densification strategy {cfg.strategy!r}; expected 'default' or 'mcmc'")
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
    k_max composited splats (``pixel``) or its tile list's first k_max entries (``patch``)."""

    mode: str = "softmax_gs"
    steps: int = 30_000
    seed: int = 0
    k_max: int = K.DEFAULT_K_MAX
    k_max_scope: Literal["pixel", "patch"] = K.DEFAULT_K_MAX_SCOPE   # docs/kmax-scope.md
    eq15: Literal["solved", "printed"] = "solved"
    backend: str = "auto"
    t_min: float = K.T_MIN
    sort: str = "global"    # or "per_pixel" (StopThePop's order; smgs.raster.rasterize)
    sh_degree_interval: int = 1000
    random_background: bool = False
    check_finite_every: int = 1
    gaussians: GaussianConfig = field(default_factory=GaussianConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    densify: DensifyConfig = field(default_factory=DensifyConfig)

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
        if not isinstance(value, dict) and not (isinstance(value, str) and tp in PRESETS):
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
    """A TrainConfig dict (e.g. a checkpoint's) with every section's earlier key names as today's."""
    return _rename_sections(data, lambda cls, section: current_keys(cls, section))


def earlier_train_keys(data: dict[str, Any]) -> dict[str, Any]:
    """A TrainConfig dict with each renamed key under its earlier name (``RENAMED``): the form in
    which finished results were hashed (protocols.cell.result_hash)."""
    def earlier(cls: type, section: dict[str, Any]) -> dict[str, Any]:
        back = {new: old for old, new in cls.RENAMED.items()}
        return {back.get(k, k): v for k, v in section.items()}

    return _rename_sections(data, earlier)


def _rename_sections(data: dict[str, Any], rename: Callable[[type, dict[str, Any]], dict[str, Any]]) -> dict[str, Any]:
    hints = typing.get_type_hints(TrainConfig)
    out = dict(data)
    for f in dataclasses.fields(TrainConfig):
        if isinstance(out.get(f.name), dict) and getattr(hints[f.name], "RENAMED", None):
            out[f.name] = rename(hints[f.name], out[f.name])
    return out


def from_dict(cls: type[T], data: dict[str, Any] | str | None, _where: str = "") -> T:
    """Build a (nested) config dataclass from a plain dict (e.g. ``OmegaConf.to_container``).
    Unknown keys are an error that lists the known ones; missing keys keep their defaults (a field
    without a default is an error naming it). A section with a preset (``PRESETS``: ``optim`` by
    hyperparameter-set name, ``densify`` by ``budget_kind``) may be given as that name alone; the
    preset is applied first, then the other keys. A key's earlier name (``RENAMED``) reads as today's."""
    preset = PRESETS.get(cls)
    if isinstance(data, str) and preset:
        data = {preset[0]: data}
    data = current_keys(cls, dict(data or {}), _where)
    hints = typing.get_type_hints(cls)
    fields = dataclasses.fields(cls)
    names = {f.name for f in fields}
    unknown = set(data) - names
    if unknown:
        raise ValueError(f"{cls.__name__}{' at ' + _where if _where else ''}: unknown key(s) "
                         f"{sorted(unknown)}; known: {sorted(names)}")
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
