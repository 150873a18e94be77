"""The renderer's backends and their variants, in one registry (docs/renderer.md#backends-and-variants).

A backend composites projected splats (``fn(Splats2D, CompositeSettings) -> RenderOutput``,
``smgs.raster.composite_inputs``) with one of its kernel sets (``Kernels``: the functions, named as
``"module:function"`` and imported when used, so that listing a backend never compiles or loads a
kernel), on one kind of device, with one of its glues (how the Python side drives the device:
``smgs.raster.device_glue``). A run asks for a ``Renderer`` (backend, kernels, glue; a variant left
unset is its environment variable's, else the backend's default) and renders with the ``Variant``
it resolves to on its device, which every result records (``Variant.describe``).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

if TYPE_CHECKING:   # a type only: the table of backends reads without torch (smgs list renderers)
    import torch


@dataclass(frozen=True)
class Kernels:
    """One set of a backend's kernels. ``composite``: the global order (every backend has it);
    ``pixel``: a per-pixel order or the leading-splat map too, None where the set has none (those
    renders then composite host copies: ``smgs.raster.api``), with the variance-regulariser sums
    only where ``pixel_reg``; ``fused``: the whole render of 3D Gaussians, projection included, in
    the global order without the leading-splat map (None: project, then composite)."""

    composite: str
    pixel: str | None = None
    pixel_reg: bool = False
    fused: str | None = None
    about: str = ""


@dataclass(frozen=True)
class Backend:
    """A renderer backend: its kernel sets by name (the first the default), its glues (the first the
    default; none: one way only), the one kind of device it renders on (None: any) and whether it
    renders float32 only (the compiled ones). ``available``: ``"module:function"`` saying whether its
    toolchain is here (None: always). ``env``: the environment variable each variant axis falls back
    to where a run leaves it unset."""

    name: str
    about: str
    kernels: dict[str, Kernels]
    glues: tuple[str, ...] = ()
    device: str | None = None
    float32_only: bool = True
    available: str | None = None
    env: dict[str, str] = field(default_factory=dict)

    def axes(self) -> dict[str, tuple[str, ...]]:
        """Each variant axis with a choice, and its choices (the first the default)."""
        out = {"kernels": tuple(self.kernels), "glue": self.glues}
        return {axis: choices for axis, choices in out.items() if len(choices) > 1}


KERNELS_ENV = "SMGS_CUDA_KERNELS"
GLUE_ENV = "SMGS_CUDA_GLUE"

_REF = "smgs.raster.reference:rasterize_splats_reference"
_CPU = "smgs.raster.cpu:rasterize_splats_cpu"

BACKENDS: dict[str, Backend] = {
    "reference": Backend("reference", "PyTorch, any device and dtype: the oracle the others are tested against",
                         {"default": Kernels(_REF, pixel=_REF, pixel_reg=True)}, float32_only=False),
    "cpu": Backend("cpu", "compiled C++ (SIMD over a tile's pixels, threads over tiles; SMGS_CPU_ISA picks the "
                   "SIMD path)", {"default": Kernels(_CPU, pixel=_CPU)}, device="cpu",
                   available="smgs.raster.cpu:is_available"),
    "cuda": Backend(
        "cuda", "compiled CUDA (docs/cuda.md)",
        {"default": Kernels("smgs.raster.cuda:rasterize_splats_cuda",
                            about="compositing in the global order; ran on a GPU once, changed since "
                                  "(docs/cuda.md#what-has-run-on-a-gpu)"),
         "v2": Kernels("smgs.raster.cuda_v2:rasterize_splats_cuda_v2",
                       pixel="smgs.raster.cuda_v2:rasterize_splats_pixel_cuda",
                       fused="smgs.raster.cuda_v2:rasterize_fused",
                       about="opt-in: fused projection, v2 compositing, per-pixel order and leading-splat map on "
                             "the GPU")},
        glues=("verified", "lean"), device="cuda", available="smgs.raster.cuda:is_available",
        env={"kernels": KERNELS_ENV, "glue": GLUE_ENV}),
}
BACKEND_NAMES: tuple[str, ...] = tuple(BACKENDS)
AXES = ("kernels", "glue")
KNOWN: dict[str, frozenset[str]] = {axis: frozenset(c for b in BACKENDS.values() for c in b.axes().get(axis, ()))
                                    for axis in AXES}
"""Every variant of each axis that some backend has."""


@dataclass(frozen=True)
class Renderer:
    """What a run asks of the renderer: a backend (``auto``: the fastest available for the tensors)
    and its variants; None leaves a variant to its environment variable (``Backend.env``), else to
    the backend's default. A variant the backend has no such axis for is not used."""

    backend: str = "auto"
    kernels: str | None = None
    glue: str | None = None

    def describe(self) -> str:
        """What was asked, e.g. ``auto (kernels v2)`` (the variants left unset unnamed)."""
        asked = [f"{axis} {getattr(self, axis)}" for axis in AXES if getattr(self, axis) is not None]
        return self.backend + (f" ({', '.join(asked)})" if asked else "")

    def __post_init__(self) -> None:
        if self.backend != "auto" and self.backend not in BACKENDS:
            raise ValueError(f"unknown renderer backend {self.backend!r}; expected 'auto' or one of "
                             f"{', '.join(BACKENDS)}")
        for axis in AXES:
            check_choice(axis, getattr(self, axis), axis)


