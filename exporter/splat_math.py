"""Per-Gaussian splatting math of the numerics contract (ARCHITECTURE.md), in torch.

Each function here has a GLSL twin of the same name in the OpenGL runtime's shaders, so the two can be read side
by side line by line. Everything is differentiable (no in-place ops) and stays finite for extreme inputs: every
division is guarded by a contract epsilon or a clamp, and whatever still comes out non-finite is culled by
`keep_mask`. Shapes are noted as `# [N, 3]`; `...` means any leading batch shape.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from gaussiantalker.sdk.numerics import (
    ALPHA_MAX,
    ALPHA_MIN,
    COLOR_LIMIT,
    COV2D_HUGE_PX2,
    DET_MIN_RELATIVE,
    EXTENT_SIGMAS,
    FINITE_LIMIT,
    FRAME_EPS,
    LOW_PASS_PX2,
    QUAT_EPS,
    SH_C0,
    SH_C1,
    SH_C2,
    SH_C3,
    sh_coeff_count,
)

__all__ = [
    "quat_to_rotmat",
    "cov3d_from_rotation_scale",
    "sh_basis",
    "sh_to_rgb",
    "project_mean",
    "covariance_2d",
    "cov2d_scale",
    "covariance_2d_determinant",
    "cov2d_determinant",
    "conic_from_cov2d",
    "alpha_shape",
    "extent_radius",
    "extent_power_bound",
    "splat_color",
    "splat_alpha",
    "splat_alpha_parts",
    "keep_mask",
]


def _guarded_norm(v: Tensor, eps: float) -> Tensor:
    """max(|v|, eps) over the last axis, keepdim; written as sqrt(max(|v|^2, eps^2)) so the gradient at 0 is 0."""
    return torch.sqrt(torch.clamp_min((v * v).sum(dim=-1, keepdim=True), eps * eps))


def _safe_sqrt(x: Tensor) -> Tensor:
    """sqrt(max(x, 0)) whose gradient is 0 (not inf/NaN) where x <= 0."""
    positive = x > 0
    return torch.where(positive, torch.sqrt(torch.where(positive, x, torch.ones_like(x))), torch.zeros_like(x))


def _safe_divisor(x: Tensor) -> Tensor:
    """x where x > 0, else 1: a divisor for values that `keep_mask` culls anyway (z <= 0, det <= 0)."""
    return torch.where(x > 0, x, torch.ones_like(x))


def quat_to_rotmat(q: Tensor) -> Tensor:
    """Rotation matrix of a (w, x, y, z) quaternion divided by max(|q|, QUAT_EPS); a zero quaternion gives I."""
    q = q / _guarded_norm(q, QUAT_EPS)  # [..., 4]
    w, x, y, z = q.unbind(-1)
    rows = (
        (1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)),
        (2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)),
        (2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)),
    )
    return torch.stack([torch.stack(row, dim=-1) for row in rows], dim=-2)  # [..., 3, 3]


def cov3d_from_rotation_scale(rotation: Tensor, scale: Tensor) -> Tensor:
    """World covariance R diag(s^2) R^T, packed (xx, xy, xz, yy, yz, zz) like the GL buffers."""
    m = rotation * scale.unsqueeze(-2)  # [..., 3, 3] = R diag(s)
    cov = m @ m.transpose(-1, -2)  # [..., 3, 3]
    return torch.stack(
        [cov[..., 0, 0], cov[..., 0, 1], cov[..., 0, 2], cov[..., 1, 1], cov[..., 1, 2], cov[..., 2, 2]], dim=-1
    )  # [..., 6]


def sh_basis(dirs: Tensor, degree: int) -> Tensor:
    """Real SH basis values (3DGS computeColorFromSH order and signs) along dirs [..., 3] -> [..., (degree+1)^2]."""
    d = dirs / _guarded_norm(dirs, FRAME_EPS)  # [..., 3] camera centre -> Gaussian centre, unit
    x, y, z = d.unbind(-1)  # each [...]
    basis = [torch.full_like(x, SH_C0)]
    if degree > 0:
        basis += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree > 1:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        basis += [SH_C2[0] * xy, SH_C2[1] * yz, SH_C2[2] * (2.0 * zz - xx - yy), SH_C2[3] * xz,
                  SH_C2[4] * (xx - yy)]
    if degree > 2:
        basis += [
            SH_C3[0] * y * (3.0 * xx - yy),
            SH_C3[1] * xy * z,
            SH_C3[2] * y * (4.0 * zz - xx - yy),
            SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
            SH_C3[4] * x * (4.0 * zz - xx - yy),
            SH_C3[5] * z * (xx - yy),
            SH_C3[6] * x * (xx - 3.0 * yy),
        ]
    return torch.stack(basis, dim=-1)  # [..., K]


def sh_to_rgb(sh: Tensor, dirs: Tensor, degree: int, dc: Tensor | None = None) -> Tensor:
    """View-dependent colour: sum_k basis_k(dir) * sh_k, + 0.5, clamped at 0 (no upper clamp). sh [..., K, 3].

    `dc` [..., 3], when given, replaces sh[..., 0, :] (the per-frame kappa0' = kappa0 + BS(gamma; W_color)) without
    building a new [..., K, 3] tensor every frame.
    """
    count = sh_coeff_count(degree)
    if sh.shape[-2] < count:
        raise ValueError(f"sh_to_rgb: degree {degree} needs {count} coefficients, got {sh.shape[-2]}")
    basis = sh_basis(dirs, degree)  # [..., K]
    if dc is None:
        dc = sh[..., 0, :]
    result = basis[..., :1] * dc  # [..., 3]
    if count > 1:
        # One [..., K-1, 3] product and sum instead of K-1 broadcast products: ~6x faster in onnxruntime.
        result = result + (basis[..., 1:].unsqueeze(-1) * sh[..., 1:count, :]).sum(dim=-2)
    return torch.clamp_min(result + 0.5, 0.0)


def project_mean(
    means: Tensor, R: Tensor, t: Tensor, fx: float, fy: float, cx: float, cy: float
) -> tuple[Tensor, Tensor]:
    """World means -> (pixel xy with u = fx X/Z + cx, v = fy Y/Z + cy; camera-space points p = R X + t)."""
    points = (means.unsqueeze(-2) * R).sum(dim=-1) + t  # [N, 3], same summation order as GLSL mat3 * vec3
    x, y, z = points.unbind(-1)  # each [N]
    z_div = _safe_divisor(z)  # z <= 0 is behind the near plane: culled, only kept finite here
    xy = torch.stack([fx * x / z_div + cx, fy * y / z_div + cy], dim=-1)  # [N, 2]
    return xy, points


def _clamped_ratios(points_cam: Tensor, limits: Sequence[float]) -> tuple[Tensor, Tensor, Tensor]:
    """(z as a divisor, x/z and y/z clamped to the widened field of view `limits`), each [N]."""
    x_min, x_max, y_min, y_max = (float(v) for v in limits)
    x, y, z = points_cam.unbind(-1)  # each [N]
    z_div = _safe_divisor(z)
    return z_div, torch.clamp(x / z_div, x_min, x_max), torch.clamp(y / z_div, y_min, y_max)


def _sigma_matrix(cov3d: Tensor) -> Tensor:
    """Packed (xx, xy, xz, yy, yz, zz) [N, 6] -> symmetric [N, 3, 3]."""
    s_xx, s_xy, s_xz, s_yy, s_yz, s_zz = cov3d.unbind(-1)
    return torch.stack(
        [
            torch.stack([s_xx, s_xy, s_xz], dim=-1),
            torch.stack([s_xy, s_yy, s_yz], dim=-1),
            torch.stack([s_xz, s_yz, s_zz], dim=-1),
        ],
        dim=-2,
    )  # [N, 3, 3]


def covariance_2d(
    points_cam: Tensor, cov3d: Tensor, R: Tensor, fx: float, fy: float, limits: Sequence[float]
) -> Tensor:
    """Screen covariance J W Sigma W^T J^T (x/z, y/z clamped to `limits` first) + LOW_PASS_PX2 on the diagonal."""
    z_div, xz, yz = _clamped_ratios(points_cam, limits)  # each [N]
    # 3DGS forms tx = clamp(x/z) z and uses -fx tx / z^2; -fx clamp(x/z) / z is the same value in fewer roundings.
    zero = torch.zeros_like(z_div)
    j = torch.stack(
        [
            torch.stack([fx / z_div, zero, -fx * xz / z_div], dim=-1),
            torch.stack([zero, fy / z_div, -fy * yz / z_div], dim=-1),
        ],
        dim=-2,
    )  # [N, 2, 3] projection Jacobian
    m = j @ R  # [N, 2, 3] = J W
    cov = m @ _sigma_matrix(cov3d) @ m.transpose(-1, -2)  # [N, 2, 2]
    return torch.stack(
        [cov[..., 0, 0] + LOW_PASS_PX2, cov[..., 0, 1], cov[..., 1, 1] + LOW_PASS_PX2], dim=-1
    )  # [N, 3] = (a, b, c)


def cov2d_scale(cov2d: Tensor) -> Tensor:
    """s = max(|a|, |c|) of a packed 2D covariance. # [N]

    cov2d / s has entries in [-1, 1] for a PSD matrix, so products of them never overflow float32; s is data, not
    a constant, so no shader compiler can fold or reassociate the division away. s = 0 only where a = c = 0, which
    is culled (det NaN).
    """
    a, _, c = cov2d.unbind(-1)
    return torch.maximum(a.abs(), c.abs())


def _reliable(det: Tensor, products: Tensor) -> Tensor:
    """det where it exceeds DET_MIN_RELATIVE * products (the sum it is the difference of), else 0: noise is culled."""
    return torch.where(det > DET_MIN_RELATIVE * products, det, torch.zeros_like(det))


def covariance_2d_determinant(
    points_cam: Tensor, cov3d: Tensor, R: Tensor, fx: float, fy: float, limits: Sequence[float], cov2d: Tensor
) -> Tensor:
    """det of `covariance_2d` (its (a, b, c) [N, 3] passed in) / `cov2d_scale`^2, least-cancelling form. # [N]

    det = a c - b^2 cancels badly where J's rows are nearly parallel (grazing view angles: all of it is lost).
    Replacing J's second row by its part orthogonal to the first (closed form; a shear of determinant 1, so the
    determinant is unchanged) and adding the low-pass filter as det(A + l I) = det A + l (tr A + l) avoids that.
    Both are exact maths; the form whose second diagonal entry is smaller has the smaller products (a c, b^2) and
    so the smaller cancellation. A result lost in rounding noise (DET_MIN_RELATIVE) is returned as 0.
    """
    z_div, xz, yz = _clamped_ratios(points_cam, limits)  # each [N]
    g = 1.0 / (1.0 + xz * xz)  # [N]
    zero, one = torch.zeros_like(z_div), torch.ones_like(z_div)
    j0 = torch.stack([fx / z_div, zero, -fx * xz / z_div], dim=-1)  # [N, 3] row 0 of J
    j1 = (fy / z_div).unsqueeze(-1) * torch.stack([-(xz * g) * yz, one, -yz * g], dim=-1)  # [N, 3] row 1, sheared
    m = torch.stack([j0, j1], dim=-2) @ R  # [N, 2, 3]
    cov = m @ _sigma_matrix(cov3d) @ m.transpose(-1, -2)  # [N, 2, 2] = A in the sheared basis, no low-pass
    use_sheared = cov[..., 1, 1] + LOW_PASS_PX2 < cov2d[..., 2]  # [N]
    s = cov2d_scale(cov2d)  # [N]
    a, b, c = (cov2d / s.unsqueeze(-1)).unbind(-1)  # each [N], low-pass included
    s00, s01, s11 = cov[..., 0, 0] / s, cov[..., 0, 1] / s, cov[..., 1, 1] / s
    low_pass = LOW_PASS_PX2 / s  # [N]
    sheared = (s00 * s11 - s01 * s01) + low_pass * (a + c - low_pass)  # det A + l (tr A + l)
    sheared = _reliable(sheared, (s00 * s11).abs() + s01 * s01)
    plain = _reliable(a * c - b * b, (a * c).abs() + b * b)
    return torch.where(use_sheared, sheared, plain)


def cov2d_determinant(cov2d: Tensor) -> Tensor:
    """Plain det of a packed 2D covariance (a, b, c): a c - b^2. # [N] (culling uses `covariance_2d_determinant`)"""
    a, b, c = cov2d.unbind(-1)
    return a * c - b * b


