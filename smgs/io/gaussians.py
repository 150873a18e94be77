"""Between the trainer's Gaussians (``smgs.train``) and the PLY layout (``smgs.io.ply``).

Export writes what the model renders with: the raw parameters, the SH coefficients of the degree
in use at the model's step, the α/β/γ its mode uses, and the settings that change its renders
(mode, k_max, eq15, t_min, colour clamp, the activations of α/β/γ and the extent γ is relative to)
as ``comment smgs`` lines. Import turns a file back into ``Gaussians`` plus the ``TrainConfig``
overrides that render them the same way.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import torch

from smgs.io.ply import EXTRAS, PlyFormatError, PlySplats
from smgs.raster import mode_flags
from smgs.raster.sh import num_sh_bases
from smgs.train.config import GaussianConfig
from smgs.train.gaussians import Gaussians
from smgs.train.trainer import Trainer, active_sh_degree
from smgs.version import __version__

# PLY extra -> (Gaussians parameter group, GaussianConfig field)
_EXTRA_PARAM = {"gef_alpha": "alpha", "softmax_beta": "beta", "softmax_gamma": "gamma"}
_EQ15 = ("solved", "printed")


def _np(t: torch.Tensor) -> np.ndarray:
    return t.detach().to("cpu", torch.float32).numpy()


def splats_from_state(state: dict[str, Any]) -> PlySplats:
    """A model's PLY content from its trainer state (``Trainer.state_dict()``, or the same keys:
    ``config`` (TrainConfig dict), ``step``, ``extent``, ``gaussians`` (raw parameter groups))."""
    cfg, raw = state["config"], state["gaussians"]
    mode = str(cfg["mode"])
    use_gef, use_softmax = mode_flags(mode)
    sh = torch.cat([raw["sh0"], raw["shN"]], dim=1)
    max_degree = math.isqrt(sh.shape[1]) - 1
    degree = active_sh_degree(int(state["step"]), int(cfg["sh_degree_interval"]), max_degree)
    gcfg = cfg["gaussians"]
    extras = {e: _np(raw[p]) for e, p in _EXTRA_PARAM.items()
              if (use_gef if p == "alpha" else use_softmax)}
    meta = {"version": __version__, "mode": mode, "step": str(int(state["step"])),
            "extent": repr(float(state["extent"])), "k_max": str(int(cfg["k_max"])), "eq15": str(cfg["eq15"]),
            "t_min": repr(float(cfg["t_min"])), "clamp_colors": str(bool(gcfg["clamp_colors"])).lower()}
    for e in extras:
        meta[f"activation.{e}"] = str(gcfg[_EXTRA_PARAM[e]]["activation"])
    return PlySplats(_np(raw["means"]), _np(sh[:, :num_sh_bases(degree)]), _np(raw["opacities"]),
                     _np(raw["scales"]), _np(raw["quats"]), extras, meta)


def splats_from_trainer(trainer: Trainer) -> PlySplats:
    """``splats_from_state`` of a live trainer (its Gaussians' own extent, which γ is relative to)."""
    from smgs.train.config import to_dict

    g = trainer.gaussians
    return splats_from_state({"config": to_dict(trainer.cfg), "step": trainer.step_count, "extent": g.extent,
                              "gaussians": g.params})


def train_overrides(splats: PlySplats, where: Path | str = "<splats>") -> dict[str, Any]:
    """TrainConfig overrides that render ``splats`` as the file says: its mode, every SH degree
    from the start, no training steps, no densification, the activations of its extras and the
    render settings recorded by smgs (absent for a file from another tool: the defaults stay)."""
    mode = splats.mode
    meta = splats.meta
    if "mode" in meta and meta["mode"] != mode:
        raise PlyFormatError(where, f"comment 'smgs mode {meta['mode']}' but the properties make a {mode} model "
                             f"(extras: {sorted(splats.extras) or 'none'})", "the extras of that mode")
    gauss: dict[str, Any] = {"max_sh_degree": splats.sh_degree}
    for e in splats.extras:
        p = _EXTRA_PARAM[e]   # the initial value is unused: the file's values replace it
        gauss[p] = {"init": getattr(GaussianConfig(), p).init, "activation": meta.get(f"activation.{e}", "exp")}
    out: dict[str, Any] = {"mode": mode, "steps": 0, "sh_degree_interval": 0, "gaussians": gauss,
                           "densify": {"enabled": False}}
    try:
        if "k_max" in meta:
            out["k_max"] = int(meta["k_max"])
        if "t_min" in meta:
            out["t_min"] = float(meta["t_min"])
        if "clamp_colors" in meta:
            gauss["clamp_colors"] = {"true": True, "false": False}[meta["clamp_colors"]]
    except (ValueError, KeyError) as e:
        raise PlyFormatError(where, f"unreadable smgs render setting in the header ({e})",
                             "k_max an integer, t_min a number, clamp_colors true or false") from e
    if "eq15" in meta:
        if meta["eq15"] not in _EQ15:
            raise PlyFormatError(where, f"comment 'smgs eq15 {meta['eq15']}'", f"one of {list(_EQ15)}")
        out["eq15"] = meta["eq15"]
    return out


def splats_extent(splats: PlySplats, default: float, where: Path | str = "<splats>") -> float:
    """The extent γ is relative to: the file's ``smgs extent`` or, without it, ``default``."""
    if "extent" not in splats.meta:
        return float(default)
    try:
        extent = float(splats.meta["extent"])
    except ValueError as e:
        raise PlyFormatError(where, f"comment 'smgs extent {splats.meta['extent']}'", "a positive number") from e
    if not extent > 0 or not math.isfinite(extent):
        raise PlyFormatError(where, f"comment 'smgs extent {splats.meta['extent']}'", "a positive number")
    return extent


def gaussians_from_splats(splats: PlySplats, cfg: GaussianConfig, extent: float, *,
                          device: torch.device | str) -> Gaussians:
    """Gaussians on ``device`` holding the file's raw values (cfg's activations apply, as ``train_overrides``
    sets them); groups the file lacks (α, β, γ of a mode without them) take cfg's initial values."""
    n = len(splats)
    t = (lambda a: torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32)).to(device))
    # from_points gives every group its initial value; the file's groups then replace them
    g = Gaussians.from_points(t(splats.means), torch.zeros(n, 3, device=device), cfg, extent, splats.sh_degree,
                              scales=torch.ones(n, 3, device=device), device=device)
    params = {k: v.detach() for k, v in g.params.items()}
    params.update(means=t(splats.means), scales=t(splats.scales), quats=t(splats.quats),
                  opacities=t(splats.opacities), sh0=t(splats.sh[:, :1]), shN=t(splats.sh[:, 1:]))
    for e in EXTRAS:
        if e in splats.extras:
            params[_EXTRA_PARAM[e]] = t(splats.extras[e])
    g.params = {k: v.contiguous().requires_grad_(True) for k, v in params.items()}
    return g