def check_choice(axis: str, value: str | None, where: str) -> None:
    """Refuse a variant that no backend has (``where`` names the setting, for the error)."""
    if value is not None and value not in KNOWN[axis]:
        raise ValueError(f"{where}={value!r} names no {axis} variant of any renderer backend; choose one of "
                         f"{', '.join(sorted(KNOWN[axis]))} (docs/renderer.md#backends-and-variants)")


def is_default(axis: str, value: str | None) -> bool:
    """Whether a variant asks for what no choice asked before variants were settings: unset, or the
    default of every backend with that axis (how a result's identity leaves it out)."""
    return value is None or all(choices[0] == value for b in BACKENDS.values()
                                for a, choices in b.axes().items() if a == axis)


def as_renderer(choice: str | Renderer) -> Renderer:
    """A ``Renderer``; a bare backend name asks for its variants' defaults (or environment)."""
    return choice if isinstance(choice, Renderer) else Renderer(str(choice))


@dataclass(frozen=True)
class Variant:
    """The backend a render resolved to and the variant of each of its axes."""

    backend: str
    kernels: str = "default"
    glue: str = ""

    @property
    def spec(self) -> Backend:
        return BACKENDS[self.backend]

    @property
    def kernel_set(self) -> Kernels:
        return self.spec.kernels[self.kernels]

    def lean(self, device: torch.device) -> bool:
        """Whether renders on ``device`` take the lean glue (never on the CPU, where nothing waits)."""
        import torch

        return self.glue == "lean" and torch.device(device).type != "cpu"

    def describe(self, sort: str = "global") -> str:
        """What a result records: e.g. ``cuda (kernels v2, glue lean)``, ``cpu``; with a per-pixel
        order the set has no kernel for, where it is composited instead."""
        axes = self.spec.axes()
        parts = [f"{axis} {getattr(self, axis)}" for axis in AXES if axis in axes]
        if sort == "per_pixel" and self.kernel_set.pixel is None:
            parts.append("per-pixel order on host copies (cpu, else reference)")
        return self.backend + (f" ({', '.join(parts)})" if parts else "")


def variant(choice: Renderer, backend: str) -> Variant:
    """``choice``'s variants of the resolved ``backend``: the asked one, else its environment
    variable's, else the backend's default (an unknown value in the environment is refused naming
    the variable)."""
    spec = BACKENDS[backend]
    picked = {}
    for axis, choices in spec.axes().items():
        value = getattr(choice, axis)
        if value is None and axis in spec.env:
            value = os.environ.get(spec.env[axis], "").strip() or None
            if value is not None and value not in choices:
                raise ValueError(f"{spec.env[axis]}={value!r} names no {backend} {axis} variant; expected one of "
                                 f"{', '.join(choices)} (unset: {choices[0]})")
        picked[axis] = value if value in choices else choices[0]
    return Variant(backend, picked.get("kernels", next(iter(spec.kernels))), picked.get("glue", ""))


def backend_device(backend: str) -> str | None:
    """The one kind of device a backend renders on (None: any, or ``auto``)."""
    spec = BACKENDS.get(str(backend))
    return None if spec is None else spec.device


def check_backend(backend: str, device: torch.device) -> None:
    """Refuse a renderer backend bound to another kind of device than the run's."""
    from smgs.device import DeviceError

    want = backend_device(backend)
    if want is not None and want != device.type:
        raise DeviceError(f"backend={backend} renders on the {want.upper()} only, but the run's device is "
                          f"{device}; use backend=auto (picks the {device.type} backend) or "
                          f"device={want if want == 'cpu' else 'cuda'}")