def conic_from_cov2d(cov2d: Tensor, det: Tensor | None = None) -> Tensor:
    """Inverse of the packed 2D covariance, packed (A, B, C); det <= 0 (culled) divides by 1 instead.

    `det` is det(cov2d) / `cov2d_scale`^2 (as `covariance_2d_determinant` returns it); default: a c - b^2 of
    cov2d / cov2d_scale.
    """
    s = cov2d_scale(cov2d)  # [N]
    normalised = cov2d / s.unsqueeze(-1)  # [N, 3]
    a, b, c = normalised.unbind(-1)
    det = _safe_divisor(cov2d_determinant(normalised) if det is None else det) * s  # [N] det(cov2d) / s
    return torch.stack([c / det, -b / det, a / det], dim=-1)  # [N, 3]


def extent_radius(cov2d: Tensor) -> Tensor:
    """Exact screen radius EXTENT_SIGMAS * sqrt(lambda_max) of the packed 2D covariance (no ceil, no rounding).

    Where 0.5 (a + c) > COV2D_HUGE_PX2 it is evaluated on cov2d / `cov2d_scale` and scaled back, so mid^2 cannot
    overflow; below that the plain formula is used, bit for bit.
    """
    a, b, c = cov2d.unbind(-1)
    mid = 0.5 * (a + c)  # [N]
    plain = EXTENT_SIGMAS * _safe_sqrt(mid + _safe_sqrt(mid * mid - (a * c - b * b)))  # [N]
    s = cov2d_scale(cov2d)  # [N]
    a, b, c = (cov2d / s.unsqueeze(-1)).unbind(-1)
    mid_n = 0.5 * (a + c)
    huge = EXTENT_SIGMAS * _safe_sqrt(mid_n + _safe_sqrt(mid_n * mid_n - (a * c - b * b))) * _safe_sqrt(s)
    return torch.where(mid > COV2D_HUGE_PX2, huge, plain)  # [N]


