"""3DGS default densification (train.py / gaussian_model.py @82bc469), with budget presets and an
optional hard cap on the count.

Per step (1-based ``iteration`` < refine_stop): accumulate the norm of each visible Gaussian's
screen-space mean gradient (in NDC units, i.e. the pixel gradient × (W/2, H/2), as 3DGS and
gsplat measure it) and its largest screen radius. Every ``refine_every`` steps after
``refine_start``: clone small Gaussians and split large ones whose mean gradient ≥ grad_threshold,
then prune the transparent ones (opacity < 0.005) and, after the first opacity reset, the big ones
(largest world scale > size_prune × extent; screen radius > ``prune_screen_px`` only where that is
set: 3DGS as released never prunes by screen size, ``DefaultStrategy``). Opacity reset every
``reset_every`` steps to min(opacity, 0.01).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import torch

from smgs.device import generator_state, restore_generator
from smgs.ranges import Range
from smgs.raster.projection import quat_to_rotmat
from smgs.train.gaussians import PARAM_NAMES, Gaussians, inverse_sigmoid
from smgs.train.optim import GaussianOptimizer
from smgs.train.strategies.base import RefineEvent, Strategy, StrategyRun

SIZE_PRUNE_3DGS = 0.1
"""3DGS prunes Gaussians whose largest scale exceeds 0.1 × the scene extent."""

SIZE_PRUNE_SOFTMAX_GS = 0.4
"""Softmax-GS raises that threshold to 0.4 × extent (paper Sec. 4.2)."""

SEED_OFFSET = 7919
"""Offsets the strategy's random stream (the split samples) from the trainer's (same run seed)."""


@dataclass
class DefaultStrategy(Strategy):
    """3DGS adaptive density control: clone, split and prune by the screen-space gradient, opacity
    reset (3DGS train.py / gaussian_model.py @82bc469; gsplat DefaultStrategy). Its settings are the
    densify section's keys besides the shared ones (``DensifyConfig``).

    ``grad_threshold``: clone or split where a Gaussian's mean view-space gradient reaches it (3DGS's
    densify_grad_threshold, gsplat's grow_grad2d, this section's own earlier name); the budget's
    kind sets it. ``percent_dense``: a candidate no larger than this × extent is cloned, a larger
    one split into ``split_n``. ``prune_opacity``: Gaussians under it are pruned. ``size_prune``:
    world-space pruning of Gaussians whose largest scale exceeds size_prune × extent, only after the
    first opacity reset (3DGS 0.1); None takes the mode's (0.1 for 3dgs, 0.4 for the Softmax-GS
    variants: the paper's Sec. 4.2 raises "the Gaussian size pruning threshold to 0.4", which we read
    as this world-space 0.1 → 0.4, since GEF sharpening shrinks a splat's effective size).
    ``prune_screen_px``: also prune, after the first reset, Gaussians whose largest screen radius
    exceeds this many pixels of the training image; None (default) prunes none so. 3DGS's code names
    20 px, but its densification zeroes every Gaussian's max_radii2D before the test, so the released
    code and the paper's evaluation never pruned by screen size (its authors in
    graphdeco-inria/gaussian-splatting#123 and #643: the world-space rule "suffices"; gsplat's
    DefaultStrategy leaves it off too). With it on, a 3000-step run from random points at the 5 %
    budget lost 70 % of its Gaussians to it within 100 steps of the first reset and collapsed
    (docs/studies/fox-collapse.md). ``reset_value``: the opacity every Gaussian is reset to at most.

    Running (``Strategy.start``): the statistics and the split samples' generator live on the run's
    device; ``size_limit`` is the resolved size threshold (relative to the extent).
    """

    strategy: str = "default"
    grad_threshold: float = 2e-4
    percent_dense: float = 0.01
    split_n: int = 2
    prune_opacity: float = 0.005
    size_prune: float | None = None
    prune_screen_px: float | None = None   # 3DGS as released (see above); 20 = the rule 3DGS's code names
    reset_value: float = 0.01

    RANGES: ClassVar[dict[str, Range]] = {
        "grad_threshold": Range(0), "percent_dense": Range(0, lo_open=True), "split_n": Range(1, integer=True),
        "prune_opacity": Range(0, 1, hi_open=True), "size_prune": Range(0, lo_open=True, optional=True),
        "prune_screen_px": Range(0, lo_open=True, optional=True), "reset_value": Range(0, 1, lo_open=True, hi_open=True),
    }

    def setup(self, run: StrategyRun) -> None:
        self.extent = float(run.extent)
        self.size_limit = float(self.size_prune if self.size_prune is not None
                                else SIZE_PRUNE_3DGS if run.mode == "3dgs" else SIZE_PRUNE_SOFTMAX_GS)
        self.device = torch.device(run.device)
        self.seed = int(run.seed) + SEED_OFFSET
        self.gen = torch.Generator(device=self.device).manual_seed(self.seed)
        self._scales: dict[tuple, torch.Tensor] = {}
        self._reset_stats(0)

    def _ensure(self, n: int) -> None:
        if self.grad2d.shape[0] != n:
            self._reset_stats(n)

    def _reset_stats(self, n: int) -> None:
        self.grad2d = torch.zeros(n, device=self.device)
        self.count = torch.zeros(n, device=self.device)
        self.max_radii = torch.zeros(n, device=self.device)

    def active(self, iteration: int) -> bool:
        return self.enabled and iteration < self.refine_stop

    def wants_stats(self, n: int) -> bool:
        """Whether this step's screen-space statistics can change a refinement. Not when ``n``
        Gaussians already fill the cap and no opacity reset (hence no screen-size pruning) is
        configured: the count only changes at refinements, which then have no room to grow and
        zero the statistics afterwards, so they would be discarded unread (the Table 1 fits
        spend their whole run so). ``RefineEvent.capped`` then reports 0."""
        return self.cap is None or n < self.cap or self.reset_every is not None

    # -- the Strategy interface -------------------------------------------------------------
    def describe(self) -> list[str]:
        return [f"densification: budget {self.budget_kind} (grad {self.grad_threshold:g}{', cap ' + str(self.cap) if self.cap else ''}), "
                f"steps {self.refine_start}-{self.refine_stop} every {self.refine_every}",
                "opacity reset: off; size pruning: off (only after a reset)" if self.reset_every is None
                else f"opacity reset every {self.reset_every}; size pruning {self.size_limit:g} x extent"
                     + ("" if self.prune_screen_px is None else f" and {self.prune_screen_px:g} px on screen")
                     + " after the first reset"]

    def step_pre_backward(self, iteration: int, g: Gaussians, out) -> None:
        """Keep the screen-space mean gradients of this render when they can be used."""
        means2d = out.extras["means2d"]
        if self.active(iteration) and self.wants_stats(len(g)) and means2d.requires_grad:
            means2d.retain_grad()

    def step_post_backward(self, iteration: int, g: Gaussians, opt: GaussianOptimizer, out, camera,
                           lr_means: float) -> RefineEvent | None:
        if not self.active(iteration):
            return None
        if self.wants_stats(len(g)):
            self.accumulate(len(g), out.extras["ids"], out.extras["means2d"].grad, out.extras["radii"],
                            camera.width, camera.height)
        return self.step(iteration, g, opt)

    # -- per step ----------------------------------------------------------------------------
    @torch.no_grad()
    def accumulate(self, n: int, ids: torch.Tensor, means2d_grad: torch.Tensor, radii: torch.Tensor,
                   width: int, height: int) -> None:
        """Add one view's screen-space gradient norms (3DGS ``add_densification_stats``), in place
        and without a host wait: the rows that reach no pixel (radius 0: the dense projection's
        culled rows) add 0 to the sums and the counts instead of being picked out by a mask (a
        data-dependent shape: on a GPU a wait each)."""
        self._ensure(n)
        if ids.numel() == 0 or means2d_grad is None:
            return
        # the two radii as columns: elementwise ops (a reduction over a dimension of 2 cost ~50 µs on
        # 10K rows, the same values)
        rx, ry = radii.unbind(1)
        vis = ((rx > 0) & (ry > 0)).to(self.count.dtype)
        g = means2d_grad.detach() * self._ndc_scale(width, height, means2d_grad)
        self.grad2d.index_add_(0, ids, g.norm(dim=1).to(self.grad2d.dtype) * vis)
        self.count.index_add_(0, ids, vis)
        # Largest screen radius; the renderer gives per-axis 3σ half extents, 3DGS the 3σ radius
        # of the major axis (equal for axis-aligned splats, up to √2 larger for rotated ones). A
        # culled row's 0 leaves the maximum as it was (radii are >= 0).
        self.max_radii.scatter_reduce_(0, ids, torch.maximum(rx, ry).to(self.max_radii.dtype), "amax")

    def _ndc_scale(self, width: int, height: int, like: torch.Tensor) -> torch.Tensor:
        """(W/2, H/2) on the gradients' device, made once per image size (a copy to the device, a
        wait on a GPU, only then)."""
        key = (width, height, like.device, like.dtype)
        if key not in self._scales:
            self._scales[key] = like.new_tensor([width / 2.0, height / 2.0])
        return self._scales[key]

    @torch.no_grad()
    def step(self, iteration: int, g: Gaussians, opt: GaussianOptimizer) -> RefineEvent:
        """Refinement due at this 1-based iteration (call after ``accumulate`` and the optimiser
        step)."""
        ev = RefineEvent()
        if not self.active(iteration):
            return ev
        if iteration > self.refine_start and iteration % self.refine_every == 0:
            after_reset = self.reset_every is not None and iteration > self.reset_every
            ev = self.densify_and_prune(g, opt, prune_big=after_reset)
        if self._resets(iteration):
            self.reset_opacity(g, opt)
            ev.reset = True
        return ev

    def _resets(self, iteration: int) -> bool:
        """Whether the step of this 1-based iteration (an active one) ends in an opacity reset."""
        return self.reset_every is not None and iteration % self.reset_every == 0

    def reset_steps(self, steps: int) -> list[int]:
        """The 1-based iterations of a ``steps`` run that end in an opacity reset (``step``)."""
        return [i for i in range(1, steps + 1) if self.active(i) and self._resets(i)]

    # -- operations --------------------------------------------------------------------------
    @torch.no_grad()
    def densify_and_prune(self, g: Gaussians, opt: GaussianOptimizer, prune_big: bool) -> RefineEvent:
        n = len(g)
        self._ensure(n)
        grads = self.grad2d / self.count.clamp_min(1)
        grads[self.count == 0] = 0.0
        max_scale = g.scales.max(dim=1).values
        small = max_scale <= self.percent_dense * self.extent
        cand = grads >= self.grad_threshold
        capped = 0
        if self.cap is not None:
            room = max(self.cap - n, 0)
            if int(cand.sum()) > room:
                # Keep the candidates with the largest gradients; each adds one Gaussian net.
                idx = torch.nonzero(cand).squeeze(1)
                keep = idx[torch.argsort(grads[idx], descending=True, stable=True)[:room]]
                capped = int(cand.sum()) - room
                cand = torch.zeros_like(cand)
                cand[keep] = True
        clone = cand & small
        split = cand & ~small
        n_clone, n_split = int(clone.sum()), int(split.sum())

        p = {k: v.detach() for k, v in g.params.items()}
        extra = {k: [] for k in PARAM_NAMES}
        if n_clone:
            for k in PARAM_NAMES:
                extra[k].append(p[k][clone])
        if n_split:
            k_n = self.split_n
            sel = torch.nonzero(split).squeeze(1).repeat(k_n)
            s = g.scales.detach()[sel]
            samples = torch.randn(s.shape, generator=self.gen, dtype=s.dtype, device=s.device) * s
            rot = quat_to_rotmat(p["quats"][sel])
            for k in PARAM_NAMES:
                if k == "means":
                    extra[k].append((rot @ samples[:, :, None]).squeeze(-1) + p["means"][sel])
                elif k == "scales":
                    extra[k].append(torch.log(s / (0.8 * k_n)))
                else:
                    extra[k].append(p[k][sel])
        if n_clone or n_split:
            opt.append({k: torch.cat(v, 0) for k, v in extra.items()})
        n_new = len(g) - n
        # Originals of the split Gaussians go; so do transparent ones and, after the first
        # reset, big ones (new rows have no screen radius yet).
        split_rows = torch.cat([split, split.new_zeros(n_new)])
        transparent = (g.opacities.detach() < self.prune_opacity) & ~split_rows
        drop = split_rows | transparent
        n_screen = 0
        if prune_big:
            if self.prune_screen_px is not None:
                radii = torch.cat([self.max_radii, self.max_radii.new_zeros(n_new)])
                on_screen = (radii > self.prune_screen_px) & ~drop
                n_screen = int(on_screen.sum())
                drop |= on_screen
            drop |= g.scales.detach().max(dim=1).values > self.size_limit * self.extent
        n_pruned = int(drop.sum()) - n_split
        n_transparent = int(transparent.sum())
        if bool(drop.any()):
            opt.keep(~drop)
        self._reset_stats(len(g))   # 3DGS zeroes every Gaussian's statistics after a refinement
        return RefineEvent(cloned=n_clone, split=n_split, pruned=n_pruned, pruned_transparent=n_transparent,
                           pruned_big=n_pruned - n_transparent, pruned_big_screen=n_screen, capped=capped)

    @torch.no_grad()
    def reset_opacity(self, g: Gaussians, opt: GaussianOptimizer) -> None:
        """Opacities to min(opacity, reset_value); the opacity Adam moments restart at 0."""
        new = g.opacities.detach().clamp_max(self.reset_value)
        opt.reset("opacities", inverse_sigmoid(new))

    # -- checkpoints -------------------------------------------------------------------------
    def state_dict(self) -> dict:
        return {"kind": self.strategy, "grad2d": self.grad2d.clone(), "count": self.count.clone(),
                "max_radii": self.max_radii.clone(), "gen": generator_state(self.gen)}

    def load_state_dict(self, state: dict) -> None:
        """Restore onto this strategy's device; the generator as ``smgs.device.restore_generator``
        (a checkpoint written before strategies named themselves in it has no ``kind``)."""
        self.check_kind(state.get("kind", self.strategy))
        self.grad2d = state["grad2d"].to(self.device, copy=True)
        self.count = state["count"].to(self.device, copy=True)
        self.max_radii = state["max_radii"].to(self.device, copy=True)
        restore_generator(self.gen, state["gen"], self.seed)
