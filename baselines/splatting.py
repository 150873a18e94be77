"""The four built-in methods (3dgs, gef_only, softmax_only, softmax_gs): one class, the render mode
is the switch (fixed per name by the registry)."""

from __future__ import annotations

import io
import json
import pickle
from pathlib import Path
from typing import Any, ClassVar

import torch

import smgs
from baselines.method import RunSettings, SceneNeeds
from baselines.trainer_settings import train_config
from smgs.camera import Camera
from smgs.data.scene import Scene
from smgs.device import as_device
from smgs.raster import RenderOutput
from smgs.atomic import atomic_write_bytes
from smgs.io.gaussians import (gaussians_from_splats, splats_extent, splats_from_state,
                               splats_from_trainer, train_overrides)
from smgs.io.ply import PlySplats, read_ply, write_ply
from smgs.train.config import TrainConfig, current_train_keys, from_dict, to_dict, without_default_variants
from smgs.train.gaussians import Gaussians
from smgs.train.trainer import Trainer

CHECKPOINT = "checkpoint.pt"
MANIFEST = "checkpoint.json"


class GaussianSplatting:
    """Gaussian splatting trained by ``smgs.train.Trainer``. SfM points are optional (flat or
    random initialisation without them); view dependence is used when the scene has it."""

    needs: ClassVar[SceneNeeds] = SceneNeeds(optional=frozenset({"sfm_points", "view_dependence", "background"}))

    def __init__(self, scene: Scene, config: dict[str, Any] | TrainConfig | None = None, *,
                 name: str | None = None, device: torch.device | str, run: RunSettings | None = None,
                 settings: TrainConfig | None = None, gaussians: Gaussians | None = None) -> None:
        """``settings``: the run's TrainConfig as ``resolved_settings`` made it (the registry hands
        it over, so it is built once per run); without it, made here from ``config`` and ``run``.
        A TrainConfig given as ``config`` is taken as it is."""
        if isinstance(config, TrainConfig):
            if run is not None or settings is not None:
                raise ValueError("a TrainConfig is complete: give the run's settings in it, not as `run` or `settings`")
            settings = config
        cfg = settings if settings is not None else self.resolved_settings(config or {}, run)
        self.name = name or cfg.mode
        self.notes = self.needs.check(scene, self.name)
        self.trainer = Trainer(scene, cfg, gaussians, device=device)

    @property
    def device(self) -> torch.device:
        return self.trainer.device

    @classmethod
    def resolved_settings(cls, config: dict[str, Any], run: RunSettings | None) -> TrainConfig:
        """The run's TrainConfig, every default filled in (``ResolvedSettings``): the method's
        ``config`` mapped with ``run`` (``baselines.trainer_settings``), or as it is without one."""
        return from_dict(TrainConfig, train_config(config, run) if run else config)

    @classmethod
    def from_ply(cls, scene: Scene, path: str | Path, config: dict[str, Any] | None = None, *,
                 device: torch.device | str) -> "GaussianSplatting":
        """The model of a 3DGS PLY (``smgs.io.ply``), ready to render: the method its extras call
        for (``3dgs`` without any), ``config`` (a TrainConfig dict) under the file's own settings."""
        return cls.from_splats(scene, read_ply(path), config, where=path, device=device)

    @classmethod
    def from_splats(cls, scene: Scene, splats: PlySplats, config: dict[str, Any] | None = None,
                    where: str | Path = "<splats>", *, device: torch.device | str,
                    run: RunSettings | None = None) -> "GaussianSplatting":
        from baselines.method import merge_config

        config = train_config(config or {}, run) if run else config or {}
        cfg = from_dict(TrainConfig, merge_config(config, train_overrides(splats, where)))
        dev = as_device(device)
        g = gaussians_from_splats(splats, cfg.gaussians, splats_extent(splats, scene.extent, where), device=dev)
        return cls(scene, name=cfg.mode, device=dev, settings=cfg, gaussians=g)

    def export_ply(self, path: str | Path) -> Path:
        """Write the model as a 3DGS PLY (atomically; ``smgs.io.ply`` documents the layout)."""
        return write_ply(path, splats_from_trainer(self.trainer))

    @property
    def config(self) -> TrainConfig:
        return self.trainer.cfg

    def train_step(self, step: int) -> dict[str, float]:
        return self.trainer.train_step(step)

    @torch.no_grad()
    def render(self, camera: Camera) -> RenderOutput:
        return self.trainer.render(camera)

    @torch.no_grad()
    def render_leaders(self, camera: Camera) -> RenderOutput:
        """``render`` with the leading-splat map (``LeadingSplats``)."""
        return self.trainer.render(camera, leaders=True)

    def num_gaussians(self) -> int:
        return len(self.trainer.gaussians)

    def reset_steps(self, steps: int) -> list[int]:
        """The steps of a ``steps`` run that end in an opacity reset (``OpacityResets``)."""
        return self.trainer.strategy.reset_steps(steps)

    @torch.no_grad()
    def parameter_values(self) -> dict[str, torch.Tensor]:
        """The learned α, β, γ (γ relative to the scene extent) that this mode uses, for the
        report's diagnostics."""
        g = self.trainer.gaussians
        out = {}
        if self.trainer.use_gef:
            out["alpha"] = g.alpha
        if self.trainer.use_softmax:
            out["beta"], out["gamma"] = g.beta, g.gamma_rel
        return out

    def prepare(self) -> str:
        """Build or load the renderer, projection and loss kernels this run uses; returns the
        renderer backend and its variants."""
        from smgs.train.kernels import prepare_kernels

        renders = prepare_kernels(self.config.renderer, self.device, torch.float32, self.config.t_min,
                                  self.config.sort)
        return f"renderer backend {renders}"

    def describe(self) -> dict[str, Any]:
        return {"method": self.name, "config": to_dict(self.config), "hparams": self.config.optim.name,
                "step": self.trainer.step_count, "plan": self.notes + self.trainer.plan}

    def save(self, path: str | Path) -> None:
        """``path/checkpoint.pt`` (torch: parameters, Adam moments, densification state, random
        generators, step) and ``path/checkpoint.json`` (readable manifest), each written
        atomically."""
        path = Path(path)
        path.mkdir(parents=True, exist_ok=True)
        buf = io.BytesIO()
        torch.save({"method": self.name, "trainer": self.trainer.state_dict()}, buf)
        atomic_write_bytes(path / CHECKPOINT, buf.getvalue())
        manifest = {**self.describe(), "num_gaussians": self.num_gaussians(),
                    "versions": {"smgs": smgs.__version__, "torch": torch.__version__}}
        atomic_write_bytes(path / MANIFEST, json.dumps(manifest, indent=1).encode())

    def _as_compared(self, config: dict[str, Any]) -> dict[str, Any]:
        """A TrainConfig dict as a checkpoint's is compared with this run's: the renderer's variants
        left out where they ask for the default or where this device's renderer has no such axis
        (``smgs.identity.unused_variants``: a CUDA kernel set renders nothing differently on the CPU)."""
        from smgs.identity import unused_variants

        unused = unused_variants({"device": str(self.device), "backend": config.get("backend")})
        return {k: v for k, v in without_default_variants(config).items() if k not in unused}

    def load(self, path: str | Path) -> None:
        """Restore ``path/checkpoint.pt``. Refused: a file whose pickle would run code (only
        tensors and plain containers are read) and a checkpoint of another config (it would carry
        that config's state under this one's name). A checkpoint written on any device loads
        onto this method's device."""
        file = Path(path) / CHECKPOINT
        state = load_weights(file, map_location=self.device)
        if state.get("method") != self.name:
            raise ValueError(f"checkpoint {path} is of method {state.get('method')!r}, not {self.name!r}")
        saved = state.get("trainer", {}).get("config")
        if isinstance(saved, dict):   # written before a key's rename: read under today's names
            saved = current_train_keys(saved)
        diff = config_difference(self._as_compared(saved) if isinstance(saved, dict) else saved,
                                 self._as_compared(to_dict(self.config)))
        if diff:
            raise ValueError(f"checkpoint {file} was trained under another config ({diff}); it cannot "
                             "be resumed under this one (delete it, or rerun with --force)")
        self.trainer.load_state_dict(state["trainer"])


