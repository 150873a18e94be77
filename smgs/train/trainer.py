"""One Gaussian-splatting model being trained: Gaussians + optimiser + densification + loss.

The four methods (3dgs, gef_only, softmax_only, softmax_gs) are this one class with the renderer's
mode switch; ``baselines.splatting`` wraps it in the ``Method`` interface. The caller owns the loop:
``train_step`` runs exactly one step.
"""

from __future__ import annotations

import contextlib
import logging
import math
import time
from typing import Any, Iterator

import torch

from smgs.camera import Camera
from smgs.data.scene import Scene
from smgs.device import as_device, generator_state, restore_generator
from smgs.metrics.image import psnr_from_mse
from smgs.raster import RenderOutput, mode_flags, rasterize
from smgs.raster.backends import check_backend
from smgs.raster.checks import NonFiniteInputError, nonfinite_counts
from smgs.raster.kernel_clock import KernelClock
from smgs.raster.ray_depth import check_sort
from smgs.train.allocator import keep_freed_buffers
from smgs.train.config import TrainConfig, to_dict
from smgs.train.gaussians import PARAM_NAMES, Gaussians, flat_layout
from smgs.train.image_loss import PhotometricLoss, ray_variance
from smgs.train.optim import GaussianOptimizer
from smgs.train.strategies import StrategyRun, start_strategy

log = logging.getLogger(__name__)

RANDOM_INIT_PLAN = "random points (no SfM)"
"""The plan line's words for a random initialisation (protocols.collapse reads them for a cause)."""


class NonFiniteError(FloatingPointError):
    """A loss or parameter became NaN/inf; ``group`` names the parameter group (or "loss")."""

    def __init__(self, group: str, step: int, detail: str = "") -> None:
        self.group, self.step = group, step
        super().__init__(f"non-finite {'loss' if group == 'loss' else 'parameter group ' + repr(group)} "
                         f"at step {step}{': ' + detail if detail else ''}")


def trainable_groups(mode: str, max_sh_degree: int) -> tuple[str, ...]:
    """Groups the optimiser moves: α only with GEF, β and γ only with softmax, SH rest only with
    view dependence."""
    use_gef, use_softmax = mode_flags(mode)
    skip = set()
    if not use_gef:
        skip.add("alpha")
    if not use_softmax:
        skip |= {"beta", "gamma"}
    if max_sh_degree == 0:
        skip.add("shN")
    return tuple(n for n in PARAM_NAMES if n not in skip)