def extent_power_bound(conic: Tensor, radius: Tensor) -> Tensor:
    """Largest |power| reachable with |dx|, |dy| <= radius: (|A| + 2|B| + |C|) r r. # [N]"""
    a, b, c = conic.abs().unbind(-1)
    return (a + 2.0 * b + c) * radius * radius


def splat_color(rgb: Tensor) -> Tensor:
    """Colour as composited: clamped to +-COLOR_LIMIT (far above any real colour) so sums stay finite. # [..., 3]"""
    return torch.clamp(rgb, -COLOR_LIMIT, COLOR_LIMIT)


def alpha_shape(cov2d: Tensor, det: Tensor | None = None) -> Tensor:
    """The conic in completed-square form (A, k, q) [N, 3]: d^T cov2d^-1 d = A (dx - k dy)^2 + q dy^2.

    A = c / det, k = b / c, q = 1 / c (the same quadratic form as the conic (A, B, C), since B / A = -k and
    C - B^2 / A = 1 / c). A sum of non-negative terms: on the ridge of a long, thin splat, A dx^2 + 2 B dx dy +
    C dy^2 cancels and float32 rounding can make it positive (3DGS then skips a pixel that should be fully drawn);
    this form cannot. `det` as for `conic_from_cov2d`.
    """
    _, b, c = cov2d.unbind(-1)
    c_div = torch.where(c == 0, torch.ones_like(c), c)  # c == 0 is not positive definite: culled (det <= 0)
    return torch.stack([conic_from_cov2d(cov2d, det)[..., 0], b / c_div, 1.0 / c_div], dim=-1)  # [N, 3]


