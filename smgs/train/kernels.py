"""Every compiled kernel a training run uses, built (or loaded from the cache) before its clock
starts: a build takes minutes the first time, and a benchmark must never count it as a method's
training time. The caller times this call and records it apart (``build_seconds``)."""

from __future__ import annotations

import torch

from smgs.raster import constants as K
from smgs.raster import projection, rasterize_splats, resolve_backend
from smgs.train import image_loss


def prepare_kernels(backend: str = "auto", device: torch.device | str = "cpu",
                    dtype: torch.dtype = torch.float32, t_min: float = K.T_MIN, sort: str = "global") -> str:
    """Build or load the renderer backend (for this ``t_min``), the compiled projection and the
    compiled training loss wherever a run on these tensors would use them; return the renderer
    backend it will use. Raises ``BuildError`` for a failed build, as the run would. With
    ``sort="per_pixel"`` off the CPU, the CPU window kernel that renders it on host copies too."""
    device = torch.device(device)
    name = resolve_backend(backend, device, dtype)
    if sort == "per_pixel" and device.type != "cpu" and backend == "auto":
        from smgs.raster import backend_available

        backend_available("cpu", "cpu")   # builds it (or says it cannot be)
    if name != "reference":
        # one tiny render (a plain valid splat) through the public entry point builds exactly the
        # variant the run needs
        t = lambda *v: torch.tensor(v, device=device, dtype=dtype)  # noqa: E731
        rasterize_splats(t([2.0, 2.0]), t([1.0, 0.0, 1.0]), t(0.5), t([0.5, 0.5, 0.5]), t(1.0), None, None, None,
                         4, 4, mode="3dgs", backend=name, t_min=t_min)
    if device.type == "cpu" and dtype == torch.float32:
        if name != "reference":   # the reference renderer keeps its projection in PyTorch
            projection.fused_available()
        image_loss.fused_available()
    return name
