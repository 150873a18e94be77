"""The built-in trainer's defaults that every built-in method's config shows, from their one home.

``k_max``, ``k_max_scope``, ``eq15`` and the hyperparameter set (``optim``) are defaults of
``smgs.train.config.TrainConfig``. Each configs/method/*.yaml of a built-in method takes them from
the Hydra config group ``method/train`` option ``splatting``, which is made here from those
defaults (Hydra's ConfigStore), not restated: the composed config (``smgs run --cfg job``) and
config.yaml still show the user what they can override (``method.train.k_max=64``), and a default
changed in the code shows there too.
"""

from __future__ import annotations

from typing import Any

from smgs.train.config import OptimConfig, TrainConfig

GROUP, OPTION = "method/train", "splatting"
SHOWN: tuple[str, ...] = ("k_max", "k_max_scope", "eq15")
"""The TrainConfig keys shown with their defaults (the ones a study of the method changes most)."""


def trainer_defaults() -> dict[str, Any]:
    """The shown keys with the values TrainConfig gives them, and the default hyperparameter set."""
    return {**{key: getattr(TrainConfig, key) for key in SHOWN}, "optim": OptimConfig.name}


def register() -> None:
    """Make ``method/train=splatting`` known to Hydra (idempotent: the same node each time)."""
    from hydra.core.config_store import ConfigStore

    ConfigStore.instance().store(group=GROUP, name=OPTION, node=trainer_defaults())
