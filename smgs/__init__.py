"""smgs: a benchmark and evaluation harness for Gaussian splatting (Softmax-GS and baselines)."""

from smgs.camera import Camera
from smgs.raster import MODES, RenderOutput, rasterize, rasterize_splats

__version__ = "0.1.0"
__all__ = ["Camera", "rasterize", "rasterize_splats", "RenderOutput", "MODES", "__version__"]
