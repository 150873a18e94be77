"""Run one cell of an experiment: load the scene, train, evaluate, write results.json.

``run_cell`` is the function every executor calls. It never raises for a failing run: the error is
recorded in the run's results.json (status "failed") and the sweep goes on. A KeyboardInterrupt
does propagate; the run then resumes from its last checkpoint next time.
"""

from __future__ import annotations

import logging
import traceback
from pathlib import Path
from typing import Any

from smgs.env import versions
from protocols.cell_lock import cell_lock
from protocols.live_cells import live_cell
from protocols.results import RESULTS_FILE, RunResult, atomic_write_text, config_hash, read_result, write_result
from protocols.run_settings import CellSettings, cell_settings
from protocols.sections import BudgetConfig
from smgs.train.config import earlier_train_keys

LOG = "log.txt"
# Keys of a cell's config that do not change its result (where and how it runs).
VOLATILE = ("force", "executor", "report", "report_builder", "out_dir", "data_root", "on_missing", "grid",
            "seeds", "experiment_name", "checkpoint_every", "export_ply", "on_busy")


def result_hash(cfg: dict, settings: CellSettings | None = None) -> str:
    """The identity of a cell's result: its config without the volatile keys, and the method's
    complete settings where it gives them (``baselines.method.ResolvedSettings``), so that a
    changed default retrains instead of reusing a result computed under the old one. ``settings``:
    the cell's ``CellSettings`` where the caller has them (made here otherwise)."""
    ident = {k: v for k, v in cfg.items() if k not in VOLATILE}
    if isinstance(cfg.get("budget"), dict):
        try:
            ident["budget"] = BudgetConfig.of(cfg).identity()
        except (TypeError, ValueError):   # refused before any cell runs (protocols.validate)
            pass
    resolved = (settings if settings is not None else cell_settings(cfg)).resolved
    if resolved is not None:   # a renamed setting keeps the name results were hashed with
        ident["resolved_settings"] = earlier_train_keys(resolved)
    return config_hash(ident)


def _logger(run_dir: Path) -> logging.Logger:
    log = logging.getLogger(f"smgs.run.{run_dir}")
    log.setLevel(logging.INFO)
    log.propagate = False
    if not log.handlers:
        run_dir.mkdir(parents=True, exist_ok=True)
        fh = logging.FileHandler(run_dir / LOG)
        fh.setFormatter(logging.Formatter("%(asctime)s %(message)s"))
        log.addHandler(fh)
    return log


def _identity(cfg: dict) -> dict[str, Any]:
    return dict(method=cfg["method"]["name"], dataset=cfg["dataset"]["name"], scene=str(cfg["scene"]),
                budget=cfg["budget"]["name"], seed=int(cfg["seed"]), preset=cfg["protocol"]["name"])


def with_device(cfg: dict) -> dict:
    """The cell's config with ``device`` resolved on this machine (``auto`` → ``cuda:0`` or
    ``cpu``; ``cuda`` → ``cuda:<index>``), so the config hash, config.yaml and results.json name
    the device the run used: a result of another device is not taken for this one. Raises
    ``smgs.device.DeviceError`` (a device this machine lacks, a backend of the other kind)."""
    from smgs.device import check_backend, resolve_device

    dev = resolve_device(cfg.get("device"))
    check_backend(str(cfg.get("backend", "auto")), dev)
    return {**cfg, "device": str(dev)}


