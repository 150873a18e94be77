"""Run one cell of an experiment: load the scene, train, evaluate, write results.json.

``run_cell`` is the function every executor calls. It never raises for a failing run: the error is
recorded in the run's results.json (status "failed") and the sweep goes on. A KeyboardInterrupt
does propagate; the run then resumes from its last checkpoint next time.
"""

from __future__ import annotations

import contextlib
import logging
import os
import traceback
from pathlib import Path
from typing import Any, Iterator

from smgs.env import versions
from protocols.cell_lock import cell_lock
from protocols.cell_rerun import CONFIG_FILE, remove_leftovers, rerun_dir, swap_in
from protocols.cell_scene import cell_inputs
from protocols.grid import PRETRAINED
from protocols.live_cells import live_cell
from protocols.results import RESULTS_FILE, NewerResults, RunResult, atomic_write_text, read_result, write_result
from protocols.run_settings import CellSettings, asked_renderer, cell_settings
from protocols.sections import BudgetConfig
from smgs.identity import CellKey, cell_key

LOG = "log.txt"


def result_key(cfg: dict, settings: CellSettings | None = None, inputs: dict | None = None) -> CellKey:
    """The identity of a cell's result (``smgs.identity.cell_key``): its config that changes numbers,
    its budget as identified, the method's complete settings where it gives them
    (``baselines.method.ResolvedSettings``, so that a changed default retrains instead of reusing a
    result computed under the old one), and its inputs' fingerprint ``inputs``
    (``protocols.cell_scene.cell_inputs``). ``settings``: the cell's ``CellSettings`` where the caller
    has them (made here otherwise)."""
    budget = None
    if isinstance(cfg.get("budget"), dict):
        try:
            budget = BudgetConfig.of(cfg).identity()
        except (TypeError, ValueError):   # refused before any cell runs (protocols.validate)
            pass
    resolved = (settings if settings is not None else cell_settings(cfg)).resolved
    return cell_key(cfg, budget, resolved, inputs)


def result_hash(cfg: dict, settings: CellSettings | None = None) -> str:
    """The hash of a cell's result (``result_key``), the one its results.json records."""
    return result_key(cfg, settings).hash


@contextlib.contextmanager
def _logger(run_dir: Path) -> Iterator[logging.Logger]:
    """The cell's log file ``run_dir/log.txt`` for the block (closed after it: a rerun's folder is
    swapped in under another name, and the next run of the cell opens its own)."""
    log = logging.getLogger(f"smgs.run.{run_dir}")
    log.setLevel(logging.INFO)
    log.propagate = False
    run_dir.mkdir(parents=True, exist_ok=True)
    fh = logging.FileHandler(run_dir / LOG)
    fh.setFormatter(logging.Formatter("%(asctime)s %(message)s"))
    log.addHandler(fh)
    try:
        yield log
    finally:
        log.removeHandler(fh)
        fh.close()


def _identity(cfg: dict) -> dict[str, Any]:
    return dict(method=cfg["method"]["name"], dataset=cfg["dataset"]["name"], scene=str(cfg["scene"]),
                budget=cfg["budget"]["name"], seed=int(cfg["seed"]), preset=cfg["protocol"]["name"])


def with_device(cfg: dict) -> dict:
    """The cell's config with ``device`` resolved on this machine (``auto`` → ``cuda:0`` or
    ``cpu``; ``cuda`` → ``cuda:<index>``), so the config hash, config.yaml and results.json name
    the device the run used: a result of another device is not taken for this one. Raises
    ``smgs.device.DeviceError`` (a device this machine lacks, a backend of the other kind)."""
    from smgs.device import resolve_device
    from smgs.raster.backends import check_backend

    dev = resolve_device(cfg.get("device"))
    check_backend(str(cfg.get("backend", "auto")), dev)
    return {**cfg, "device": str(dev)}


