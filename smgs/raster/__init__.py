"""The splatting renderer: EWA projection, then compositing by one of the backends (``backends``:
the backends and their variants in one registry)."""

from smgs.lazy import lazy_names

# on first use: the backends' table (smgs list renderers) reads without torch
__getattr__ = lazy_names("smgs.raster", {
    **dict.fromkeys(("backend_available", "rasterize", "rasterize_splats", "render_variant", "resolve_backend"), "api"),
    **dict.fromkeys(("Renderer", "Variant"), "backends"),
    **dict.fromkeys(("MODES", "RenderOutput", "RenderStats", "mode_flags"), "types")})

__all__ = ["rasterize", "rasterize_splats", "backend_available", "resolve_backend", "render_variant", "Renderer",
           "Variant", "RenderOutput", "RenderStats", "MODES", "mode_flags"]
