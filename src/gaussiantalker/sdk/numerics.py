"""Numerics contract constants shared by the torch reference and the GL runtime (docs/numerics.md).

Every renderer in the project reads these values from here; none hard-codes its own copy.
"""

# Pixel (x, y) covers [x, x+1) x [y, y+1); its centre, where Gaussians are evaluated, is at (x + 0.5, y + 0.5).
PIXEL_CENTER_OFFSET = 0.5

# Gaussians whose camera-space centre z is below the near plane are culled (z == near is kept).
DEFAULT_NEAR = 0.2

# Before forming the projection Jacobian, x/z (and y/z) is clamped to the field of view widened by this
# fraction of the half-extent on each side (3DGS uses 1.3x the half field of view).
FOV_CLAMP_MARGIN = 0.3

# Low-pass filter: added to the diagonal of every 2D covariance, in px^2.
LOW_PASS_PX2 = 0.3

# A splat touches pixels within EXTENT_SIGMAS * sqrt(lambda_max) of its centre (per axis, |dx|, |dy| <= r).
EXTENT_SIGMAS = 3.0

# alpha = min(ALPHA_MAX, opacity * exp(-0.5 d^T Sigma^-1 d)); contributions below ALPHA_MIN are skipped.
ALPHA_MAX = 0.99
ALPHA_MIN = 1.0 / 255.0

# Colours are clamped to +-COLOR_LIMIT just before compositing, so float32 sums stay finite (no inf - inf = NaN).
# Far above any real colour, so "no upper clamp before compositing" holds for every real input.
COLOR_LIMIT = 1e30

# A per-splat screen-space value (projected centre, extent radius, conic and its alpha_shape form, and the largest
# |power| reachable inside the extent) whose magnitude reaches FINITE_LIMIT counts as non-finite: the Gaussian is
# culled. Only values no pixel of a 16384-px image could use come near it; it keeps per-pixel float32 math finite.
FINITE_LIMIT = 1e30

# A 2D determinant is the difference of two products (a c - b^2). Where it is below DET_MIN_RELATIVE times the
# rounding noise those products carry (their sum, or more where a, b, c are themselves cancelling sums:
# `rounding_products`, docs/numerics.md) it is float32 rounding noise (its sign included), so it counts as not
# positive: the Gaussian is culled on both sides alike. That takes a diagonal 2D covariance with
# lambda_max / lambda_min above ~2e6 (a sub-pixel-thin needle ~5000 px long, or a near-singular covariance from
# huge 3D scales); the noise is ~1e-7 of the products. Just above the cut the opacity is faded in
# (`reliability_fade`: 1 - exp(-ALPHA_MIN (rho - 1)), rho the determinant in units of the cut), so no alpha reaches
# ALPHA_MIN there: sides that round the determinant differently, one culling and another not, draw the same pixels.
DET_MIN_RELATIVE = 2.0**-20

# Where 0.5 (a + c) > COV2D_HUGE_PX2, the extent radius is evaluated on the 2D covariance divided by max(|a|, |c|),
# so a huge splat keeps a finite radius instead of mid^2 overflowing float32; below it the formula is unchanged.
COV2D_HUGE_PX2 = 1e18

# Front-to-back compositing stops before a Gaussian that would take transmittance below this.
TRANSMITTANCE_MIN = 1e-4

# Quaternion (w, x, y, z) is divided by max(|q|, QUAT_EPS): a zero quaternion gives the identity rotation.
QUAT_EPS = 1e-12

# Floor of every normalisation guard: the triangle frame's guards are relative to each triangle's rest size
# (docs/numerics.md, "Triangle frame") and never below this; the SH view direction divides by max(|d|, FRAME_EPS).
FRAME_EPS = 1e-12

# Real spherical-harmonics constants (degree 0..3), as in the 3DGS rasterizer.
SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)
MAX_SH_DEGREE = 3


def sh_coeff_count(degree: int) -> int:
    """Number of SH coefficients per colour channel for a given degree: (degree + 1)^2."""
    if not 0 <= degree <= MAX_SH_DEGREE:
        raise ValueError(f"SH degree must be in 0..{MAX_SH_DEGREE}, got {degree}")
    return (degree + 1) ** 2
