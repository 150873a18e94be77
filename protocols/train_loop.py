"""The harness's loop for one run: train with checkpoints and intermediate evaluations, then the
final evaluation (8-bit metrics, renders, FPS, memory, diagnostics)."""

from __future__ import annotations

import json
import logging
import math
import shutil
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from PIL import Image

from baselines.method import LeadingSplats, OpacityResets
from protocols.cell_scene import load_scene_for
from protocols.cell_stop import StopRequests
from protocols.collapse import CollapseWatch
from protocols.sections import EvalConfig
from protocols.ply import after_run, make_method
from protocols.fps_slot import fps_slot
from protocols.job_cpus import train_conditions as job_train_conditions
from protocols.live_cells import NeighbourLog
from protocols.progress import progress as progress_bar
from protocols.results import POINTER, CurvePoint, RunResult
from protocols.run_settings import CellSettings, asked_renderer
from protocols.run_video import end_video, save_trajectory, start_video, video_cameras
from protocols.view_images import save_popping_strip, save_view_images
from smgs.env import versions
from smgs.identity import CellKey
from smgs.atomic import atomic_write_bytes, atomic_write_text
from smgs.metrics.image import evaluate_images, psnr, quantize_8bit
from smgs.metrics.result import Missing
from smgs.metrics.timing import TrainClock, device_name, measure_render_fps, track_peak_memory
from smgs.raster import Renderer, mode_flags


def left_out_of(plan: list[str]) -> list[str]:
    """The plan lines that say a stage is off or a scene capability is missing (the rest say what
    the run uses)."""
    return [line for line in plan if ": off" in line or line.startswith("scene has no")]


def eval_steps(steps: int, fractions: list[float], resets: list[int] | tuple[int, ...] = ()) -> list[int]:
    """The steps after which the test views are scored: ``fractions`` of the run, each moved to the
    last step before an opacity reset it would land on (``resets``). A reset drops every opacity to
    0.01, so a point there scores the reset, not the method (10 % of 3DGS's schedule is its first
    reset: ~13.6 dB at step 300 of 3000, 3000 of 30 000)."""
    avoid = set(resets)
    out = set()
    for f in fractions:
        s = max(1, min(steps, math.ceil(f * steps)))
        while s in avoid and s > 1:
            s -= 1
        if s not in avoid:
            out.add(s)
    return sorted(out)


def _save_checkpoint(run_dir: Path, method, progress: dict) -> None:
    """Write the new checkpoint beside the one in force, switch the pointer to it atomically, then
    remove the others. The new folder gets a name no folder there has (``ckpt-<step>``, or
    ``ckpt-<step>-<n>`` when a run resumed at its last step saves that step again), so at every
    instant of a save the pointer names a complete checkpoint: the previous one until the switch,
    the new one after it (docs/runs.md). ``progress`` carries the cell's config hash, which both
    the folder and the pointer record, so a checkpoint is only ever resumed by its own config."""
    base = f"ckpt-{progress['step']:07d}"
    name, n = base, 0
    while (run_dir / name).exists() or (run_dir / name).is_symlink():
        n += 1
        name = f"{base}-{n}"
    d = run_dir / name
    method.save(d)
    atomic_write_text(d / "progress.json", json.dumps(progress))
    atomic_write_text(run_dir / POINTER, json.dumps({"dir": name, "config_hash": progress["config_hash"]}))
    for old in run_dir.glob("ckpt-*"):
        if old.name != name:
            shutil.rmtree(old, ignore_errors=True)


def discard_checkpoints(run_dir: Path) -> None:
    """Remove the run's checkpoint (pointer first, so a crash midway leaves none in force)."""
    (run_dir / POINTER).unlink(missing_ok=True)
    for old in run_dir.glob("ckpt-*"):
        shutil.rmtree(old, ignore_errors=True)


def _load_checkpoint(run_dir: Path, method, key: CellKey | str, log: logging.Logger) -> dict | None:
    """The progress of this cell's checkpoint (``key``: its identity, or its config hash alone),
    restored into ``method``; None (and the checkpoint discarded) when there is none or it belongs
    to another config or was trained on other inputs."""
    ptr = run_dir / POINTER
    if not ptr.exists():
        return None
    try:
        d = run_dir / json.loads(ptr.read_text())["dir"]
        progress = json.loads((d / "progress.json").read_text())
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise ValueError(f"checkpoint {ptr} is unreadable ({type(e).__name__}: {e}); rerun with --force "
                         "to discard it") from None
    key = CellKey(key) if isinstance(key, str) else key
    why = key.mismatch(progress.get("config_hash"), progress.get("inputs"))
    if why:
        log.info("checkpoint %s is not this cell's (%s): discarded, training from step 0", d, why)
        discard_checkpoints(run_dir)
        return None
    method.load(d)
    return progress


