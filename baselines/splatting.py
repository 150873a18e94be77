"""The four built-in methods (3dgs, gef_only, softmax_only, softmax_gs): one class, the render mode
is the switch (fixed per name by the registry)."""

from __future__ import annotations

import io
import json
from pathlib import Path
from typing import Any, ClassVar

import torch

import smgs
from baselines.method import SceneNeeds
from smgs.camera import Camera
from smgs.data.scene import Scene
from smgs.raster import RenderOutput
from smgs.train.config import TrainConfig, from_dict, to_dict
from smgs.train.trainer import Trainer

CHECKPOINT = "checkpoint.pt"
MANIFEST = "checkpoint.json"


def _atomic_write(path: Path, data: bytes) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_bytes(data)
    tmp.replace(path)


class GaussianSplatting:
    """Gaussian splatting trained by ``smgs.train.Trainer``. SfM points are optional (flat or
    random initialisation without them); view dependence is used when the scene has it."""

    needs: ClassVar[SceneNeeds] = SceneNeeds(optional=frozenset({"sfm_points", "view_dependence", "background"}))

    def __init__(self, scene: Scene, config: dict[str, Any] | TrainConfig | None = None, *,
                 name: str | None = None, device: torch.device | str) -> None:
        cfg = config if isinstance(config, TrainConfig) else from_dict(TrainConfig, config or {})
        self.name = name or cfg.mode
        self.notes = self.needs.check(scene, self.name)
        self.trainer = Trainer(scene, cfg, device=device)

    @property
    def device(self) -> torch.device:
        return self.trainer.device

    @property
    def config(self) -> TrainConfig:
        return self.trainer.cfg

    def train_step(self, step: int) -> dict[str, float]:
        return self.trainer.train_step(step)

    @torch.no_grad()
    def render(self, camera: Camera) -> RenderOutput:
        return self.trainer.render(camera)

    def num_gaussians(self) -> int:
        return len(self.trainer.gaussians)

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
        _atomic_write(path / CHECKPOINT, buf.getvalue())
        manifest = {**self.describe(), "num_gaussians": self.num_gaussians(),
                    "versions": {"smgs": smgs.__version__, "torch": torch.__version__}}
        _atomic_write(path / MANIFEST, json.dumps(manifest, indent=1).encode())

    def load(self, path: str | Path) -> None:
        """Restore a checkpoint written on any device onto this method's device."""
        state = torch.load(Path(path) / CHECKPOINT, map_location=self.device, weights_only=False)
        if state.get("method") != self.name:
            raise ValueError(f"checkpoint {path} is of method {state.get('method')!r}, not {self.name!r}")
        self.trainer.load_state_dict(state["trainer"])
