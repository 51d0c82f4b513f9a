"""Per-Gaussian splatting maths of the numerics contract (docs/numerics.md), in torch.

This is the reference that the OpenGL runtime's shaders (shaders/splat.vert, shaders/splat.frag) mirror. Every
GLSL function that implements a contract step has a function here with the same name, the same arguments in the
same order and the same meaning; its docstring names it ("GLSL twin: `name` in shaders/file"). A public function
without a GLSL twin says why ("No GLSL twin: ..."). tests/test_mirror_names.py parses both sides and checks this.
The GLSL functions that only decide where to rasterise (`pixel_box`, `cull`) are listed in
`gaussiantalker.runtime.splat.gl.NON_CONTRACT_GLSL_FUNCTIONS` and have no twin here.

How a torch twin maps its GLSL function:
* Batched: GLSL handles one Gaussian (or one pixel); the twin takes the same arguments with a leading batch axis
  ([N], or any `...` where noted), and a GLSL scalar becomes a tensor [N]. Argument names are the GLSL ones.
* Uniforms become explicit trailing arguments: whatever the GLSL function reads from a uniform, itself or through
  the functions it calls, follows its GLSL arguments, in the order R, t, fx, fy, cx, cy, limits (`u_R` -> R [3, 3],
  `u_t` -> t [3], `u_intrinsics` -> fx, fy, cx, cy as floats, `u_fov_limits` -> limits, the four floats of
  `Camera.fov_clamp_limits()`).
* The packed world covariance (xx, xy, xz, yy, yz, zz) is one argument `cov3d` [N, 6] here and two vec3 in GLSL,
  which has no 6-vector: `cov_a` = (xx, xy, xz), `cov_b` = (yy, yz, zz).
* Where GLSL divides by a value whose Gaussian is culled anyway (camera z <= 0, 2D determinant <= 0), torch
  divides by 1 instead (`_safe_divisor`), so culled Gaussians stay finite and out of autograd; kept Gaussians get
  the same values.
* Contract constants come from sdk/numerics.py on both sides (GLSL gets them as #defines).

Everything is differentiable (no in-place ops) and stays finite for extreme inputs: every division is guarded by a
contract epsilon or a clamp, and whatever still comes out non-finite is culled by `keep_mask`. Shapes are noted as
`# [N, 3]`; `...` means any leading batch shape.
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
    # No GLSL twin: the deformation graph (runs in the runtime as the ONNX export of this same code).
    "quat_to_rotmat",
    "cov3d_from_rotation_scale",
    "sh_basis",
    "sh_to_rgb",
    # GLSL twins in shaders/splat.vert, in the order the vertex shader's main uses them.
    "world_to_camera",
    "camera_to_pixel",
    "clamped_ratios",
    "sigma_matrix",
    "covariance_2d",
    "cov2d_scale",
    "reliable",
    "rounding_products",
    "determinant_and_noise",
    "covariance_2d_determinant",
    "reliability_fade",
    "conic_from_cov2d",
    "alpha_shape",
    "radius_of",
    "extent_radius",
    "extent_power_bound",
    "screen_bounded",
    # GLSL twins in shaders/splat.frag.
    "splat_color",
    "splat_alpha",
    # No GLSL twin: torch-only vectorised forms used by the reference rasterizer.
    "alpha_from_components",
    "keep_mask",
]


def _guarded_norm(v: Tensor, eps: float, dim: int = -1) -> Tensor:
    """max(|v|, eps) over axis `dim`, keepdim; written as sqrt(max(|v|^2, eps^2)) so the gradient at 0 is 0."""
    return torch.sqrt(torch.clamp_min((v * v).sum(dim=dim, keepdim=True), eps * eps))


def _safe_sqrt(x: Tensor) -> Tensor:
    """sqrt(max(x, 0)) whose gradient is 0 (not inf/NaN) where x <= 0."""
    positive = x > 0
    return torch.where(positive, torch.sqrt(torch.where(positive, x, torch.ones_like(x))), torch.zeros_like(x))


def _safe_divisor(x: Tensor) -> Tensor:
    """x where x > 0, else 1: a divisor for values that `keep_mask` culls anyway (z <= 0, det <= 0)."""
    return torch.where(x > 0, x, torch.ones_like(x))


def quat_to_rotmat(q: Tensor, dim: int = -1) -> Tensor:
    """Rotation matrix of a (w, x, y, z) quaternion divided by max(|q|, QUAT_EPS); a zero quaternion gives I.

    q [..., 4] -> [..., 3, 3]. With `dim` >= 0 the components lie on that axis instead and so do the matrix's
    (row, column) axes: [B, 4, N] with dim=1 -> [B, 3, 3, N] (the deformation graph's component-major layout).

    No GLSL twin: part of the deformation graph, which the runtime runs as the ONNX export of this code.
    """
    q = q / _guarded_norm(q, QUAT_EPS, dim)  # [..., 4]
    w, x, y, z = q.unbind(dim)
    rows = (
        (1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)),
        (2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)),
        (2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)),
    )
    if dim < 0:
        return torch.stack([torch.stack(row, dim=-1) for row in rows], dim=-2)  # [..., 3, 3]
    return torch.stack([torch.stack(row, dim=dim) for row in rows], dim=dim)  # [..., 3, 3, ...] at `dim`


def cov3d_from_rotation_scale(rotation: Tensor, scale: Tensor) -> Tensor:
    """World covariance R diag(s^2) R^T, packed (xx, xy, xz, yy, yz, zz) like the GL buffers.

    No GLSL twin: part of the deformation graph, which the runtime runs as the ONNX export of this code.
    """
    m = rotation * scale.unsqueeze(-2)  # [..., 3, 3] = R diag(s)
    cov = m @ m.transpose(-1, -2)  # [..., 3, 3]
    return torch.stack(
        [cov[..., 0, 0], cov[..., 0, 1], cov[..., 0, 2], cov[..., 1, 1], cov[..., 1, 2], cov[..., 2, 2]], dim=-1
    )  # [..., 6]


def sh_basis(dirs: Tensor, degree: int, dim: int = -1, skip_dc: bool = False) -> Tensor:
    """Real SH basis values (3DGS computeColorFromSH order and signs) along dirs [..., 3] -> [..., (degree+1)^2].

    `dim` is the axis holding the direction's components and, in the result, the basis index ([B, 3, N] with
    dim=1 -> [B, K, N]). `skip_dc` leaves out the constant degree-0 value SH_C0 ([..., K - 1]).

    No GLSL twin: part of the deformation graph, which the runtime runs as the ONNX export of this code.
    """
    d = dirs / _guarded_norm(dirs, FRAME_EPS, dim)  # [..., 3] camera centre -> Gaussian centre, unit
    x, y, z = d.unbind(dim)  # each [...]
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
    return torch.stack(basis[1:] if skip_dc else basis, dim=dim)  # [..., K]


def sh_to_rgb(sh: Tensor, dirs: Tensor, degree: int, dc: Tensor | None = None) -> Tensor:
    """View-dependent colour: sum_k basis_k(dir) * sh_k, + 0.5, clamped at 0 (no upper clamp). sh [..., K, 3].

    `dc` [..., 3], when given, replaces sh[..., 0, :] (the per-frame kappa0' = kappa0 + BS(gamma; W_color)) without
    building a new [..., K, 3] tensor every frame.

    No GLSL twin: part of the deformation graph, which the runtime runs as the ONNX export of this code.
    """
    count = sh_coeff_count(degree)
    if sh.shape[-2] < count:
        raise ValueError(f"sh_to_rgb: degree {degree} needs {count} coefficients, got {sh.shape[-2]}")
    basis = sh_basis(dirs, degree)  # [..., K]
    if dc is None:
        dc = sh[..., 0, :]
    result = basis[..., :1] * dc  # [..., 3]
    if count > 1:
        # One [..., K-1, 3] product and sum instead of K-1 broadcast products: faster in onnxruntime
        # (docs/deformation.md, "Layout").
        result = result + (basis[..., 1:].unsqueeze(-1) * sh[..., 1:count, :]).sum(dim=-2)
    return torch.clamp_min(result + 0.5, 0.0)


def world_to_camera(mean: Tensor, R: Tensor, t: Tensor) -> Tensor:
    """Camera-space points p = R mean + t of world positions mean [N, 3]. # [N, 3]

    GLSL twin: `world_to_camera` in shaders/splat.vert.
    """
    return (mean.unsqueeze(-2) * R).sum(dim=-1) + t  # [N, 3], same summation order as GLSL mat3 * vec3


def camera_to_pixel(p_cam: Tensor, fx: float, fy: float, cx: float, cy: float) -> Tensor:
    """Projected centre in continuous pixel coordinates: u = fx x / z + cx, v = fy y / z + cy. # [N, 2]

    GLSL twin: `camera_to_pixel` in shaders/splat.vert.
    """
    x, y, z = p_cam.unbind(-1)  # each [N]
    z_div = _safe_divisor(z)  # z <= 0 is behind the near plane: culled, only kept finite here
    return torch.stack([fx * x / z_div + cx, fy * y / z_div + cy], dim=-1)  # [N, 2]


def clamped_ratios(p_cam: Tensor, limits: Sequence[float]) -> Tensor:
    """(x / z, y / z) of camera-space points, each clamped to the widened field of view `limits`. # [N, 2]

    GLSL twin: `clamped_ratios` in shaders/splat.vert.
    """
    x_min, x_max, y_min, y_max = (float(v) for v in limits)
    x, y, z = p_cam.unbind(-1)  # each [N]
    z_div = _safe_divisor(z)
    return torch.stack([torch.clamp(x / z_div, x_min, x_max), torch.clamp(y / z_div, y_min, y_max)], dim=-1)


def sigma_matrix(cov3d: Tensor) -> Tensor:
    """Packed world covariance (xx, xy, xz, yy, yz, zz) [N, 6] -> symmetric [N, 3, 3].

    GLSL twin: `sigma_matrix` in shaders/splat.vert.
    """
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
    p_cam: Tensor, cov3d: Tensor, R: Tensor, fx: float, fy: float, limits: Sequence[float]
) -> Tensor:
    """Screen covariance J W Sigma W^T J^T (x/z, y/z clamped to `limits` first) + LOW_PASS_PX2 on the diagonal.

    Packed (a, b, c) = [[a, b], [b, c]]. # [N, 3]

    GLSL twin: `covariance_2d` in shaders/splat.vert.
    """
    z_div = _safe_divisor(p_cam[..., 2])  # [N]
    xz, yz = clamped_ratios(p_cam, limits).unbind(-1)  # each [N]
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
    cov = m @ sigma_matrix(cov3d) @ m.transpose(-1, -2)  # [N, 2, 2]
    return torch.stack(
        [cov[..., 0, 0] + LOW_PASS_PX2, cov[..., 0, 1], cov[..., 1, 1] + LOW_PASS_PX2], dim=-1
    )  # [N, 3] = (a, b, c)


def cov2d_scale(cov2d: Tensor) -> Tensor:
    """s = max(|a|, |c|) of a packed 2D covariance. # [N]

    cov2d / s has entries in [-1, 1] for a PSD matrix, so products of them never overflow float32; s is data, not
    a constant, so no shader compiler can fold or reassociate the division away. s = 0 only where a = c = 0, which
    is culled (det NaN).

    GLSL twin: `cov2d_scale` in shaders/splat.vert.
    """
    a, _, c = cov2d.unbind(-1)
    return torch.maximum(a.abs(), c.abs())


def reliable(det: Tensor, products: Tensor) -> Tensor:
    """det where it exceeds DET_MIN_RELATIVE * products (`rounding_products`), else 0. # [N]

    A determinant lost in float32 rounding noise, its sign included, counts as not positive, so it is culled.

    GLSL twin: `reliable` in shaders/splat.vert.
    """
    return torch.where(det > DET_MIN_RELATIVE * products, det, torch.zeros_like(det))


def rounding_products(value: Tensor, magnitude: Tensor) -> Tensor:
    """What the rounding noise of x z - y^2 scales with, for packed (x, y, z) [N, 3] each computed as a sum whose
    terms' absolute values sum to `magnitude` [N, 3]: (x̄ |z| + |x| z̄) / 2 + |y| ȳ. # [N]

    Each entry's own float32 rounding is a few ulps of its magnitude, not of its value, which a cancelling sum
    (a slab seen edge-on) can leave far below it. Without cancellation (magnitude = |value|) this is |x z| + y^2,
    the two products the determinant is the difference of (docs/numerics.md, "2D determinant conditioning").

    GLSL twin: `rounding_products` in shaders/splat.vert.
    """
    x, y, z = value.unbind(-1)
    x_mag, y_mag, z_mag = magnitude.unbind(-1)
    return 0.5 * (x_mag * z.abs() + x.abs() * z_mag) + y.abs() * y_mag


def determinant_and_noise(
    p_cam: Tensor, cov3d: Tensor, cov2d: Tensor, R: Tensor, fx: float, fy: float, limits: Sequence[float]
) -> Tensor:
    """(det, noise) [N, 2]: det of `covariance_2d` (its (a, b, c) [N, 3] passed in) / `cov2d_scale`^2 in the
    least-cancelling form, and the `rounding_products` its float32 rounding noise scales with.

    det = a c - b^2 cancels badly where J's rows are nearly parallel (grazing view angles: all of it is lost).
    Replacing J's second row by its part orthogonal to the first (closed form; a shear of determinant 1, so the
    determinant is unchanged) and adding the low-pass filter as det(A + l I) = det A + l (tr A + l) avoids that.
    Both are exact maths; the form whose second diagonal entry is smaller has the smaller products (a c, b^2) and
    so the smaller cancellation. The noise is measured from the entries' magnitudes: the same quadratic forms over
    |J W| and |Sigma|. `covariance_2d_determinant` and `reliability_fade` both read it (docs/numerics.md, "2D
    determinant conditioning").

    GLSL twin: `determinant_and_noise` in shaders/splat.vert.
    """
    z_div = _safe_divisor(p_cam[..., 2])  # [N]
    xz, yz = clamped_ratios(p_cam, limits).unbind(-1)  # each [N]
    g = 1.0 / (1.0 + xz * xz)  # [N]
    zero, one = torch.zeros_like(z_div), torch.ones_like(z_div)
    j0 = torch.stack([fx / z_div, zero, -fx * xz / z_div], dim=-1)  # [N, 3] row 0 of J
    j1 = (fy / z_div).unsqueeze(-1) * torch.stack([-(xz * g) * yz, one, -yz * g], dim=-1)  # [N, 3] row 1, sheared
    m = torch.stack([j0, j1], dim=-2) @ R  # [N, 2, 3]
    sigma = sigma_matrix(cov3d)  # [N, 3, 3]
    cov = m @ sigma @ m.transpose(-1, -2)  # [N, 2, 2] = A in the sheared basis, no low-pass
    use_sheared = cov[..., 1, 1] + LOW_PASS_PX2 < cov2d[..., 2]  # [N]
    s = cov2d_scale(cov2d)  # [N]
    a, b, c = (cov2d / s.unsqueeze(-1)).unbind(-1)  # each [N], low-pass included
    s00, s01, s11 = cov[..., 0, 0] / s, cov[..., 0, 1] / s, cov[..., 1, 1] / s
    low_pass = LOW_PASS_PX2 / s  # [N]
    sheared = (s00 * s11 - s01 * s01) + low_pass * (a + c - low_pass)  # det A + l (tr A + l)
    # Magnitudes of both forms' entries: the quadratic forms over |rows| and |Sigma| (rows: J W's first row, its
    # sheared second row, its plain second row as `covariance_2d` forms it).
    j1_plain = torch.stack([zero, fy / z_div, -fy * yz / z_div], dim=-1)  # [N, 3]
    rows = (torch.stack([j0, j1, j1_plain], dim=-2) @ R).abs()  # [N, 3, 3]
    spread = rows @ sigma.abs()  # [N, 3, 3]: row i is |Sigma| |row i| (Sigma is symmetric)
    m0_mag = (rows[..., 0, :] * spread[..., 0, :]).sum(-1)  # [N]
    sheared_mag = torch.stack([m0_mag, (rows[..., 0, :] * spread[..., 1, :]).sum(-1),
                               (rows[..., 1, :] * spread[..., 1, :]).sum(-1)], dim=-1) / s.unsqueeze(-1)
    plain_mag = torch.stack([m0_mag + LOW_PASS_PX2, (rows[..., 0, :] * spread[..., 2, :]).sum(-1),
                             (rows[..., 2, :] * spread[..., 2, :]).sum(-1) + LOW_PASS_PX2], dim=-1) / s.unsqueeze(-1)
    sheared_noise = rounding_products(torch.stack([s00, s01, s11], dim=-1), sheared_mag)
    plain_noise = rounding_products(torch.stack([a, b, c], dim=-1), plain_mag)
    return torch.where(use_sheared.unsqueeze(-1), torch.stack([sheared, sheared_noise], dim=-1),
                       torch.stack([a * c - b * b, plain_noise], dim=-1))  # [N, 2]


def covariance_2d_determinant(
    p_cam: Tensor, cov3d: Tensor, cov2d: Tensor, R: Tensor, fx: float, fy: float, limits: Sequence[float]
) -> Tensor:
    """det of `covariance_2d` (its (a, b, c) [N, 3] passed in) / `cov2d_scale`^2, 0 where unreliable. # [N]

    `determinant_and_noise`'s det, returned as 0 where it is lost in rounding noise (`reliable`). This is the only
    2D determinant of the contract: culling, the conic and `alpha_shape` all use it.

    GLSL twin: `covariance_2d_determinant` in shaders/splat.vert.
    """
    det, noise = determinant_and_noise(p_cam, cov3d, cov2d, R, fx, fy, limits).unbind(-1)
    return reliable(det, noise)


def reliability_fade(
    p_cam: Tensor, cov3d: Tensor, cov2d: Tensor, R: Tensor, fx: float, fy: float, limits: Sequence[float]
) -> Tensor:
    """The factor in [0, 1] a Gaussian's opacity is multiplied by: 1 - exp(-ALPHA_MIN (rho - 1)), 0 for rho <= 1. # [N]

    rho = det / (DET_MIN_RELATIVE noise) of `determinant_and_noise`, so `reliable` culls rho <= 1. Sides that round
    the determinant differently disagree on rho by a few sixteenths. Just above the cut the factor grows by
    ALPHA_MIN per unit of rho, so no alpha there reaches ALPHA_MIN on any side (rho < 1 + 1 / opacity): the cut
    changes no pixel. Further up it saturates, so its change for a rounding difference stays within the
    conditioning bound, and from rho ~ 4400 on it is exactly 1 in float32: splats whose screen axes are less than
    ~20:1 apart (and whose entries do not cancel) are never faded (docs/numerics.md, "Reliability fade").

    GLSL twin: `reliability_fade` in shaders/splat.vert.
    """
    det, noise = determinant_and_noise(p_cam, cov3d, cov2d, R, fx, fy, limits).unbind(-1)
    threshold = DET_MIN_RELATIVE * noise  # [N]
    excess = (det - threshold) / _safe_divisor(threshold)  # [N] rho - 1 where threshold > 0
    fade = 1.0 - torch.exp(-ALPHA_MIN * torch.clamp_min(excess, 0.0))
    # threshold == 0 with det > 0 (the noise underflowed) is a fully reliable det, as det / 0 = inf would say.
    return torch.where(det > threshold, torch.where(threshold > 0, fade, torch.ones_like(fade)),
                       torch.zeros_like(fade))


def conic_from_cov2d(cov2d: Tensor, det: Tensor) -> Tensor:
    """Inverse of the packed 2D covariance, packed (A, B, C); det <= 0 (culled) divides by 1 instead. # [N, 3]

    `det` is det(cov2d) / `cov2d_scale`^2, as `covariance_2d_determinant` returns it.

    GLSL twin: `conic_from_cov2d` in shaders/splat.vert.
    """
    s = cov2d_scale(cov2d)  # [N]
    a, b, c = (cov2d / s.unsqueeze(-1)).unbind(-1)
    det = _safe_divisor(det) * s  # [N] det(cov2d) / s
    return torch.stack([c / det, -b / det, a / det], dim=-1)  # [N, 3]


def alpha_shape(cov2d: Tensor, det: Tensor) -> Tensor:
    """The conic in completed-square form (A, k, q) [N, 3]: d^T cov2d^-1 d = A (dx - k dy)^2 + q dy^2.

    A = c / det, k = b / c, q = 1 / c (the same quadratic form as the conic (A, B, C), since B / A = -k and
    C - B^2 / A = 1 / c). A sum of non-negative terms: on the ridge of a long, thin splat, A dx^2 + 2 B dx dy +
    C dy^2 cancels and float32 rounding can make it positive (3DGS then skips a pixel that should be fully drawn);
    this form cannot. `det` as for `conic_from_cov2d`.

    GLSL twin: `alpha_shape` in shaders/splat.vert.
    """
    _, b, c = cov2d.unbind(-1)
    c_div = torch.where(c == 0, torch.ones_like(c), c)  # c == 0 is not positive definite: culled (det <= 0)
    return torch.stack([conic_from_cov2d(cov2d, det)[..., 0], b / c_div, 1.0 / c_div], dim=-1)  # [N, 3]


def radius_of(cov2d: Tensor) -> Tensor:
    """EXTENT_SIGMAS * sqrt(lambda_max) of a packed symmetric 2x2 (a, b, c), negative roots taken as 0. # [N]

    GLSL twin: `radius_of` in shaders/splat.vert.
    """
    a, b, c = cov2d.unbind(-1)
    mid = 0.5 * (a + c)  # [N]
    return EXTENT_SIGMAS * _safe_sqrt(mid + _safe_sqrt(mid * mid - (a * c - b * b)))


def extent_radius(cov2d: Tensor) -> Tensor:
    """Exact screen radius EXTENT_SIGMAS * sqrt(lambda_max) of the packed 2D covariance (no ceil, no rounding).

    Where 0.5 (a + c) > COV2D_HUGE_PX2 it is `radius_of` cov2d / `cov2d_scale`, scaled back by sqrt(scale), so
    mid^2 cannot overflow; below that it is `radius_of` cov2d, bit for bit. # [N]

    GLSL twin: `extent_radius` in shaders/splat.vert.
    """
    a, _, c = cov2d.unbind(-1)
    s = cov2d_scale(cov2d)  # [N]
    huge = radius_of(cov2d / s.unsqueeze(-1)) * _safe_sqrt(s)
    return torch.where(0.5 * (a + c) > COV2D_HUGE_PX2, huge, radius_of(cov2d))  # [N]


def extent_power_bound(conic: Tensor, radius: Tensor) -> Tensor:
    """Largest |power| reachable with |dx|, |dy| <= radius: (|A| + 2|B| + |C|) r r. # [N]

    GLSL twin: `extent_power_bound` in shaders/splat.vert.
    """
    a, b, c = conic.abs().unbind(-1)
    return (a + 2.0 * b + c) * radius * radius


def screen_bounded(center: Tensor, conic: Tensor, shape: Tensor, radius: Tensor) -> Tensor:
    """Whether every screen-space value of a splat stays below FINITE_LIMIT in magnitude (NaN fails). # [N] bool

    The values: projected centre [N, 2], conic [N, 3], `alpha_shape` [N, 3], extent radius [N] and the
    `extent_power_bound`, which keeps the per-pixel float32 maths finite (no inf - inf = NaN).

    GLSL twin: `screen_bounded` in shaders/splat.vert.
    """

    def bounded(value: Tensor) -> Tensor:
        return value.abs() < FINITE_LIMIT  # NaN fails too

    return (
        bounded(center).all(dim=-1)
        & bounded(conic).all(dim=-1)
        & bounded(shape).all(dim=-1)
        & bounded(radius)
        & bounded(extent_power_bound(conic, radius))
    )


def splat_color(rgb: Tensor) -> Tensor:
    """Colour as composited: clamped to +-COLOR_LIMIT (far above any real colour) so sums stay finite. # [..., 3]

    GLSL twin: `splat_color` in shaders/splat.frag.
    """
    return torch.clamp(rgb, -COLOR_LIMIT, COLOR_LIMIT)


def splat_alpha(d: Tensor, shape: Tensor, opacity: Tensor) -> Tensor:
    """min(ALPHA_MAX, opacity exp(power)), 0 where skipped (power > 0 or alpha < ALPHA_MIN). # [...]

    d [..., 2] is pixel centre - projected centre, shape [..., 3] the `alpha_shape` (A, k, q), and
    power = -1/2 (A (dx - k dy)^2 + q dy^2) = -1/2 d^T cov2d^-1 d.

    GLSL twin: `splat_alpha` in shaders/splat.frag.
    """
    dx, dy = d.unbind(-1)  # each [...]
    a, k, q = shape.unbind(-1)  # each [...]
    return alpha_from_components(dx, dy, a, k, q, opacity)


def alpha_from_components(
    dx: Tensor, dy: Tensor, a: Tensor, k: Tensor, q: Tensor, opacity: Tensor, inside: Tensor | None = None,
    alpha_min: float = ALPHA_MIN,
) -> Tensor:
    """`splat_alpha` on split, broadcastable components: d = (dx, dy), `alpha_shape` = (a, k, q). # [...]

    No GLSL twin: the reference rasterizer's vectorised form of `splat_alpha` (its [tiles, pixels, splats] tensors
    come split). `inside` (bool), when given, also zeroes pixels outside the extent. `alpha_min` replaces the
    contract's cut as the CPU splatter's `RenderSettings.alpha_min` does (docs/precision.md, "Alpha cut-off").
    """
    t = dx - k * dy
    power = -0.5 * (a * t * t + q * dy * dy)
    # exp of min(power, 0): a positive power is skipped below anyway, and this keeps exp (and its grad) finite.
    alpha = torch.clamp_max(opacity * torch.exp(torch.clamp_max(power, 0.0)), ALPHA_MAX)
    # 3DGS skips power > 0 (a non-positive-definite conic) and alpha < ALPHA_MIN; both contribute nothing.
    # Multiplying by the mask is exact and much cheaper than torch.where; alpha is finite here (keep_mask).
    keep = (power <= 0) & (alpha >= alpha_min)
    return alpha * (keep if inside is None else keep & inside)


def keep_mask(
    p_cam: Tensor,
    center: Tensor,
    cov2d: Tensor,
    det: Tensor,
    conic: Tensor,
    shape: Tensor,
    radius: Tensor,
    near: float,
    *extra: Tensor,
) -> Tensor:
    """Which Gaussians are rasterized: camera z >= near (z == near kept), 2D det > 0, every value finite. # [N]

    `det` is `covariance_2d_determinant`'s. Screen-space values must pass `screen_bounded` (below FINITE_LIMIT);
    the others (camera-space points, cov2d and the per-Gaussian inputs in `extra`) must be finite.

    No GLSL twin: the runtime makes the same decisions in two places, the near-plane and finite-input tests in
    numpy (`depth_order` in runtime/splat/depth_sort.py) and the det > 0 and `screen_bounded` tests in the vertex
    shader's main.
    """
    keep = (p_cam[..., 2] >= near) & (det > 0) & screen_bounded(center, conic, shape, radius)
    for value in (p_cam, cov2d, *extra):
        finite = torch.isfinite(value)
        keep = keep & (finite.flatten(1).all(dim=-1) if finite.dim() > 1 else finite)
    return keep  # [N] bool
