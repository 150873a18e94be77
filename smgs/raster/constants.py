"""Numeric conventions of the renderer, pinned in one place (3DGS 2023 / gsplat).

Every backend reads these values; the compiled kernels receive them as arguments or mirror them in
``csrc/splat_math.h`` (a test checks that the header agrees with this module).
"""

ALPHA_MAX = 0.99
"""Absorbance clamp a = min(0.99, o·kernel) (3DGS; gsplat <= 1.5.3 used 0.999)."""

ALPHA_MIN = 1.0 / 255.0
"""A splat whose absorbance at a pixel is below this is skipped there."""

T_MIN = 1e-4
"""A splat whose vanilla update would bring the transmittance below this is not composited, and
the pixel stops (3DGS ``test_T < 0.0001``). The default of the renderer's ``t_min`` option; 0 turns
the early stop off. In vanilla compositing the stop drops at most 1e-4 of a pixel; with softmax
competition the dropped splat could have won most of the pixel (two splats at the a = 0.99 clamp
already give T = 0.01·0.01, below 1e-4 in float32), see docs/table1."""

EPS2D = 0.3
"""Added to the diagonal of every projected 2D covariance (px², the 3DGS low-pass filter)."""

SIGMA_EXTENT = 3.0
"""A splat reaches a pixel only inside its 3σ ellipse."""

P_MIN = -0.5 * SIGMA_EXTENT**2
"""p = -½·Mahalanobis² must be >= this (-4.5) for the splat to reach the pixel."""

PIXEL_CENTER = 0.5
"""Pixel (col i, row j) has its centre at (i + 0.5, j + 0.5) (gsplat; the Inria kernel uses i, j)."""

NEAR_PLANE = 0.01
"""Gaussians whose camera-space depth is below this are culled (gsplat default)."""

TILE_SIZE = 16
"""Tile edge in pixels for binning in the compiled backends (tiling never changes an image)."""

DEFAULT_K_MAX = 128
"""Softmax competition applies to the first k_max splats that reach a pixel (paper, Sec. 3.3)."""

EXP_ARG_MIN = -80.0
"""Arguments to exp are clamped here: exp(-80) ~ 1.8e-35 is already far below every threshold, and
PyTorch's CPU exp is ~10x slower below -88 (denormals)."""

DECAY_ARG_MAX = 1e3
"""γ·|Δd| is capped here: s = exp(-1e3) is exactly 0 in float32 and float64, and the cap keeps
γ = inf (the GEF-only limit) free of inf·0 in the gradients."""