def _prepare_kernels(method, log: logging.Logger) -> float:
    t0 = time.perf_counter()
    note = method.prepare()
    seconds = time.perf_counter() - t0
    log.info("compiled kernels ready in %.1f s (%s; not counted as training time)", seconds, note or "none to build")
    return seconds


def _render_rgb(method, camera) -> torch.Tensor:
    return method.render(camera).rgb.clamp(0, 1)


def quick_psnr(method, views, targets: list[torch.Tensor], quantize: bool = True) -> float:
    """Mean PSNR of the test views against their ``targets`` (on the run's device; the
    intermediate evaluations), on 8-bit renders by default."""
    q = quantize_8bit if quantize else (lambda x: x)
    with torch.no_grad():
        return float(np.mean([psnr(q(_render_rgb(method, v.camera)), q(t)) for v, t in zip(views, targets)]))


def _save_png(path: Path, img: torch.Tensor) -> None:
    import io

    buf = io.BytesIO()
    Image.fromarray((img.clamp(0, 1).cpu().numpy() * 255 + 0.5).astype(np.uint8)).save(buf, format="PNG")
    atomic_write_bytes(path, buf.getvalue())


def _quantiles(t: torch.Tensor) -> dict[str, float]:
    t = t.detach().float().flatten()
    q = torch.quantile(t, t.new_tensor([0.05, 0.25, 0.5, 0.75, 0.95]))
    return dict(zip(("p05", "p25", "p50", "p75", "p95"), map(float, q))) | {"mean": float(t.mean())}


def train_and_evaluate(cfg: dict, settings: CellSettings, run_dir: Path, result: RunResult,
                       log: logging.Logger, key: CellKey, stops: StopRequests | None = None) -> RunResult:
    """One run: train (with checkpoints and intermediate evaluations), then the final metrics,
    speed, diagnostics and view consistency. ``cfg["device"]`` is the resolved device
    (``protocols.cell.with_device``); ``settings`` the cell's resolved settings (``cell_settings``);
    ``key`` the cell's identity (``protocols.cell.result_key``), which its checkpoints record and
    match; ``stops`` the stop requests of the job the cell runs in (``protocols.cell_stop``), if any."""
    started = time.perf_counter()
    device = torch.device(cfg["device"])
    scene = load_scene_for(cfg)
    result.data = dict(scene.meta)
    method = make_method(cfg, settings, scene, result, device)   # trained, or read from a PLY (protocols.ply)
    run = settings.run   # made: make_method raised otherwise
    log.info("device: %s", device_name(device))
    ev = EvalConfig.of(cfg)
    test_rgb = [v.rgb.to(device) for v in scene.test]
    desc = method.describe()
    result.hparams = str(desc.get("hparams", ""))
    steps = 0 if result.source else run.steps   # a model read from a PLY is scored as it is
    plan = run_plan(desc, ev, scene)
    for line in plan:
        log.info("plan: %s", line)

    # Compiled kernels are built (or loaded) before the train clock starts: a build is never a
    # method's training time; its seconds are recorded apart.
    result.build_seconds = _prepare_kernels(method, log)
    clock = TrainClock(device)
    neighbours = NeighbourLog()   # the cells (of any sweep) that shared this machine while it trained
    watch = CollapseWatch.start(method.num_gaussians())
    with track_peak_memory(device) as peak:
        result.curve = train(method, scene, test_rgb, steps, clock, ev, cfg, run_dir, key, log,
                             neighbours, watch, stops)
    result.steps = steps
    result.train_seconds = clock.seconds
    result.num_gaussians = method.num_gaussians()

    within, coverage = final_metrics(method, scene, test_rgb, ev, run_dir, device, result)
    with fps_slot() as fps_conditions:
        fps = measure_render_fps(lambda c: method.render(c), [v.camera for v in scene.test],
                                 warmup=ev.fps_warmup, repeats=ev.fps_repeats, device=device)
    result.render_fps = fps.fps
    result.render_device = fps.device
    result.peak_memory_mb = peak.mib
    record_renderer(result, cfg, settings, device)
    result.diagnostics = diagnostics(method, desc, plan, within, ev, clock, peak.kind, fps_conditions)
    result.diagnostics["train_conditions"] = {"threads": torch.get_num_threads(),
                                              "cells_in_parallel": neighbours.most, **job_train_conditions()}
    if peak.baseline_bytes:   # resident at the training block's entry: peak minus this is the run's own
        result.diagnostics["peak_memory_baseline_mb"] = peak.baseline_bytes / 2**20
    result.diagnostics["collapse"] = watch.assess(result.num_gaussians, coverage, plan,
                                                  run.grad_threshold, log)
    if ev.consistency and (scene.trajectory or len(scene.test) >= 2):
        with clock.exclude("consistency"):
            result.consistency = consistency(method, scene, run_dir, ev, device, asked_renderer(cfg), log,
                                             f"{cfg['scene']}/{cfg['method']['name']}")
    result.status = "ok"
    # this process's wall time on the run (since its resume, for a resumed one): what a video's cost is a share of
    result.diagnostics["run_seconds"] = time.perf_counter() - started
    after_run(cfg, run_dir, method, result, log)   # PLY export (export_ply), pretrained bookkeeping
    return result


