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

import torch

from smgs.env import versions
from protocols.results import (RunResult, atomic_write_bytes, atomic_write_text, config_hash,
                               read_result, write_result)

CHECKPOINT = "checkpoint.pt"
LOG = "log.txt"
# Keys of a cell's config that do not change its result (where and how it runs).
VOLATILE = ("force", "executor", "report", "out_dir", "data_root", "on_missing", "grid",
            "experiment_name", "checkpoint_every")


def result_hash(cfg: dict) -> str:
    return config_hash({k: v for k, v in cfg.items() if k not in VOLATILE})


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
    h = result_hash(cfg)
    res_path = run_dir / "results.json"
    if res_path.exists() and not cfg.get("force", False):
        try:
            old = read_result(res_path)
            if old.status == "ok" and old.config_hash == h:
                return {"key": payload["key"], "status": "ok", "skipped": True}
        except ValueError:
            pass  # unreadable: run again
    run_dir.mkdir(parents=True, exist_ok=True)
    log = _logger(run_dir)
    atomic_write_text(run_dir / "config.yaml", _yaml(cfg))
    base = RunResult(**_identity(cfg), config=cfg, config_hash=h)
    try:
        from protocols.train_loop import train_and_evaluate
        result = train_and_evaluate(cfg, run_dir, base, log)
    except KeyboardInterrupt:
        log.info("interrupted; rerun to resume from the last checkpoint")
        raise
    except Exception as e:  # recorded; the sweep goes on
        from protocols.datasets import DatasetMissing

        tb = traceback.format_exc()
        log.error(tb)
        skipped = isinstance(e, DatasetMissing)
        base.status = "skipped" if skipped else "failed"
        base.error = f"{type(e).__name__}: {e}"
        base.versions = versions(cfg.get("backend", "auto"), _device_label(cfg["device"]))
        write_result(run_dir, base)
        return {"key": payload["key"], "status": base.status, "error": base.error}
    write_result(run_dir, result)
    return {"key": payload["key"], "status": "ok", "psnr": result.metrics.get("psnr")}


def _device_label(device: str) -> str:
    from smgs.device import device_name

    try:
        return device_name(device)
    except Exception:   # naming must never hide the run's own error
        return device


def _yaml(cfg: dict) -> str:
    from omegaconf import OmegaConf

    return OmegaConf.to_yaml(OmegaConf.create(cfg))


def save_checkpoint(run_dir: Path, state: dict) -> None:
    import io

    buf = io.BytesIO()
    torch.save(state, buf)
    atomic_write_bytes(run_dir / CHECKPOINT, buf.getvalue())


def load_checkpoint(run_dir: Path, device: torch.device | str) -> dict | None:
    """The state saved by ``save_checkpoint``, its tensors on ``device`` whatever device wrote it."""
    p = run_dir / CHECKPOINT
    if not p.exists():
        return None
    return torch.load(p, map_location=torch.device(device), weights_only=False)