def export_checkpoint_ply(path: str | Path, out: str | Path) -> tuple[Path, int]:
    """Write the model of a checkpoint directory (written by ``GaussianSplatting.save``) as a 3DGS
    PLY without its scene; returns the file and the checkpoint's step."""
    path = Path(path)
    file = path / CHECKPOINT
    if not file.is_file():
        raise FileNotFoundError(f"{file}: no checkpoint there (GaussianSplatting.save writes {CHECKPOINT})")
    state = load_weights(file, map_location="cpu")
    trainer = state.get("trainer") if isinstance(state, dict) else None
    if not isinstance(trainer, dict) or trainer.get("format") != "smgs.train/1":
        raise ValueError(f"{file}: not a checkpoint of the built-in splatting methods (method "
                         f"{state.get('method') if isinstance(state, dict) else None!r}); only those export a PLY")
    return write_ply(out, splats_from_state(trainer)), int(trainer["step"])


# Settings that say where a run happens, not what it computes: a checkpoint may move between them.
PLACEMENT_KEYS = frozenset({"device"})


def config_difference(saved: Any, current: dict[str, Any], where: str = "") -> str:
    """The first setting in which a checkpoint's config differs from ``current`` ("" if none)."""
    if not isinstance(saved, dict):
        return "the checkpoint records no config"
    for k in sorted(set(saved) | set(current)):
        if k in PLACEMENT_KEYS and not where:
            continue
        a, b = saved.get(k, "<absent>"), current.get(k, "<absent>")
        if isinstance(a, dict) and isinstance(b, dict):
            inner = config_difference(a, b, f"{where}{k}.")
            if inner:
                return inner
        elif a != b and not (isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)) and list(a) == list(b)):
            return f"{where}{k}: checkpoint {a!r}, this run {b!r}"
    return ""


def load_weights(file: Path, map_location: str | torch.device = "cpu") -> Any:
    """``torch.load`` with ``weights_only=True``: tensors, numbers, strings and containers only, so
    a shared or planted checkpoint cannot run code when it is read."""
    try:
        return torch.load(file, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as e:
        raise ValueError(f"checkpoint {file} refused: it holds objects whose loading could run code, "
                         f"which an smgs checkpoint never has ({one_line(e)}). Only load checkpoints "
                         "you trust; an smgs run rewrites it after --force") from None
    except (RuntimeError, EOFError, OSError) as e:
        raise ValueError(f"checkpoint {file} is unreadable ({type(e).__name__}: {one_line(e)}); "
                         "rerun with --force to discard it") from None


def one_line(e: BaseException, limit: int = 200) -> str:
    text = " ".join(str(e).split())
    return text if len(text) <= limit else text[:limit] + "…"