def record_renderer(result: RunResult, cfg: dict, settings: CellSettings, device: torch.device) -> None:
    """What rendered, in ``result.versions``: the backend, the backend with its variants (``renderer``,
    e.g. "cuda (kernels v2, glue lean)") and the SIMD path of the compiled CPU kernels (``cpu_isa``)."""
    from smgs.raster import cpu_build, render_variant

    v = render_variant(asked_renderer(cfg), device, torch.float32)
    result.versions = versions(v.backend, device_name(device))
    result.versions["renderer"] = v.describe(str((settings.resolved or {}).get("sort", "global")))
    result.versions["cpu_isa"] = cpu_build.isa_in_use()


def run_plan(desc: dict, ev: EvalConfig, scene) -> list[str]:
    """What the run uses and leaves out: the method's plan, then the harness's own stages."""
    plan = list(desc.get("plan", []))
    if (scene.meta or {}).get("alpha_dropped"):
        plan.append(f"scene images: {scene.meta['alpha_dropped']}")
    if not ev.consistency:
        plan.append("view consistency: off (eval.consistency=false)")
    elif not scene.trajectory and len(scene.test) < 2:
        plan.append("view consistency: off (no video trajectory and fewer than 2 test views)")
    return plan


def train(method, scene, test_rgb: list[torch.Tensor], steps: int, clock: TrainClock, ev: EvalConfig,
          cfg: dict, run_dir: Path, key: CellKey, log: logging.Logger,
          neighbours: NeighbourLog | None, watch: CollapseWatch, stops: StopRequests | None = None) -> list[CurvePoint]:
    """The training loop, resumed from this cell's checkpoint if there is one: the test-view
    PSNR at ``ev.fractions`` of the steps, moved off opacity resets (``eval_steps``; the error-
    against-time curve, returned) and a checkpoint every ``checkpoint_every`` steps, both outside
    the train clock. The trained state is the last checkpoint, saved before the loop returns (so
    before the final evaluation: a kill there resumes without retraining, and rendering and PLY
    export read it; a run resumed from it, or a PLY's 0-step evaluation resumed, has it already).
    ``neighbours`` counts the cells running on this machine every 10 steps; ``watch`` follows the
    Gaussian count (``protocols.collapse``; its history is kept in the checkpoints). A stop request
    (``stops``: a signal to the cell's job) is carried out after the step it came in, that step's
    checkpoint saved first; one that comes after the last step's look, once the final checkpoint
    is saved."""
    loaded = _load_checkpoint(run_dir, method, key, log)
    progress = loaded or {"step": 0, "train_seconds": 0.0, "curve": []}
    if progress.get("collapse_watch"):
        watch.restore(progress["collapse_watch"])
    start = int(progress["step"])
    saved = start if loaded else None   # the step of the checkpoint in force
    clock.seconds = float(progress["train_seconds"])
    curve = [CurvePoint(**c) for c in progress["curve"]]
    if start:
        log.info("resumed from step %d (%.1f s of training)", start, clock.seconds)
    resets = method.reset_steps(steps) if isinstance(method, OpacityResets) else []
    checks = set(eval_steps(steps, list(ev.fractions), resets))
    every = int(cfg.get("checkpoint_every") or 0)
    bar = progress_bar(steps, f"{cfg['scene']}/{cfg['method']['name']}", initial=start, position=1, leave=False)
    if stops is not None:
        stops.begin()   # a stop request now waits for the end of a step
    for step in range(start, steps):
        with clock.training():
            logs = method.train_step(step)
        done = step + 1
        watch.step(done, method.num_gaussians(), logs, log)
        if done in checks:
            with clock.exclude("eval"):
                last_psnr = quick_psnr(method, scene.test, test_rgb, ev.quantize)
            curve.append(CurvePoint(done, clock.seconds, last_psnr, method.num_gaussians()))
            log.info("step %d: %.1f s, PSNR %.2f, %d Gaussians", done, clock.seconds, last_psnr,
                     method.num_gaussians())
        stop = stops.take() if stops is not None else None
        if (every and done % every == 0 and done < steps) or stop is not None:
            _checkpoint(run_dir, method, done, clock, curve, key, watch)
            saved = done
        if stop is not None:
            log.info("step %d: stopping for %s; checkpoint saved", done, stop.reason)
            stop.action()
        bar.update(1)
        if done % 10 == 0 or done == steps:
            if neighbours is not None:
                neighbours.sample()
            # psnr: this step's training view; test: the last intermediate evaluation
            post = {"loss": f"{logs.get('loss', float('nan')):.4f}"}
            if "psnr" in logs:
                post["psnr"] = f"{logs['psnr']:.2f}"
            if curve:
                post["test"] = f"{curve[-1].psnr:.2f}"
            bar.set_postfix(post, gs=method.num_gaussians())
    if saved != steps:   # the final state, before a late stop request acts on it (stops.end)
        _checkpoint(run_dir, method, steps, clock, curve, key, watch)
    if stops is not None:
        stops.end()
    bar.close()
    return curve


