"""Every compiled kernel a training run uses, built (or loaded from the cache) before its clock
starts: a build takes minutes the first time, and a benchmark must never count it as a method's
training time. The caller times this call and records it apart (``build_seconds``)."""

from __future__ import annotations

import torch

from smgs.camera import Camera
from smgs.raster import constants as K
from smgs.raster import projection, rasterize, rasterize_splats, render_variant
from smgs.raster.backends import Renderer, as_renderer
from smgs.train import image_loss


def prepare_kernels(backend: str | Renderer = "auto", device: torch.device | str = "cpu",
                    dtype: torch.dtype = torch.float32, t_min: float = K.T_MIN, sort: str = "global") -> str:
    """Build or load the renderer backend's kernels of the variant a run asks for (for this
    ``t_min``; a variant whose kernels project too, its projection), the compiled projection and the
    compiled training loss wherever a run on these tensors would use them; return what renders
    (``Variant.describe``: the backend and its variants). Raises ``BuildError`` for a failed build, as
    the run would. With ``sort="per_pixel"`` off the CPU, the CPU window kernel that renders it on
    host copies too."""
    device = torch.device(device)
    choice = as_renderer(backend)
    v = render_variant(choice, device, dtype)
    if sort == "per_pixel" and device.type != "cpu" and v.kernel_set.pixel is None:
        from smgs.raster import backend_available

        backend_available("cpu", "cpu")   # builds it (or says it cannot be)
    if v.backend != "reference":
        # one tiny render (a plain valid splat) through the public entry point builds exactly the
        # variant the run needs; a fused variant's through the 3D entry point, which its renders take
        resolved = Renderer(v.backend, v.kernels, v.glue or None)
        t = lambda *x: torch.tensor(x, device=device, dtype=dtype)  # noqa: E731
        rasterize_splats(t([2.0, 2.0]), t([1.0, 0.0, 1.0]), t(0.5), t([0.5, 0.5, 0.5]), t(1.0), None, None, None,
                         4, 4, mode="3dgs", backend=resolved, t_min=t_min)
        if v.kernel_set.fused is not None and sort == "global":
            cam = Camera.look_at([0.0, 0.0, -2.0], [0.0, 0.0, 0.0], [0.0, -1.0, 0.0], 4.0, 4.0, 4, 4)
            rasterize(t([0.0, 0.0, 0.0]), t([1.0, 0.0, 0.0, 0.0]), t([0.1, 0.1, 0.1]), t(0.5), t([0.5, 0.5, 0.5]),
                      cam, mode="3dgs", backend=resolved, t_min=t_min)
    if device.type == "cpu" and dtype == torch.float32:
        if v.backend != "reference":   # the reference renderer keeps its projection in PyTorch
            projection.fused_available()
        image_loss.fused_available()
    return v.describe(sort)
