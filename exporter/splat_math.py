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
    EXTENT_SIGMAS,
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
    "cov2d_determinant",
    "conic_from_cov2d",
    "extent_radius",
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


def covariance_2d(
    points_cam: Tensor, cov3d: Tensor, R: Tensor, fx: float, fy: float, limits: Sequence[float]
) -> Tensor:
    """Screen covariance J W Sigma W^T J^T (x/z, y/z clamped to `limits` first) + LOW_PASS_PX2 on the diagonal."""
    x_min, x_max, y_min, y_max = (float(v) for v in limits)
    x, y, z = points_cam.unbind(-1)  # each [N]
    z_div = _safe_divisor(z)
    # 3DGS forms tx = clamp(x/z) z and uses -fx tx / z^2; -fx clamp(x/z) / z is the same value in fewer roundings.
    xz = torch.clamp(x / z_div, x_min, x_max)  # [N]
    yz = torch.clamp(y / z_div, y_min, y_max)  # [N]
    zero = torch.zeros_like(z)
    j = torch.stack(
        [
            torch.stack([fx / z_div, zero, -fx * xz / z_div], dim=-1),
            torch.stack([zero, fy / z_div, -fy * yz / z_div], dim=-1),
        ],
        dim=-2,
    )  # [N, 2, 3] projection Jacobian
    s_xx, s_xy, s_xz, s_yy, s_yz, s_zz = cov3d.unbind(-1)
    sigma = torch.stack(
        [
            torch.stack([s_xx, s_xy, s_xz], dim=-1),
            torch.stack([s_xy, s_yy, s_yz], dim=-1),
            torch.stack([s_xz, s_yz, s_zz], dim=-1),
        ],
        dim=-2,
    )  # [N, 3, 3]
    m = j @ R  # [N, 2, 3] = J W
    cov = m @ sigma @ m.transpose(-1, -2)  # [N, 2, 2]
    return torch.stack(
        [cov[..., 0, 0] + LOW_PASS_PX2, cov[..., 0, 1], cov[..., 1, 1] + LOW_PASS_PX2], dim=-1
    )  # [N, 3] = (a, b, c)


def cov2d_determinant(cov2d: Tensor) -> Tensor:
    """det of a packed 2D covariance (a, b, c): a c - b^2. # [N]"""
    a, b, c = cov2d.unbind(-1)
    return a * c - b * b


def conic_from_cov2d(cov2d: Tensor) -> Tensor:
    """Inverse of the packed 2D covariance, packed (A, B, C); det <= 0 (culled) divides by 1 instead."""
    a, b, c = cov2d.unbind(-1)
    det = _safe_divisor(cov2d_determinant(cov2d))  # [N]
    return torch.stack([c / det, -b / det, a / det], dim=-1)  # [N, 3]


def extent_radius(cov2d: Tensor) -> Tensor:
    """Exact screen radius EXTENT_SIGMAS * sqrt(lambda_max) of the packed 2D covariance (no ceil, no rounding)."""
    a, _, c = cov2d.unbind(-1)
    mid = 0.5 * (a + c)  # [N]
    lambda_max = mid + _safe_sqrt(mid * mid - cov2d_determinant(cov2d))  # [N]
    return EXTENT_SIGMAS * _safe_sqrt(lambda_max)  # [N]


def splat_alpha_parts(
    opacity: Tensor, a: Tensor, b: Tensor, c: Tensor, dx: Tensor, dy: Tensor, inside: Tensor | None = None
) -> Tensor:
    """`splat_alpha` on split, broadcastable components; `inside` (bool) also zeroes pixels outside the extent."""
    power = -0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy
    # exp of min(power, 0): a positive power is skipped below anyway, and this keeps exp (and its grad) finite.
    alpha = torch.clamp_max(opacity * torch.exp(torch.clamp_max(power, 0.0)), ALPHA_MAX)
    # 3DGS skips power > 0 (a non-positive-definite conic) and alpha < ALPHA_MIN; both contribute nothing.
    # Multiplying by the mask is exact and much cheaper than torch.where; alpha is finite here (keep_mask).
    keep = (power <= 0) & (alpha >= ALPHA_MIN)
    return alpha * (keep if inside is None else keep & inside)


def splat_alpha(opacity: Tensor, conic: Tensor, d: Tensor) -> Tensor:
    """min(ALPHA_MAX, opacity exp(-1/2 d^T conic d)), 0 where skipped (power > 0 or alpha < ALPHA_MIN)."""
    a, b, c = conic.unbind(-1)  # each [...]
    dx, dy = d.unbind(-1)  # each [...]: pixel centre - projected centre
    return splat_alpha_parts(opacity, a, b, c, dx, dy)  # [...]


def keep_mask(
    points_cam: Tensor, xy: Tensor, cov2d: Tensor, conic: Tensor, radius: Tensor, near: float, *extra: Tensor
) -> Tensor:
    """Which Gaussians are rasterized: camera z >= near (z == near kept), 2D det > 0, every value finite. # [N]"""
    keep = (points_cam[..., 2] >= near) & (cov2d_determinant(cov2d) > 0)
    # Also the largest |power| reachable inside the extent box, so per-pixel float32 math cannot overflow
    # (inf - inf = NaN); only splats over ~1e18 px wide fail this on top of the plain finiteness checks.
    a, b, c = conic.abs().unbind(-1)
    power_bound = (a + 2.0 * b + c) * radius * radius  # [N]
    for value in (points_cam, xy, cov2d, conic, radius, power_bound, *extra):
        finite = torch.isfinite(value)
        keep = keep & (finite.flatten(1).all(dim=-1) if finite.dim() > 1 else finite)
    return keep  # [N] bool
