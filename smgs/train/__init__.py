"""Training: Gaussians and activations, optimiser groups, loss, densification, the trainer."""

from smgs.train.config import (BUDGETS, HPARAMS, DensifyConfig, GaussianConfig, LossConfig, OptimConfig,
                               ParamInit, TrainConfig, densify_config, from_dict, hparams, pattern_config,
                               to_dict)
from smgs.train.gaussians import PARAM_NAMES, Gaussians
from smgs.train.optim import GaussianOptimizer, expon_lr
from smgs.train.strategies import SIZE_PRUNE_3DGS, SIZE_PRUNE_SOFTMAX_GS, DefaultStrategy
from smgs.train.trainer import NonFiniteError, Trainer

__all__ = ["TrainConfig", "GaussianConfig", "OptimConfig", "LossConfig", "DensifyConfig", "ParamInit",
           "HPARAMS", "BUDGETS", "hparams", "densify_config", "pattern_config", "from_dict", "to_dict",
           "Gaussians", "PARAM_NAMES", "GaussianOptimizer", "expon_lr", "DefaultStrategy",
           "SIZE_PRUNE_3DGS", "SIZE_PRUNE_SOFTMAX_GS", "Trainer", "NonFiniteError"]
