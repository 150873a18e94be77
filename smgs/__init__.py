"""smgs: a benchmark and evaluation harness for Gaussian splatting (Softmax-GS and baselines)."""

import os

# torch's CPU thread pool (OpenMP) spins at its barriers by default; on a loaded 2-core machine a
# spinning waiter holds the core its descheduled partner needs: 100 training steps of `3dgs` on the
# procedural scene took 16.2 s with 2 threads against 3.9 s passive and 2.6 s on one thread (AMD
# EPYC, load 5-6), and passive was not slower on a quiet host (0.69 vs 0.82 s). OpenMP reads this
# when torch loads, so it only takes effect where smgs is imported before torch (every smgs entry
# point is); a value the user set is kept.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from smgs.lazy import lazy_names
from smgs.version import __version__

# The renderer's names load on first use, so that `import smgs.x` for a light module (the command
# line's `--help` and `smgs list`) does not import torch.
__getattr__ = lazy_names("smgs", {"Camera": "camera", "rasterize": "raster", "rasterize_splats": "raster",
                                  "RenderOutput": "raster", "MODES": "raster"})
__all__ = ["Camera", "rasterize", "rasterize_splats", "RenderOutput", "MODES", "__version__", "results", "curves"]


def results(*runs_dirs, per_view: bool = False):
    """Every cell below the runs directories as a pandas DataFrame, one row per cell (failed and
    skipped ones with their reason; ``per_view=True``: one row per cell and test view). Columns and
    dtypes: docs/reports.md ("Results as data"), ``smgs.cells.table.CELL_COLUMNS``."""
    from smgs.cells.table import results as table   # pandas loads here, not at ``import smgs``

    return table(*runs_dirs, per_view=per_view)


def curves(*runs_dirs):
    """The error-against-time curves of every cell below the runs directories as a long pandas
    DataFrame: one row per evaluation during training (step, train seconds, PSNR, #Gaussians)."""
    from smgs.cells.table import curves as table

    return table(*runs_dirs)
