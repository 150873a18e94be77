"""3DGS-MCMC densification (Kheradmand et al. 2024, "3D Gaussian Splatting as Markov Chain Monte
Carlo"; defaults as gsplat's ``MCMCStrategy``), in plain PyTorch on the Gaussians' device.

Every ``refine_every`` steps inside (refine_start, refine_stop):
* relocation: every dead Gaussian (opacity <= ``prune_opacity``) becomes a copy of a live one
  drawn with probability proportional to opacity; a source drawn n times and its n copies (N =
  n + 1 Gaussians at one place) get the opacity and scale of the paper's eq. (9) (``relocation``),
  so that together they render as the source did, to first order in its opacity;
* growth: ``mcmc_grow_rate`` × count new Gaussians (at least one) up to ``cap``, placed the same
  way on sources drawn from all Gaussians by opacity;
* the Adam moments of every Gaussian changed so (sources and copies) restart at zero.

Every step, after the optimiser: the means move by noise ε ~ N(0, Σ) (Σ the Gaussian's
covariance) scaled by ``mcmc_noise_lr`` × the position learning rate and gated by opacity with
sigmoid(-k (o - t)) (k = ``mcmc_gate_k``, t = ``mcmc_gate_t``): dead Gaussians explore, opaque ones
(gate ~ e^-100) stay. The loss gets the L1 regularisers ``mcmc_opacity_reg`` · mean(o) and
``mcmc_scale_reg`` · mean(scales).
"""

from __future__ import annotations

import torch

from dataclasses import dataclass
from typing import ClassVar

from smgs.device import generator_state, restore_generator
from smgs.ranges import Range
from smgs.raster.projection import quat_to_rotmat
from smgs.train.gaussians import PARAM_NAMES, Gaussians
from smgs.train.optim import GaussianOptimizer
from smgs.train.strategies.base import RefineEvent, Strategy, StrategyRun

N_MAX = 51
"""Largest number of Gaussians one source becomes in one relocation (gsplat's table size); a
source drawn more often is treated as N_MAX (its copies are then a little too faint)."""

GATE_FLOOR = 1e-20
"""Gates below this are set to 0: the step they give is far below the float32 resolution of any
mean, and an opaque Gaussian's gate (~e^-99) would otherwise make subnormal products."""

SEED_OFFSET = 104_729
"""Offsets the strategy's random stream from the trainer's (same run seed)."""