def splat_alpha_parts(
    opacity: Tensor, a: Tensor, k: Tensor, q: Tensor, dx: Tensor, dy: Tensor, inside: Tensor | None = None
) -> Tensor:
    """`splat_alpha` on split, broadcastable `alpha_shape` components (A, k, q); `inside` (bool) also zeroes pixels
    outside the extent."""
    t = dx - k * dy
    power = -0.5 * (a * t * t + q * dy * dy)
    # exp of min(power, 0): a positive power is skipped below anyway, and this keeps exp (and its grad) finite.
    alpha = torch.clamp_max(opacity * torch.exp(torch.clamp_max(power, 0.0)), ALPHA_MAX)
    # 3DGS skips power > 0 (a non-positive-definite conic) and alpha < ALPHA_MIN; both contribute nothing.
    # Multiplying by the mask is exact and much cheaper than torch.where; alpha is finite here (keep_mask).
    keep = (power <= 0) & (alpha >= ALPHA_MIN)
    return alpha * (keep if inside is None else keep & inside)


def splat_alpha(opacity: Tensor, conic: Tensor, d: Tensor) -> Tensor:
    """min(ALPHA_MAX, opacity exp(-1/2 d^T conic d)), 0 where skipped (power > 0 or alpha < ALPHA_MIN).

    Takes the conic (A, B, C) and evaluates it in `alpha_shape` form (A, -B/A, C - B^2/A), as the renderers do.
    """
    a, b, c = conic.unbind(-1)  # each [...]
    a_div = torch.where(a == 0, torch.ones_like(a), a)
    dx, dy = d.unbind(-1)  # each [...]: pixel centre - projected centre
    return splat_alpha_parts(opacity, a, -b / a_div, c - b * b / a_div, dx, dy)  # [...]