def run_cell(payload: dict) -> dict:
    """payload: {"key", "run_dir", "config" (resolved dict), optionally "settings" (the config's
    ``CellSettings``, made when the cell was planned)}. Returns a small summary."""
    from smgs.device import DeviceError

    run_dir = Path(payload["run_dir"])
    try:
        cfg: dict = with_device(payload["config"])
    except DeviceError as e:   # before anything is written: no half-made run directory
        return {"key": payload["key"], "status": "failed", "error": f"{type(e).__name__}: {e}"}
    settings = payload.get("settings") or cell_settings(cfg)   # made once: the hash and the method read it
    inputs = cell_inputs(cfg)
    ident = result_key(cfg, settings, inputs)
    base = RunResult(**_identity(cfg), config=cfg, config_hash=ident.hash, inputs=inputs or {})
    try:
        if _finished(run_dir / RESULTS_FILE, ident, bool(cfg.get("force", False))):
            return {"key": payload["key"], "status": "ok", "skipped": True}
        run_dir.mkdir(parents=True, exist_ok=True)
        with cell_lock(run_dir, str(cfg.get("out_dir", "?")), str(cfg.get("on_busy", "skip"))) as holder:
            if holder is not None:   # another live process writes this cell: it is left to it
                return {"key": payload["key"], "status": "skipped", "busy": True,
                        "error": f"held by {holder.describe()}, which is writing this cell; left to it "
                                 "(rerun later to pick up its result, or on_busy=wait to wait for it)"}
            return _run_locked(payload["key"], cfg, settings, run_dir, ident, base)
    except LeftAlone as e:   # nothing is written: the folder is not ours to change
        return {"key": payload["key"], "status": "failed", "error": str(e)}
    except Exception as e:  # the folder or its lock is the problem: recorded where it can be
        return _failed(payload["key"], run_dir, base, e, None)


def _run_locked(key: str, cfg: dict, settings: CellSettings, run_dir: Path, ident: CellKey, base: RunResult) -> dict:
    """The cell's run, with its folder's lock held (``protocols.cell_lock``). A finished result that
    is not this cell's (another config, other inputs: ``ident.mismatch``), or any under ``force``,
    is kept whole until this run's own is complete: the run then works in the folder beside it
    (``protocols.cell_rerun``) and is swapped in at the end; the summary's ``rerun`` says why."""
    force = bool(cfg.get("force", False))
    if _finished(run_dir / RESULTS_FILE, ident, force):
        return {"key": key, "status": "ok", "skipped": True}   # finished by the lock's last holder
    kept = _finished_result(run_dir / RESULTS_FILE)
    if kept is not None and not force:
        _check_same_kind(kept, cfg, run_dir)
        _check_same_model(kept, cfg, run_dir)
    work = run_dir if kept is None else rerun_dir(run_dir)
    if kept is not None:
        remove_leftovers(run_dir)
        if not force and _finished(work / RESULTS_FILE, ident, False):   # stopped before its swap: finish it
            swap_in(work, run_dir)
            return {"key": key, "status": "ok", "psnr": read_result(run_dir / RESULTS_FILE).metrics.get("psnr")}
    why = None if kept is None else ("--force" if force else ident.mismatch(kept.config_hash, kept.inputs))
    with _logger(work) as log:
        try:
            if kept is not None:
                log.info("%s holds the finished result of config %s, rerun because %s; it stays there until this "
                         "run (config %s) is complete, which works in %s", run_dir, kept.config_hash, why, ident.hash,
                         work)
            if force:
                from protocols.train_loop import discard_checkpoints

                discard_checkpoints(work)  # --force retrains: nothing of an earlier run is resumed
            atomic_write_text(work / CONFIG_FILE, _yaml(cfg))
            from protocols.train_loop import train_and_evaluate
            with live_cell(run_dir):
                result = train_and_evaluate(cfg, settings, work, base, log, ident)
            if result.config_hash != ident.hash:  # a result is only ever recorded under its own config
                raise RuntimeError(f"internal error: result of config {result.config_hash} under {ident.hash}")
        except KeyboardInterrupt:
            log.info("interrupted; rerun to resume from the last checkpoint"
                     + (f" (the finished result in {run_dir} is untouched)" if kept is not None else ""))
            raise
        except Exception as e:  # recorded; the sweep goes on
            out = _failed(key, work, base, e, log)
            if kept is not None:
                out["error"] += f" (the finished result of config {kept.config_hash} in {run_dir} is kept)"
            return out
        if work != run_dir:
            result = _relocated(result, work, run_dir)
        write_result(work, result)
    if work != run_dir:
        swap_in(work, run_dir)
    return {"key": key, "status": "ok", "psnr": result.metrics.get("psnr"), **({"rerun": why} if why else {})}


def _relocated(result: RunResult, work: Path, run_dir: Path) -> RunResult:
    """``result`` with the paths it records below ``work`` named where they will be, below ``run_dir``."""
    def move(x):
        if isinstance(x, str) and (x == str(work) or x.startswith(f"{work}{os.sep}")):
            return str(run_dir) + x[len(str(work)):]
        if isinstance(x, dict):
            return {k: move(v) for k, v in x.items()}
        if isinstance(x, list):
            return [move(v) for v in x]
        return x

    return RunResult.from_dict(move(result.to_dict()))