def _relocation_weights(n_max: int, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """W[N-1, k] = Σ_{i=1..N} C(i-1, k) (-1)^k / √(k+1) for N, k+1 in 1..n_max."""
    i = torch.arange(n_max, dtype=torch.float64)
    k = i[None, :]
    binom = torch.exp(torch.lgamma(i[:, None] + 1) - torch.lgamma(k + 1) - torch.lgamma((i[:, None] - k).clamp_min(0) + 1))
    binom = torch.where(k <= i[:, None], binom.round(), torch.zeros(()))
    terms = binom * (-1.0) ** k / torch.sqrt(k + 1)
    return terms.cumsum(0).to(dtype=dtype, device=device)


def relocation(opacities: torch.Tensor, scales: torch.Tensor, ratios: torch.Tensor,
               min_opacity: float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
    """The paper's eq. (9): a Gaussian of opacity o and scales s split into N = ``ratios``
    identical Gaussians at the same place, each with

        o' = 1 − (1 − o)^(1/N),
        s' = s · o / Σ_{i=1..N} Σ_{k=0..i−1} C(i−1, k) (−1)^k o'^(k+1) / √(k+1),

    so that the N composited have the source's opacity at the centre and its footprint to first
    order in o. The alternating binomial sum runs in float64 (it cancels); o' is kept in
    [min_opacity, 1 − eps] so that it stays a finite logit."""
    n = ratios.long().clamp(1, N_MAX)
    o = opacities.double()
    o_new = 1.0 - torch.pow(1.0 - o, 1.0 / n.double())
    eps = torch.finfo(opacities.dtype).eps
    o_new = o_new.clamp(min=min_opacity, max=1.0 - eps)
    w = _relocation_weights(N_MAX, torch.float64, o.device)[n - 1]                 # [M, N_MAX]
    powers = o_new[:, None] ** torch.arange(1, N_MAX + 1, dtype=torch.float64, device=o.device)
    denom = (w * powers).sum(1)
    s_new = scales.double() * (o / denom)[:, None]
    return o_new.to(opacities.dtype), s_new.to(scales.dtype)


def noise_gate(opacities: torch.Tensor, k: float, t: float) -> torch.Tensor:
    """sigmoid(−k (o − t)): ~1 for dead Gaussians, ~e^(−k (1 − t)) for opaque ones."""
    return torch.sigmoid(-k * (opacities - t))


def position_noise(g: Gaussians, lr_means: float, noise_lr: float, k: float, t: float,
                   generator: torch.Generator | None = None) -> torch.Tensor:
    """The SGLD term added to the means: Σ ε · gate(o) · noise_lr · lr_means, ε ~ N(0, I),
    Σ = R diag(s²) Rᵀ each Gaussian's covariance."""
    means = g.means.detach()
    eps = torch.randn(means.shape, generator=generator, dtype=means.dtype, device=means.device)
    rot = quat_to_rotmat(g.quats.detach())
    local = (rot * eps[:, :, None]).sum(1) * g.scales.detach().square()      # S² Rᵀ ε
    cov_eps = (rot * local[:, None, :]).sum(2)                               # R S² Rᵀ ε
    gate = noise_gate(g.opacities.detach(), k, t)
    gate = torch.where(gate > GATE_FLOOR, gate, torch.zeros_like(gate))
    return cov_eps * (gate * noise_lr * lr_means)[:, None]


@dataclass
class MCMCStrategy(Strategy):
    """3DGS-MCMC (Kheradmand et al. 2024): dead Gaussians relocated onto live ones, growth up to the
    cap, position noise and L1 regularisers (see the module doc). Its settings are the densify
    section's keys besides the shared ones (``DensifyConfig``, of which it
    reads ``cap`` as its ``cap_max`` and the refinement schedule; it never resets): ``prune_opacity``,
    the dead-Gaussian threshold, and the ``mcmc_*`` fields (gsplat's ``MCMCStrategy`` defaults): growth
    per refinement, noise scale (× the position lr), noise gate sigmoid(-k (o - t)), L1 weights on
    opacities and scales."""

    strategy: str = "mcmc"
    refine_stop: int = 25_000
    reset_every: int | None = None
    prune_opacity: float = 0.005
    mcmc_grow_rate: float = 0.05
    mcmc_noise_lr: float = 5e5
    mcmc_gate_k: float = 100.0
    mcmc_gate_t: float = 0.005
    mcmc_opacity_reg: float = 0.01
    mcmc_scale_reg: float = 0.01

    RANGES: ClassVar[dict[str, Range]] = {
        "prune_opacity": Range(0, 1, hi_open=True),
        **{f: Range(0) for f in ("mcmc_grow_rate", "mcmc_noise_lr", "mcmc_gate_k", "mcmc_gate_t",
                                 "mcmc_opacity_reg", "mcmc_scale_reg")},
    }

    def setup(self, run: StrategyRun) -> None:
        if not self.cap or self.cap < 1:
            raise ValueError("the mcmc strategy needs a cap on the count (densify.cap, e.g. budget=mcmc_<cap>)")
        self.device = torch.device(run.device)
        self.seed = int(run.seed) + SEED_OFFSET
        self.gen = torch.Generator(device=self.device).manual_seed(self.seed)

    # -- the Strategy interface --------------------------------------------------------------
    def describe(self) -> list[str]:
        return [f"densification: mcmc (budget {self.budget_kind}, cap {self.cap}), relocation of opacity <= "
                f"{self.prune_opacity:g} and growth x{1 + self.mcmc_grow_rate:g} at steps {self.refine_start}-"
                f"{self.refine_stop} every {self.refine_every}; no opacity reset",
                f"mcmc: position noise {self.mcmc_noise_lr:g} x lr gated by sigmoid(-{self.mcmc_gate_k:g}(o - "
                f"{self.mcmc_gate_t:g})); L1 regularisers opacity {self.mcmc_opacity_reg:g}, scale {self.mcmc_scale_reg:g}"]

    @torch.no_grad()
    def initialize(self, g: Gaussians, opt: GaussianOptimizer) -> list[str]:
        """More initial Gaussians than the cap: keep a random ``cap`` of them."""
        n, cap = len(g), int(self.cap)
        if n <= cap:
            return []
        gen = self.gen
        keep = torch.zeros(n, dtype=torch.bool, device=g.means.device)
        keep[torch.randperm(n, generator=gen, device=g.means.device)[:cap]] = True
        opt.keep(keep)
        return [f"mcmc: {n} initial Gaussians above the cap {cap}; kept a random {cap}"]

    def regularizer(self, iteration: int, g: Gaussians) -> torch.Tensor | None:
        if len(g) == 0:   # a mean over no Gaussian is NaN; with none left there is nothing to regularise
            return None
        terms = []
        if self.mcmc_opacity_reg > 0:
            terms.append(self.mcmc_opacity_reg * g.opacities.mean())
        if self.mcmc_scale_reg > 0:
            terms.append(self.mcmc_scale_reg * g.scales.mean())
        return sum(terms) if terms else None

    def refines_at(self, iteration: int) -> bool:
        return self.refine_start < iteration < self.refine_stop and iteration % self.refine_every == 0

    @torch.no_grad()
    def step_post_backward(self, iteration: int, g: Gaussians, opt: GaussianOptimizer, out, camera,
                           lr_means: float) -> RefineEvent:
        ev = RefineEvent()
        if self.refines_at(iteration):
            ev.relocated = self.relocate(g, opt)
            ev.added = self.grow(g, opt)
        if self.mcmc_noise_lr > 0 and lr_means > 0 and len(g):
            noise = position_noise(g, lr_means, self.mcmc_noise_lr, self.mcmc_gate_k, self.mcmc_gate_t,
                                   self.gen)
            g.params["means"].add_(noise)
        return ev

    # -- operations --------------------------------------------------------------------------
    def _sample(self, probs: torch.Tensor, n: int) -> torch.Tensor:
        return torch.multinomial(probs, n, replacement=True, generator=self.gen)

    def _split_sources(self, g: Gaussians, opt: GaussianOptimizer, src: torch.Tensor) -> dict[str, torch.Tensor]:
        """Give each source drawn n times (in ``src``) the eq. (9) opacity and scale for n + 1 and
        reset its Adam moments; returns the copies' parameters, one row per entry of ``src``."""
        counts = torch.bincount(src, minlength=len(g))
        o, s = relocation(g.opacities.detach()[src], g.scales.detach()[src], counts[src] + 1,
                          min_opacity=self.prune_opacity)
        opt.set_rows(src, {"opacities": torch.logit(o), "scales": torch.log(s)})
        return {k: g.params[k].detach()[src].clone() for k in PARAM_NAMES}

    @torch.no_grad()
    def relocate(self, g: Gaussians, opt: GaussianOptimizer) -> int:
        """Dead Gaussians become copies of live ones drawn by opacity; returns how many moved."""
        op = g.opacities.detach()
        dead = op <= self.prune_opacity
        n_dead = int(dead.sum())
        if n_dead == 0 or n_dead == len(g):
            return 0
        dead_idx = torch.nonzero(dead).squeeze(1)
        alive_idx = torch.nonzero(~dead).squeeze(1)
        src = alive_idx[self._sample(op[alive_idx].double(), n_dead)]
        opt.set_rows(dead_idx, self._split_sources(g, opt, src))   # copies, moments reset
        return n_dead

    @torch.no_grad()
    def grow(self, g: Gaussians, opt: GaussianOptimizer) -> int:
        """Add copies of Gaussians drawn by opacity: the count × (1 + grow_rate), at least one
        more, at most ``cap``; returns how many were added."""
        n = len(g)
        target = min(int(self.cap), max(int(n * (1.0 + self.mcmc_grow_rate)), n + 1))
        n_add = target - n
        if n_add <= 0 or n == 0 or self.mcmc_grow_rate == 0:
            return 0
        src = self._sample(g.opacities.detach().double(), n_add)
        opt.append(self._split_sources(g, opt, src))
        return n_add

    # -- checkpoints -------------------------------------------------------------------------
    def state_dict(self) -> dict:
        return {"kind": self.strategy, "gen": generator_state(self.gen)}

    def load_state_dict(self, state: dict) -> None:
        """The generator as ``smgs.device.restore_generator`` (exact on the same kind of device)."""
        self.check_kind(state.get("kind", "default"))   # the default strategy's earliest states name none
        restore_generator(self.gen, state["gen"], self.seed)
