"""Keep freed image-sized buffers in the process heap (glibc) during training.

glibc serves blocks above ``M_MMAP_THRESHOLD`` (128 KiB until its dynamic adjustment kicks in)
with mmap and trims the heap top above ``M_TRIM_THRESHOLD``: every step then re-faults the pages
of its 100 KiB-1 MiB temporaries (a 128² image, its SSIM statistics, the renderer's outputs), which
measured ~0.7 ms per SSIM evaluation at 128², more than the blur itself. Raising both thresholds
lets freed blocks be reused. The setting is per process, changes no result, and is skipped where
the C library has no ``mallopt`` (non-glibc platforms).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import sys

M_TRIM_THRESHOLD = -1
M_MMAP_THRESHOLD = -3

MMAP_THRESHOLD_BYTES = 64 << 20
"""Blocks up to 64 MiB come from the heap (larger ones, e.g. whole datasets, are still mmapped)."""

TRIM_THRESHOLD_BYTES = 256 << 20
"""Up to 256 MiB of free heap top is kept instead of being returned to the OS."""


def keep_freed_buffers() -> bool:
    """Set the glibc malloc thresholds above; True if applied. Idempotent."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    ok = mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES) == 1
    return mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES) == 1 and ok
