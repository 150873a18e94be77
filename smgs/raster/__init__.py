"""The splatting renderer: EWA projection, then compositing by one of the backends."""

from smgs.raster.api import backend_available, rasterize, rasterize_splats, resolve_backend
from smgs.raster.types import MODES, RenderOutput, RenderStats, mode_flags

__all__ = ["rasterize", "rasterize_splats", "backend_available", "resolve_backend", "RenderOutput",
           "RenderStats", "MODES", "mode_flags"]
