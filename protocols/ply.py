"""The 3DGS PLY at the edges of a run: a model read from a PLY instead of trained (``make_method``),
the trained model written as a PLY at the end (``after_run``, config ``export_ply``), and the PLY of
a finished run directory (``export_run``). The commands are ``protocols.export_ply`` and
``protocols.evaluate_ply``; the format is ``smgs.io.ply``.
"""

from __future__ import annotations

import hashlib
import json
import logging
from pathlib import Path

import torch

from protocols.results import RunResult
from protocols.run_settings import CellSettings

PLY_FILE = "point_cloud.ply"
"""The file name of a run's exported model (the name the original 3DGS code uses)."""


def sha256(path: Path | str) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 22), b""):
            h.update(block)
    return h.hexdigest()


def read_scored_ply(path: Path | str):
    """The model of a PLY to be scored (``smgs.io.ply.read_ply``); a file of no Gaussians is refused:
    it renders the background alone, a score of nothing (a collapsed run's export reads back as
    written, but is not evaluated as a model)."""
    from smgs.io.ply import PlyFormatError, read_ply

    splats = read_ply(path)
    if len(splats) == 0:
        raise PlyFormatError(path, "0 vertices: a model of no Gaussians, nothing to score",
                             "a model with at least one Gaussian ('element vertex N', N ≥ 1)")
    return splats


def is_ply_argument(arg: str) -> bool:
    """Whether a command-line argument names the PLY file rather than a key=value setting: a name
    ending in .ply is the file even with '=' in it (``iter=30000.ply``)."""
    return "=" not in arg or arg.lower().endswith(".ply") or Path(arg).is_file()


def make_method(cfg: dict, settings: CellSettings, scene, result: RunResult, device: torch.device):
    """The run's method, created with the cell's ``settings`` (``protocols.run_settings.cell_settings``):
    by name to be trained or, when ``cfg["ply"]`` names a file (``protocols.evaluate_ply``), the model
    of that file with zero training steps; ``result.source`` then records where it came from."""
    from baselines.registry import create_method

    name = cfg["method"]["name"]
    resolved = settings.for_method()
    src = cfg.get("ply")
    if not src:
        return create_method(name, scene, device=device, resolved=resolved)
    from baselines.splatting import GaussianSplatting

    path = Path(src["path"])
    digest = sha256(path)
    if src.get("sha256") and digest != src["sha256"]:
        raise ValueError(f"{path} changed since the run was set up (sha256 {digest[:12]}…, expected "
                         f"{src['sha256'][:12]}…); run protocols.evaluate_ply again")
    splats = read_scored_ply(path)
    if splats.mode != name:
        raise ValueError(f"{path} holds a {splats.mode} model (extras: {sorted(splats.extras) or 'none'}), "
                         f"the run is for method {name!r}")
    method = GaussianSplatting.from_splats(scene, splats, resolved.config, where=path, device=device, run=resolved.run)
    result.source = {"kind": "pretrained", "trained_here": False, "ply": str(path.resolve()), "sha256": digest,
                     "format": splats.meta.get("format"), "sh_degree": splats.sh_degree,
                     "num_gaussians": len(splats), "written_by": "smgs" if "version" in splats.meta else "another tool",
                     "header": {k: v for k, v in splats.meta.items() if k != "format"}}
    return method


def after_run(cfg: dict, run_dir: Path, method, result: RunResult, log: logging.Logger) -> None:
    """End of a run: a model this run did not train has no train time; with ``export_ply`` the
    model is written to ``run_dir/point_cloud.ply``."""
    if result.source:
        result.train_seconds = None
    if not cfg.get("export_ply"):
        return
    export = getattr(method, "export_ply", None)
    if not callable(export):
        raise TypeError(f"export_ply=true, but method {cfg['method']['name']!r} cannot write a PLY "
                        "(only the built-in splatting methods do)")
    path = export(run_dir / PLY_FILE)
    result.diagnostics["ply"] = str(path)
    log.info("model written to %s", path)


def export_run(run_dir: Path | str, out: Path | str | None = None) -> tuple[Path, int, str]:
    """The PLY of a run directory's last checkpoint (the final model of a finished run); returns
    the file, the checkpoint's step and the run's status ("ok", "failed", or "unfinished")."""
    from baselines.splatting import export_checkpoint_ply
    from protocols.results import POINTER, RESULTS_FILE, read_result

    run_dir = Path(run_dir)
    ptr = run_dir / POINTER
    if not ptr.is_file():
        raise FileNotFoundError(f"{run_dir}: no {POINTER} (not a run directory, or the run saved no checkpoint yet)")
    ckpt = run_dir / json.loads(ptr.read_text())["dir"]
    res = run_dir / RESULTS_FILE
    status = read_result(res).status if res.is_file() else "unfinished"
    path, step = export_checkpoint_ply(ckpt, Path(out) if out is not None else run_dir / PLY_FILE)
    return path, step, status