def _checkpoint(run_dir: Path, method, step: int, clock: TrainClock, curve: list[CurvePoint], key: CellKey,
                watch: CollapseWatch) -> None:
    with clock.exclude("checkpoint"):
        _save_checkpoint(run_dir, method, {"step": step, "train_seconds": clock.seconds,
                                           "curve": [c.__dict__ for c in curve], **key.checkpoint_fields(),
                                           "collapse_watch": watch.to_json()})


def final_metrics(method, scene, test_rgb: list[torch.Tensor], ev: EvalConfig, run_dir: Path,
                  device: torch.device, result: RunResult) -> tuple[list[float], dict[str, float]]:
    """The test views' PSNR, SSIM, LPIPS and FLIP (on 8-bit renders unless ``ev.quantize`` is
    off) into ``result``, the renders saved; returns each view's fraction of pixels within k_max
    and each view's mean alpha (how much of it the model covers; ``protocols.collapse``)."""
    renders, names, within, coverage = [], [], [], {}
    with torch.no_grad():
        for v in scene.test:
            out = method.render(v.camera)
            renders.append(out.rgb.clamp(0, 1))
            names.append(v.name)
            within.append(out.stats.frac_within_kmax)
            coverage[v.name] = float(out.alpha.float().mean())
    if ev.save_renders:
        for n, img in zip(names, renders):
            _save_png(run_dir / "renders" / f"{Path(n).stem}.png", quantize_8bit(img))
        save_view_images(run_dir / "renders", names, renders, test_rgb, ev.viewer_views)
    m = evaluate_images(renders, test_rgb, names, lpips_net=ev.lpips_net,
                        lpips_weights=ev.lpips_weights, lpips_input=ev.lpips_input, flip=ev.flip,
                        quantize=ev.quantize, device=device)
    means = m.means()
    result.metrics = {"psnr": means["psnr"], "ssim": means["ssim"]}
    result.per_view = {"name": names, "psnr": m.psnr, "ssim": m.ssim}
    for key, values, mean in (("lpips", m.lpips, means[m.lpips_name]), ("flip", m.flip, means[m.flip_name])):
        if isinstance(values, Missing):
            result.missing[key] = values.reason
        else:
            result.metrics[key] = float(mean)
            result.per_view[key] = values
    result.lpips_net = m.lpips_name
    return within, coverage