def active_sh_degree(iteration: int, interval: int, max_degree: int) -> int:
    """SH degree in use at ``iteration``: +1 every ``interval`` iterations (3DGS ``oneupSHdegree``);
    ``interval`` <= 0 uses every degree from the start (a model trained elsewhere)."""
    if interval <= 0:
        return max_degree
    return min(iteration // interval, max_degree)


class Trainer:
    """Trains Gaussians on a ``Scene`` with a ``TrainConfig`` on ``device`` (``smgs.device.as_device``:
    a resolved ``torch.device``, used as it is, or a setting such as "auto", "cuda:1"). Every tensor of the run lives there:
    the scene's training images and background are copied there once. Deterministic for a given
    seed and device (initialisation, view order, random backgrounds and split samples use private
    generators on the device, saved in checkpoints). ``gaussians`` starts from given Gaussians (e.g.
    read from a PLY) instead of initialising them from the scene."""

    def __init__(self, scene: Scene, cfg: TrainConfig, gaussians: Gaussians | None = None, *,
                 device: torch.device | str) -> None:
        mode_flags(cfg.mode)  # validates the mode
        check_sort(cfg.sort)
        self.device = as_device(device)
        check_backend(cfg.backend, self.device)
        self.renderer = cfg.renderer   # the backend and its variants (smgs.raster.backends)
        keep_freed_buffers()  # per-step image temporaries reuse heap pages (see smgs.train.allocator)
        self.scene = scene
        self.cfg = cfg
        self.extent = float(scene.extent)
        self.use_gef, self.use_softmax = mode_flags(cfg.mode)
        self.plan: list[str] = []
        gc = cfg.gaussians
        self.max_sh_degree = 0 if scene.flat else gc.max_sh_degree
        if scene.flat and gc.max_sh_degree:
            self.plan.append("SH: degree 0 (flat scene, no view dependence)")
        self.gen = torch.Generator(device=self.device).manual_seed(int(cfg.seed))
        if gaussians is not None:
            self.max_sh_degree = gaussians.max_sh_degree
            self.plan.append(f"init: {len(gaussians)} given Gaussians, SH degree {gaussians.max_sh_degree}")
        self.gaussians = self._init_gaussians() if gaussians is None else gaussians
        self.optimizer = GaussianOptimizer(self.gaussians, cfg.optim, self.extent, cfg.steps,
                                           trainable_groups(cfg.mode, self.max_sh_degree))
        for n in PARAM_NAMES:   # unused groups get no gradients at all
            if n not in self.optimizer.names:
                self.gaussians.params[n].requires_grad_(False)
        self.strategy = start_strategy(cfg.densify, StrategyRun(self.extent, cfg.mode, int(cfg.seed), self.device))
        self.plan += self.strategy.describe()
        self.plan += self.strategy.initialize(self.gaussians, self.optimizer)
        self.reg_on = self.use_softmax and (cfg.loss.lambda_beta_var > 0 or cfg.loss.lambda_gamma_var > 0)
        self.reg_depth_scale = cfg.loss.reg_depth_scale_rel * self.extent
        if not self.reg_on:
            self.plan.append("beta/gamma variance regulariser: off" + (" (no softmax)" if not self.use_softmax else ""))
        self.plan.append(f"hyperparameters: {cfg.optim.name}")
        self.photometric = PhotometricLoss(cfg.loss.lambda_dssim)
        self._targets = [v.rgb.to(self.device) for v in scene.train]
        self.background = None if scene.background is None else scene.background.to(self.device, torch.float32)
        self._stack: list[int] = []
        self.step_count = 0          # steps completed
        # with ``profile`` on (bench/train_step.py): each stage's wall time, and within them the
        # compiled kernels' (``smgs.raster.kernel_clock``); off, they cost nothing
        self.timings = {"render": 0.0, "loss": 0.0, "backward": 0.0, "optim": 0.0, "strategy": 0.0}
        self.kernel_clock = KernelClock()
        self.profile = False

    # -- initialisation ----------------------------------------------------------------------
    def _init_gaussians(self) -> Gaussians:
        gc, scene, dev = self.cfg.gaussians, self.scene, self.device
        how = gc.init
        if how == "auto":
            how = "sfm" if scene.points is not None else ("flat" if scene.flat else "random")
        if how == "sfm":
            if scene.points is None:
                raise ValueError(f"init 'sfm' needs SfM points, but scene {scene.name!r} has none")
            cols = scene.point_colors if scene.point_colors is not None else \
                torch.full(tuple(scene.points.shape), 0.5, device=dev)
            self.plan.append(f"init: {scene.points.shape[0]} SfM points")
            return Gaussians.from_points(scene.points, cols, gc, self.extent, self.max_sh_degree, device=dev)
        if how == "flat":
            cam = scene.train[0].camera
            c2w = cam.to(dev).camtoworld.double()
            pts = flat_layout(gc.n_flat, gc.flat_depth, gc.flat_spacing, c2w[:3, 3], c2w[:3, :3],
                              jitter=gc.flat_jitter, generator=self.gen, device=dev)
            cols = torch.tensor(gc.flat_color, dtype=torch.float32, device=dev).expand(gc.n_flat, 3)
            self.plan.append(f"init: {gc.n_flat} identical Gaussians at depth {gc.flat_depth:g}, "
                             f"{gc.flat_spacing:g} apart (jitter ±{gc.flat_jitter:g}), scale {gc.flat_scale:g} (no SfM)")
            return Gaussians.from_points(pts, cols, gc, self.extent, self.max_sh_degree,
                                         scales=torch.full((gc.n_flat, 3), gc.flat_scale, device=dev), device=dev)
        if how == "random":
            n = gc.n_random
            pts = (torch.rand(n, 3, generator=self.gen, dtype=torch.float64, device=dev) - 0.5) \
                * gc.random_extent * self.extent
            cols = torch.rand(n, 3, generator=self.gen, device=dev)
            self.plan.append(f"init: {n} {RANDOM_INIT_PLAN}")
            return Gaussians.from_points(pts.float(), cols, gc, self.extent, self.max_sh_degree, device=dev)
        raise ValueError(f"unknown init {gc.init!r}; expected auto, sfm, flat or random")

    # -- rendering ---------------------------------------------------------------------------
    def sh_degree(self, iteration: int | None = None) -> int:
        """Active SH degree (``active_sh_degree``) at ``iteration`` (default: the steps done)."""
        it = self.step_count if iteration is None else iteration
        return active_sh_degree(it, self.cfg.sh_degree_interval, self.max_sh_degree)

    def reg_values(self) -> torch.Tensor:
        g = self.gaussians
        b, c = g.beta, g.gamma_rel
        if self.cfg.loss.reg_space == "log":
            b, c = torch.log(b), torch.log(c)
        return torch.stack([b, c], dim=1)

    def render(self, camera: Camera, *, with_reg: bool = False, sh_degree: int | None = None,
               background: torch.Tensor | None = None, leaders: bool = False) -> RenderOutput:
        g = self.gaussians
        deg = self.sh_degree() if sh_degree is None else sh_degree
        # the two SH parameter groups as they are (no torch.cat per step), the renderer reading the
        # coefficients the degree uses; at degree 0 the first alone, so that the others get no
        # gradient (Adam keeps their state until their degree is active, as 3DGS)
        if background is None:
            background = self.background
        return rasterize(
            g.means, g.quats, g.scales, g.opacities, g.params["sh0"], camera,
            alpha=g.alpha if self.use_gef else None,
            beta=g.beta if self.use_softmax else None,
            gamma=g.gamma if self.use_softmax else None,
            mode=self.cfg.mode, k_max=self.cfg.k_max, k_max_scope=self.cfg.k_max_scope, sh_degree=deg,
            sh_rest=g.params["shN"] if deg > 0 else None,
            background=background,
            backend=self.renderer, eq15=self.cfg.eq15, t_min=self.cfg.t_min, sort=self.cfg.sort,
            reg_values=self.reg_values() if with_reg else None, reg_depth_scale=self.reg_depth_scale,
            clamp_sh_colors=self.cfg.gaussians.clamp_colors, leaders=leaders)

    # -- one step ----------------------------------------------------------------------------
    def _next_view(self) -> int:
        """3DGS's view stack: a fresh random permutation whenever it runs empty."""
        if not self._stack:
            self._stack = torch.randperm(len(self.scene.train), generator=self.gen, device=self.device).tolist()
        return self._stack.pop()

    def _param_tensors(self) -> list[tuple[str, torch.Tensor]]:
        params = self.gaussians.params
        return [(n, params[n].detach()) for n in PARAM_NAMES if params[n].numel()]

    def _finite_flag(self) -> torch.Tensor | bool | None:
        """False if a parameter may be non-finite (None without Gaussians). On the CPU, a host bool,
        exact: every value counted in one compiled pass (``checks.nonfinite_counts``). Elsewhere a
        0-dim bool on the device (read later, with the step's values): one sum per group, NaN/inf
        propagate into it; a finite group whose sum overflows is a false alarm, which
        ``check_finite``'s exact count clears."""
        tensors = [t for _, t in self._param_tensors()]
        if not tensors:   # no Gaussian left (a collapsed model): nothing can be non-finite
            return None
        counts = nonfinite_counts(tensors)
        if counts is not None:
            return not any(counts)
        return torch.isfinite(torch.stack([t.sum() for t in tensors])).all()

    def check_finite(self, step: int, where: str = "") -> None:
        """Raise ``NonFiniteError`` naming the first parameter group with a NaN or inf (a host read)."""
        flag = self._finite_flag()
        if flag is None or bool(flag):
            return
        for n, t in self._param_tensors():
            bad = int((~torch.isfinite(t)).sum())
            if bad:
                raise NonFiniteError(n, step, f"{bad} non-finite value(s) {where}".strip())

    def train_step(self, step: int | None = None) -> dict[str, float]:
        """Run one step. ``step`` is the number of steps already done (0-based; defaults to the
        trainer's own count); schedules use the 1-based iteration step + 1 as 3DGS does.

        Outside a refinement the step waits on the host once (on a GPU: ``_read_step``): the loss,
        its parts and the parameters' finiteness are read together after the optimiser step, which
        a non-finite loss cancels on the device (so the parameters stay as they were when it
        raises). The view order waits once per pass over the views, a refinement where it edits."""
        if step is not None and step != self.step_count:
            raise ValueError(f"train_step({step}) but {self.step_count} steps are done; "
                             "load the checkpoint of that step to resume")
        if not self.profile:
            return self._step(self.step_count + 1)
        with self.kernel_clock.running():
            return self._step(self.step_count + 1)

    def _step(self, it: int) -> dict[str, float]:
        """``train_step`` of the 1-based iteration ``it``."""
        with self._timed("render"):
            lr = self.optimizer.update_lr(it)
            view, target, out = self._forward(it)
        with self._timed("loss"):
            loss, parts, var = self._loss(out, target, it)
        with self._timed("backward"):
            if loss.requires_grad:      # no Gaussian visible in this view: nothing to learn from it
                loss.backward()
        with self._timed("optim"):
            self.optimizer.step(skip=~torch.isfinite(loss.detach()))
            values = self._read_step(loss, parts, var, it)
        with self._timed("strategy"):
            ev = self.strategy.step_post_backward(it, self.gaussians, self.optimizer, out, view.camera, lr)
            self.optimizer.zero_grad()
        self.step_count += 1
        logs = {"loss": values[0], "l1": values[1], "ssim": values[2], "psnr": psnr_from_mse(values[3]),
                "num_gaussians": float(len(self.gaussians)), "lr_means": lr}
        if var is not None:
            logs["var_beta"], logs["var_gamma"] = values[4], values[5]
        if ev is not None and ev.changed():
            logs.update(cloned=float(ev.cloned), split=float(ev.split), pruned=float(ev.pruned),
                        pruned_transparent=float(ev.pruned_transparent), pruned_big=float(ev.pruned_big),
                        pruned_big_screen=float(ev.pruned_big_screen),
                        opacity_reset=float(ev.reset))
            if ev.relocated or ev.added:
                logs.update(relocated=float(ev.relocated), added=float(ev.added))
        return logs

    @contextlib.contextmanager
    def _timed(self, stage: str) -> Iterator[None]:
        """Add the block's wall time to ``timings[stage]`` when ``profile`` is on (bench/train.py)."""
        if not self.profile:
            yield
            return
        t0 = time.perf_counter()
        yield
        self.timings[stage] += time.perf_counter() - t0

    def _forward(self, it: int) -> tuple[Any, torch.Tensor, RenderOutput]:
        """The next training view, its target and its render (with the strategy's pre-backward
        hook, which keeps the screen-space gradients it needs)."""
        vi = self._next_view()
        view, target = self.scene.train[vi], self._targets[vi]
        bg = torch.rand(3, generator=self.gen, device=self.device) if self.cfg.random_background else None
        try:
            out = self.render(view.camera, with_reg=self.reg_on, sh_degree=self.sh_degree(it), background=bg)
        except NonFiniteInputError:
            self.check_finite(self.step_count, "before the step")  # names the parameter group
            raise
        self.strategy.step_pre_backward(it, self.gaussians, out)
        return view, target, out

    def _loss(self, out: RenderOutput, target: torch.Tensor, it: int) -> tuple[torch.Tensor, Any, Any]:
        """(1 − λ)·L1 + λ·(1 − SSIM) (with L1, SSIM and MSE apart), the β/γ ray-variance terms and
        the strategy's regulariser, on the device (``_read_step`` reads them)."""
        cfg = self.cfg
        parts = self.photometric(out.rgb, target)
        loss = parts.total
        var = None
        if self.reg_on and out.reg is not None:
            var = ray_variance(out.reg)
            loss = loss + cfg.loss.lambda_beta_var * var[0] + cfg.loss.lambda_gamma_var * var[1]
        reg = self.strategy.regularizer(it, self.gaussians)
        if reg is not None:
            loss = loss + reg
        return loss, parts, var

    def _read_step(self, loss: torch.Tensor, parts: Any, var: torch.Tensor | None, it: int) -> list[float]:
        """The step's one host wait, after the optimiser step: the loss, L1, SSIM, MSE (and the
        variances), with the parameters' finiteness where a check is due (``check_finite_every``).
        A non-finite loss (the optimiser step was cancelled) stops the step naming the parameter
        group at fault, else the loss; a group the step made non-finite stops it as
        ``check_finite`` says. A NaN reaching the loss stops the step at once; the check catches
        parameters that went non-finite without showing in this view, up to ``every`` − 1 steps
        late."""
        every = self.cfg.check_finite_every
        flag = self._finite_flag() if every and it % every == 0 else None
        read = [loss.detach().reshape(1).double(), parts.values.to(loss.device, torch.float64).reshape(-1)]
        if var is not None:
            read.append(var.detach().double().reshape(-1))
        if isinstance(flag, torch.Tensor):   # a device flag, read with the values (else decided already)
            read.append(flag.double().reshape(1))
        values = torch.cat(read).tolist()
        if not math.isfinite(values[0]):
            self.check_finite(self.step_count, "before the step")
            raise NonFiniteError("loss", self.step_count, f"loss = {values[0]}")
        if flag is not None and not (values[-1] if isinstance(flag, torch.Tensor) else flag):
            self.check_finite(self.step_count, "after the optimiser step" + (
                "" if every == 1 else f" (checked every {every} steps: it appeared at step "
                                      f"{max(self.step_count - every + 1, 0)} or later)"))
        return values

    # -- checkpoints -------------------------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        return {
            "format": "smgs.train/1",
            "step": self.step_count,
            "config": to_dict(self.cfg),
            "extent": self.extent,
            "gaussians": self.gaussians.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "strategy": self.strategy.state_dict(),
            "gen": generator_state(self.gen),
            "device": str(self.device),
            "view_stack": list(self._stack),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if state.get("format") != "smgs.train/1":
            raise ValueError(f"not an smgs.train checkpoint (format {state.get('format')!r})")
        if state["config"]["mode"] != self.cfg.mode:
            raise ValueError(f"checkpoint is for mode {state['config']['mode']!r}, this trainer is {self.cfg.mode!r}")
        self.gaussians.load_state_dict(state["gaussians"])
        for n in PARAM_NAMES:
            if n not in self.optimizer.names:
                self.gaussians.params[n].requires_grad_(False)
        self.optimizer.load_state_dict(state["optimizer"])
        self.strategy.load_state_dict(state["strategy"])
        if not restore_generator(self.gen, state["gen"], self.cfg.seed):
            log.warning("resumed on %s from a checkpoint written on %s: the random generators cannot carry "
                        "over between kinds of device and were re-seeded deterministically, so the rest of "
                        "the run draws other views and samples than an uninterrupted run would",
                        self.device, state.get("device", "another kind of device"))
        self._stack = list(state["view_stack"])
        self.step_count = int(state["step"])
