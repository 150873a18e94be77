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
the pixel stops (3DGS ``test_T < 0.0001``): in every mode for vanilla steps, and so in softmax
modes only past the first k_max splats of the pixel, never inside the softmax head. The stop is
sound where a later splat can add at most T to the pixel; under softmax competition a later splat
can take the pixel from those before it (Algorithm 1 of the paper has no stop), and with the stop
saturated Softmax-GS splats could not compete at all (Table 1 lost up to 10 dB, docs/table1). The
default of the renderer's ``t_min`` option; 0 turns the stop off. Tested with ``T_STOP_SLACK``."""

T_STOP_SLACK = 1e-5
"""The early stop fires where T·(1 − a) < t_min·(1 − 1e-5), not at t_min itself. Two splats at the
a = 0.99 clamp bring T to exactly 1e-4, which is not below 1e-4, but float32 rounds 1 − 0.99 down
by 9.5e-7 relative (0.99 is not representable and 1/(1 − a) amplifies it), so T = 9.99998e-5 and
the 3DGS test (``test_T < 0.0001`` in float32) drops the second splat, where float64 keeps it.
In vanilla compositing that loses 1e-4 of a pixel; with softmax competition the dropped splat could
have won the pixel, and saturated Softmax-GS splats could never compete (Table 1 lost 10 dB to it,
docs/table1). A relative slack of 1e-5 covers the rounding of a few clamped factors (each at most
~6e-6 relative) and makes float32 and float64 agree at the clamp; a third saturated splat
(T = 1e-6) is still dropped."""

TINY = 1.1754943508222875e-38
"""The smallest normal float32. In a softmax step, where ã_cur's denominator â_cur + â_past·T_orig
falls below it (T_orig and â_cur both out of the float32 range), ã_cur := 0: ã_past ≈ 1 already
closes the pixel (0/0 otherwise, and rcp14 of a denormal is inf). Every backend and dtype uses it."""

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

MAX_SH_DEGREE = 3
"""The highest spherical-harmonics degree the renderer evaluates (16 coefficients per channel)."""

DEFAULT_K_MAX = 128
"""Softmax competition applies to the first k_max splats that reach a pixel (paper, Sec. 3.3)."""

DEFAULT_K_MAX_SCOPE = "pixel"
"""What "the first k_max" counts (docs/kmax-scope.md): ``pixel``, each pixel's first k_max composited
splats; ``patch``, the first k_max entries of its tile's depth-sorted list, the same for every pixel
of a tile (the paper's "closest K Gaussians for each image patch", Sec. 3)."""

EXP_ARG_MIN = -80.0
"""Arguments to exp are clamped here: exp(-80) ~ 1.8e-35 is already far below every threshold, and
PyTorch's CPU exp is ~10x slower below -88 (denormals)."""

DECAY_ARG_MAX = 1e3
"""γ·|Δd| is capped here: s = exp(-1e3) is exactly 0 in float32 and float64, and the cap keeps
γ = inf (the GEF-only limit) free of inf·0 in the gradients."""

SORT_WINDOW = 16
"""sort="per_pixel" on the compiled CPU backend: each pixel re-sorts its splats in a window of this
many (StopThePop's bounded re-sorting; the reference sorts exactly). tests/test_raster_sort.py
measures the difference to the exact order on crowded scenes."""

LEADER_ALPHA = 0.3
"""The leading-splat map (``leaders=True``): each pixel's first two composited splats whose own
absorbance a is at least this. Swapping two such splats changes the colour by a₁a₂(c₁ − c₂), at
least 9 % of their colour difference: a visible pop (smgs.metrics.consistency.score)."""
