"""The splatting renderer: EWA projection, then compositing by one of the backends (``backends``:
the backends and their variants in one registry)."""

from smgs.raster.api import backend_available, rasterize, rasterize_splats, render_variant, resolve_backend
from smgs.raster.backends import Renderer, Variant
from smgs.raster.types import MODES, RenderOutput, RenderStats, mode_flags

__all__ = ["rasterize", "rasterize_splats", "backend_available", "resolve_backend", "render_variant", "Renderer",
           "Variant", "RenderOutput", "RenderStats", "MODES", "mode_flags"]
