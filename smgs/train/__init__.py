"""Training: Gaussians and activations, optimiser groups, loss, densification, the trainer."""

from smgs.lazy import lazy_names

# on first use: the densification strategies' table (smgs list strategies) reads without torch
__getattr__ = lazy_names("smgs.train", {
    **dict.fromkeys(("BUDGETS", "HPARAMS", "DensifyConfig", "GaussianConfig", "LossConfig", "OptimConfig", "ParamInit",
                     "TrainConfig", "densify_config", "from_dict", "hparams", "pattern_config", "to_dict"), "config"),
    **dict.fromkeys(("PARAM_NAMES", "Gaussians"), "gaussians"),
    **dict.fromkeys(("GaussianOptimizer", "expon_lr"), "optim"),
    **dict.fromkeys(("SIZE_PRUNE_3DGS", "SIZE_PRUNE_SOFTMAX_GS", "DefaultStrategy"), "strategies"),
    **dict.fromkeys(("NonFiniteError", "Trainer"), "trainer")})

__all__ = ["TrainConfig", "GaussianConfig", "OptimConfig", "LossConfig", "DensifyConfig", "ParamInit",
           "HPARAMS", "BUDGETS", "hparams", "densify_config", "pattern_config", "from_dict", "to_dict",
           "Gaussians", "PARAM_NAMES", "GaussianOptimizer", "expon_lr", "DefaultStrategy",
           "SIZE_PRUNE_3DGS", "SIZE_PRUNE_SOFTMAX_GS", "Trainer", "NonFiniteError"]