def run_cell(payload: dict) -> dict:
    """payload: {"key", "run_dir", "config" (resolved dict)}. Returns a small summary."""
    from smgs.device import DeviceError

    run_dir = Path(payload["run_dir"])
    try:
        cfg: dict = with_device(payload["config"])
    except DeviceError as e:   # before anything is written: no half-made run directory
        return {"key": payload["key"], "status": "failed", "error": f"{type(e).__name__}: {e}"}
    settings = cell_settings(cfg)   # the config resolved once: the hash and the method read it
    h = result_hash(cfg, settings)
    base = RunResult(**_identity(cfg), config=cfg, config_hash=h)
    try:
        if _finished(run_dir / RESULTS_FILE, h, bool(cfg.get("force", False))):
            return {"key": payload["key"], "status": "ok", "skipped": True}
        run_dir.mkdir(parents=True, exist_ok=True)
        with cell_lock(run_dir, str(cfg.get("out_dir", "?")), str(cfg.get("on_busy", "skip"))) as holder:
            if holder is not None:   # another live process writes this cell: it is left to it
                return {"key": payload["key"], "status": "skipped", "busy": True,
                        "error": f"held by {holder.describe()}, which is writing this cell; left to it "
                                 "(rerun later to pick up its result, or on_busy=wait to wait for it)"}
            return _run_locked(payload["key"], cfg, settings, run_dir, h, base)
    except Exception as e:  # the folder or its lock is the problem: recorded where it can be
        return _failed(payload["key"], run_dir, base, e, None)


def _run_locked(key: str, cfg: dict, settings: CellSettings, run_dir: Path, h: str, base: RunResult) -> dict:
    """The cell's run, with its folder's lock held (``protocols.cell_lock``)."""
    log = None
    try:
        if _finished(run_dir / RESULTS_FILE, h, bool(cfg.get("force", False))):
            return {"key": key, "status": "ok", "skipped": True}   # finished by the lock's last holder
        log = _logger(run_dir)
        if cfg.get("force", False):
            from protocols.train_loop import discard_checkpoints

            discard_checkpoints(run_dir)  # --force retrains: nothing of an earlier run is resumed
        atomic_write_text(run_dir / "config.yaml", _yaml(cfg))
        from protocols.train_loop import train_and_evaluate
        with live_cell(run_dir):
            result = train_and_evaluate(cfg, settings, run_dir, base, log)
        if result.config_hash != h:  # a result is only ever recorded under its own config
            raise RuntimeError(f"internal error: result of config {result.config_hash} under {h}")
    except KeyboardInterrupt:
        if log:
            log.info("interrupted; rerun to resume from the last checkpoint")
        raise
    except Exception as e:  # recorded; the sweep goes on
        return _failed(key, run_dir, base, e, log)
    write_result(run_dir, result)
    return {"key": key, "status": "ok", "psnr": result.metrics.get("psnr")}


def _device_label(device: str) -> str:
    from smgs.device import device_name

    try:
        return device_name(device)
    except Exception:   # naming must never hide the run's own error
        return device


def _finished(res_path: Path, h: str, force: bool) -> bool:
    """A finished result of this very config is there (and ``force`` is off)."""
    if res_path.parent.exists() and not res_path.parent.is_dir():
        raise NotADirectoryError(f"{res_path.parent} is a file where the run's folder should be; move it away")
    if res_path.is_dir():
        raise IsADirectoryError(f"{res_path} is a folder where the run's results file should be; move it away")
    if force or not res_path.exists():
        return False
    try:
        old = read_result(res_path)
    except ValueError:
        return False  # unreadable: run again
    return old.status == "ok" and old.config_hash == h


def _failed(key: str, run_dir: Path, base: RunResult, e: Exception, log: logging.Logger | None) -> dict:
    """Record a failed (or skipped, for missing data) cell in its results.json where it can."""
    from protocols.cell_scene import DatasetMissing

    if log:
        log.error(traceback.format_exc())
    base.status = "skipped" if isinstance(e, DatasetMissing) else "failed"
    base.error = f"{type(e).__name__}: {e}"
    base.versions = versions(base.config.get("backend", "auto"), _device_label(base.config.get("device", "cpu")))
    try:
        write_result(run_dir, base)
    except OSError as w:  # the run's folder itself is the problem: the summary still says why
        base.error += f" (not recorded in {run_dir}: {type(w).__name__}: {w})"
    out = {"key": key, "status": base.status, "error": base.error}
    if log and base.status == "failed":
        out["log"] = str(run_dir / LOG)   # the summary line names the file with the traceback
    return out


def _yaml(cfg: dict) -> str:
    from omegaconf import OmegaConf

    return OmegaConf.to_yaml(OmegaConf.create(cfg))
