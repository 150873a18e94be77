"""The training configuration's sections as plain dataclasses (``smgs.train.config`` assembles them
into ``TrainConfig`` and builds them from nested dicts): the Gaussians' creation, the optimiser with
its two named hyperparameter sets (``HPARAMS``: the learning rates; the set's name is recorded with
every run), the loss, and the densify section's shared keys with the budget kinds (``BUDGETS``: what
each sets, its gradient threshold the one home of it). A densification strategy extends the densify
section with its own keys (``smgs.train.strategies``).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, ClassVar, Literal

from smgs.raster import constants as K
from smgs.ranges import Range

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
    """The ``densify`` section: the keys every densification strategy shares, which the harness
    reads and sets itself. A strategy (``smgs.train.strategies``) is a subclass, a dataclass that is
    its own config: its fields are the section's other keys (docs/adding-a-strategy.md).

    ``strategy`` names it (``smgs.train.strategies.registry``: the built-ins "default", 3DGS adaptive
    density control, and "mcmc", 3DGS-MCMC, and plugins); the budget's kind, ``budget_kind``
    (``BUDGETS``), picks one where the section names none and gives the section its starting values
    (``densify_config``); ``budget`` is its earlier name (``RENAMED``). ``enabled=False``: no strategy
    runs, the count stays fixed. ``cap``: the most Gaussians there may be (None: no cap; a strategy
    that cannot honour one refuses it). Steps are 1-based iteration numbers as in 3DGS: refinement in
    (``refine_start``, ``refine_stop``) every ``refine_every`` steps, an opacity reset every
    ``reset_every`` (None: none); the protocol scales these with the run length
    (``baselines.trainer_settings.scale_schedule``) and a strategy uses those it has a use for (MCMC
    never resets).
    """

    budget_kind: str = "full"
    enabled: bool = True
    strategy: str = "default"
    cap: int | None = None
    refine_start: int = 500
    refine_stop: int = 15_000
    refine_every: int = 100
    reset_every: int | None = 3000       # None: no opacity reset (2D patterns)

    RANGES: ClassVar[dict[str, Range]] = {
        "cap": Range(1, integer=True, optional=True), "refine_start": Range(0, integer=True),
        "refine_stop": Range(0, integer=True), "refine_every": COUNT,
        "reset_every": Range(1, integer=True, optional=True),
    }
    # Keys renamed since configs, checkpoints and result hashes were written with them (earlier name:
    # name now). A dict with an earlier name reads as if it had today's (``current_keys``); a result's
    # hash keeps the earlier form (protocols.cell), so no finished run retrains for a rename.
    RENAMED: ClassVar[dict[str, str]] = {"budget": "budget_kind", "grow_grad2d": "grad_threshold"}


# The budget kinds and what each sets: the one home of the paper's gradient thresholds (configs/budget/
# names a kind; protocols read the threshold here). A kind may name its strategy (else the default
# one); a setting its strategy lacks is not given to it (a plugin strategy without a gradient threshold).
BUDGETS: dict[str, dict[str, Any]] = {
    "full": dict(grad_threshold=2e-4),       # 3DGS default
    "light": dict(grad_threshold=3e-4),      # Softmax-GS_light
    "mini": dict(grad_threshold=5e-4),       # Softmax-GS_mini
    "5pct": dict(grad_threshold=4e-3),       # 3DGS_5% / Softmax-GS_5%
    "cap": dict(grad_threshold=2e-4),        # a hard maximum count (set ``cap``)
    # 3DGS-MCMC at a hard cap (set ``cap``); its schedule (refinement 500..25K every 100, no reset) is
    # the strategy's own (smgs.train.strategies.mcmc)
    "mcmc": dict(strategy="mcmc"),
}
CAPPED_KINDS = ("cap", "mcmc")
"""The budget kinds that are a hard cap: they need ``cap``."""


def strategy_name(budget_kind: str | None, strategy: str | None) -> str:
    """The strategy a section runs: the one it names, else its budget kind's (else "default")."""
    return strategy or BUDGETS.get(budget_kind or "full", {}).get("strategy", "default")