def diagnostics(method, desc: dict, plan: list[str], within: list[float], ev: EvalConfig, clock: TrainClock,
                peak_kind: str, fps_conditions: dict) -> dict[str, Any]:
    """What the report explains a run's numbers with: the plan and what it left out, the k_max
    coverage of a softmax mode, the learned parameters' quantiles, where time and memory went."""
    diag: dict[str, Any] = {"peak_memory_kind": peak_kind, "plan": plan, "left_out": left_out_of(plan),
                            "metrics_on_8bit": ev.quantize,
                            "eval_seconds": clock.excluded.get("eval", 0.0), "fps_conditions": fps_conditions}
    mode = desc.get("config", {}).get("mode", method.name)
    if mode in ("softmax_only", "softmax_gs", "gef_only", "3dgs") and mode_flags(mode)[1]:
        diag["frac_within_kmax"] = float(np.mean(within))
        diag["k_max_scope"] = desc.get("config", {}).get("k_max_scope", "pixel")   # what the coverage counts
    # quantiles of no value do not exist: a model with no Gaussian left records none
    diag["params"] = {k: _quantiles(v) for k, v in method.parameter_values().items() if v.numel()}
    return diag


def _no_popping_ratio(method, ev: EvalConfig, device: torch.device, renderer: Renderer) -> str:
    """Why this run's video is rendered without leading-splat maps ("" when it is rendered with)."""
    if ev.popping_ratio == "off":
        return "eval.popping_ratio=off"
    if not isinstance(method, LeadingSplats):
        return f"method {method.name!r} gives no leading-splat map (baselines.method.LeadingSplats)"
    if ev.popping_ratio == "auto" and device.type == "cuda":
        from smgs.raster.backends import variant

        v = variant(renderer, "cuda" if renderer.backend == "auto" else renderer.backend)
        if v.kernel_set.pixel is None:
            return (f"the renderer {v.describe()} has no leading-splat kernel; eval.popping_ratio=on composites the "
                    "video's frames on host copies (slow for large scenes), renderer.kernels=v2 on the GPU")
    return ""


def consistency(method, scene, run_dir: Path, ev: EvalConfig, device: torch.device, renderer: Renderer,
                log: logging.Logger, name: str) -> dict:
    """Table 4 for this run (paper supp. Sec. 7): a video of 128 frames between consecutive test
    cameras (or the scene's own trajectory), frame i warped onto i+7, MSE and FLIP over the valid
    pixels, and the popping ratio where the leading-splat maps are made (``eval.popping_ratio``).
    Scored on this method's own mask; the trajectory is saved beside the results, and its frames,
    as scored, are encoded as the run's videos (``protocols.run_video``). ``name``: the cell's, for
    its progress line."""
    from smgs.metrics.consistency.score import TABLE_STEP, consistency_row

    traj = video_cameras(save_trajectory(run_dir, scene), ev.consistency_max_width)   # at most max_width wide

    no_pop = _no_popping_ratio(method, ev, device, renderer)

    def render(cam):   # with the leading-splat map where it is made (the popping ratio)
        out = method.render(cam) if no_pop else method.render_leaders(cam)
        return out.rgb, out.depth, out.leaders

    tap, no_video = start_video(run_dir, traj, TABLE_STEP, ev)   # the frames scored are also encoded
    bar = progress_bar(len(traj) - 1, f"{name} consistency", unit="frame", position=1, leave=False)
    try:
        row = consistency_row(render, traj, scene=scene.name, method=method.name, table_step=TABLE_STEP,
                              test_views=[(v.camera, v.rgb) for v in scene.test], estimator=ev.flow, tap=tap,
                              progress=lambda done, total: bar.update(1))
    except BaseException:
        if tap is not None:
            tap.abort()
        raise
    finally:
        bar.close()
    out = row.to_json()
    out["video"] = end_video(tap, no_video, log)
    if no_pop:
        out["pop_ratio"] = out["popped_fraction"] = Missing(no_pop).to_json()
    pairs = out.get("scores", {}).get(str(row.step), {}).get("per_pair", [])
    if ev.save_renders:
        save_popping_strip(run_dir / "consistency", render, traj, pairs, row.step)
    out["mask"] = "per-method"
    out["width"], out["height"] = traj[0].width, traj[0].height
    return out