def keep_mask(
    points_cam: Tensor,
    xy: Tensor,
    cov2d: Tensor,
    conic: Tensor,
    radius: Tensor,
    near: float,
    *extra: Tensor,
    det: Tensor | None = None,
    shape: Tensor | None = None,
) -> Tensor:
    """Which Gaussians are rasterized: camera z >= near (z == near kept), 2D det > 0, every value finite. # [N]

    `det` is the 2D determinant (`covariance_2d_determinant`; default a c - b^2). Screen-space values (xy, conic,
    `shape` (`alpha_shape`), radius and the `extent_power_bound`, which keeps per-pixel float32 math finite: no
    inf - inf = NaN) must stay below FINITE_LIMIT, as in the GL vertex shader; the others (camera-space points,
    cov2d, `extra`) be finite.
    """
    det = cov2d_determinant(cov2d) if det is None else det
    keep = (points_cam[..., 2] >= near) & (det > 0)
    screen = (xy, conic, radius, extent_power_bound(conic, radius)) + (() if shape is None else (shape,))
    for value in screen:
        bounded = value.abs() < FINITE_LIMIT  # NaN fails too
        keep = keep & (bounded.flatten(1).all(dim=-1) if bounded.dim() > 1 else bounded)
    for value in (points_cam, cov2d, *extra):
        finite = torch.isfinite(value)
        keep = keep & (finite.flatten(1).all(dim=-1) if finite.dim() > 1 else finite)
    return keep  # [N] bool