def _device_label(device: str) -> str:
    from smgs.device import device_name

    try:
        return device_name(device)
    except Exception:   # naming must never hide the run's own error
        return device


def _finished(res_path: Path, ident: CellKey, force: bool) -> bool:
    """A finished result of this very cell is there (its config and inputs: ``ident``), and
    ``force`` is off."""
    if res_path.parent.exists() and not res_path.parent.is_dir():
        raise NotADirectoryError(f"{res_path.parent} is a file where the run's folder should be; move it away")
    if res_path.is_dir():
        raise IsADirectoryError(f"{res_path} is a folder where the run's results file should be; move it away")
    if force or not res_path.exists():
        return False
    old = _finished_result(res_path)
    return old is not None and ident.mismatch(old.config_hash, old.inputs) is None


def _finished_result(res_path: Path) -> RunResult | None:
    """The finished (ok) result at ``res_path``, of whatever config; None when there is none or it
    is unreadable (run again). One of a newer smgs is never replaced: ``LeftAlone``."""
    try:
        old = read_result(res_path)
    except NewerResults as e:
        raise LeftAlone(f"{e}; nothing was changed (or move the folder away to rerun the cell with this smgs)") from None
    except (OSError, ValueError):
        return None
    return old if old.status == "ok" else None


def _check_same_kind(kept: RunResult, cfg: dict, run_dir: Path) -> None:
    """A cell holds one kind of result: a trained run is never replaced by the evaluation of a PLY
    (``protocols.evaluate_ply``), nor an evaluation by a trained run, without ``force``;
    ``LeftAlone`` names both and the fix."""
    evaluation, ply = bool(kept.source), (cfg.get("ply") or {}).get("path")
    if evaluation == bool(ply):
        return
    if ply:
        raise LeftAlone(f"{run_dir} holds a trained run ({kept.method}, {kept.steps} steps, config {kept.config_hash}); "
                        f"the evaluation of {ply} would replace it (its results.json, checkpoint and config.yaml); "
                        "nothing was changed. A cell holds one kind of result: evaluate the file into a cell of its "
                        f"own, budget.name={PRETRAINED} (the default) or budget.name={PRETRAINED}-NAME, or add --force "
                        "to replace the trained run with the evaluation")
    raise LeftAlone(f"{run_dir} holds the evaluation of {kept.source.get('ply')} (sha256 "
                    f"{str(kept.source.get('sha256'))[:12]}…, not trained here); training {cfg['method']['name']} "
                    "here would replace it; nothing was changed. A cell holds one kind of result: add --force to "
                    "replace the evaluation with the trained run (and evaluate the file again with "
                    f"budget.name={PRETRAINED}-NAME to keep its row)")


def _check_same_model(kept: RunResult, cfg: dict, run_dir: Path) -> None:
    """A cell that evaluates a PLY (``protocols.evaluate_ply``) never replaces the evaluation of
    another file without ``force``: ``LeftAlone`` says how to keep both."""
    old, new = (kept.source or {}).get("sha256"), (cfg.get("ply") or {}).get("sha256")
    if not old or not new or old == new:
        return
    from protocols.grid import own_budget_name

    path = Path(cfg["ply"]["path"])
    raise LeftAlone(f"{run_dir} holds the evaluation of {kept.source.get('ply')} (sha256 {old[:12]}…), another "
                    f"file than {path} (sha256 {new[:12]}…); nothing was changed. To keep both, give this one a "
                    f"cell of its own: budget.name={own_budget_name(path)} (its own row in the report); to "
                    "replace that evaluation, add --force")


class LeftAlone(RuntimeError):
    """The cell's folder holds what this run must not replace; nothing of it was changed."""


def _failed(key: str, run_dir: Path, base: RunResult, e: Exception, log: logging.Logger | None) -> dict:
    """Record a failed (or skipped, for missing data) cell in its results.json where it can."""
    from protocols.cell_scene import DatasetMissing

    if log:
        log.error(traceback.format_exc())
    base.status = "skipped" if isinstance(e, DatasetMissing) else "failed"
    base.error = f"{type(e).__name__}: {e}"
    base.versions = versions(base.config.get("backend", "auto"), _device_label(base.config.get("device", "cpu")))
    try:
        base.versions["renderer"] = asked_renderer(base.config).describe() + " asked"
    except ValueError:   # an unknown one: the error says so
        pass
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
