"""Gaussians bound to FLAME triangles (paper §3.3.1) and the speaker-specific blendshapes (§3.3.2), in torch.

World-space Gaussian of binding i on triangle T (vertices v0, v1, v2), with gamma = W_gamma(psi):
    u = R (u_bar + BS(gamma; W_pos)) + P,   r = R r_bar BS(gamma; W_rot),   s = S s_bar,
    kappa0' = kappa0 + BS(gamma; W_color),  colour = sh_to_rgb(kappa', centre - camera centre)
where P = eta . (v0, v1, v2), R = [n0 n1 n2] (columns), S = mean edge length (`triangle_frame`).

The "scaled_triangle" binding (GaussianAvatars, docs/numerics.md) uses the same frame R but measures the local
position in units of the triangle's size k (`triangle_size`): u = k R (u_bar + ...) + P, s = k s_bar.
"""

from __future__ import annotations

import torch
from torch import nn

from gaussiantalker.sdk.config import LATENT_POSE_INPUT_DIM
from gaussiantalker.sdk.numerics import FRAME_EPS, sh_coeff_count
from gaussiantalker.sdk.rig import SCALED_TRIANGLE_BINDING, TRIANGLE_BINDING, TRIANGLE_BINDINGS

from .splat_math import cov3d_from_rotation_scale, quat_to_rotmat, sh_to_rgb

# A triangle-frame axis is divided by max(|v|, tolerance) with a tolerance of this fraction of the triangle's
# reference size (edge: fraction * L, cross product: fraction * L^2; L = rest mean edge length). Below it the axis
# fades continuously to zero instead of pointing wherever float rounding sends it: a collapsed triangle's
# direction is rounding noise, which torch and onnxruntime round differently. The demo head's thinnest rest
# triangle sits at 0.06 L^2 and its shortest first edge at 0.13 L, so no triangle fades at rest.
FRAME_DEGENERATE_FRACTION = 1e-2


def _guarded_divide(v: torch.Tensor, norm: torch.Tensor, tolerance: torch.Tensor, dim: int) -> torch.Tensor:
    """v / max(norm, tolerance), norm = |v| over axis `dim` (keepdim); tolerance > 0, so a zero vector stays zero.

    tolerance is [...] for v [..., 3] (dim=-1), and [N] for the component-major v [B, 3, N] (dim=1)."""
    return v / torch.maximum(norm, tolerance.unsqueeze(-1) if dim < 0 else tolerance)


def frame_tolerances(reference_scale: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Guards of `triangle_frame` from reference edge lengths L [...]: (edge, cross product), never below FRAME_EPS.

    Both scale with the triangle (L and L^2), so the frame of a head in millimetres or in kilometres is the same.
    """
    edge = torch.clamp(FRAME_DEGENERATE_FRACTION * reference_scale, min=FRAME_EPS)
    area = torch.clamp(FRAME_DEGENERATE_FRACTION * reference_scale * reference_scale, min=FRAME_EPS * FRAME_EPS)
    return edge, area


def quat_multiply(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product a * b of (w, x, y, z) quaternions [..., 4]: the rotation of a applied after b's."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack([aw * bw - ax * bx - ay * by - az * bz,
                        aw * bx + ax * bw + ay * bz - az * by,
                        aw * by - ax * bz + ay * bw + az * bx,
                        aw * bz + ax * by - ay * bx + az * bw], dim=-1)


def triangle_frame(v0: torch.Tensor, v1: torch.Tensor, v2: torch.Tensor,
                   reference_scale: torch.Tensor | None = None, dim: int = -1) -> tuple[torch.Tensor, torch.Tensor]:
    """Local frame of triangles [..., 3] each: rotation [..., 3, 3] with columns n0, n1, n2 and scale S [...].

    With `dim` >= 0 the vertices' components lie on that axis ([B, 3, N] with dim=1) and the rotation is
    [B, 3, 3, N] (row, column at dim, dim + 1): the deformation graph's component-major layout.

    n0 = e01 / max(|e01|, tol_edge), n1 = (e01 x e02) / max(|e01 x e02|, tol_cross), n2 = n0 x n1, with the
    tolerances of `frame_tolerances(reference_scale)` (default: the current S). Finite for any input; a triangle
    collapsed to a segment or a point gets shrunken (zero when exact) axes instead of noise-driven unit ones.
    """
    e01, e02, e12 = v1 - v0, v2 - v0, v2 - v1
    l01 = torch.linalg.vector_norm(e01, dim=dim, keepdim=True)
    lengths = l01 + torch.linalg.vector_norm(e02, dim=dim, keepdim=True) + torch.linalg.vector_norm(e12, dim=dim,
                                                                                                   keepdim=True)
    scale = lengths.squeeze(dim) / 3.0  # [...]
    tol_edge, tol_cross = frame_tolerances(scale if reference_scale is None else reference_scale)
    n0 = _guarded_divide(e01, l01, tol_edge, dim)
    cross = torch.cross(e01, e02, dim=dim)
    n1 = _guarded_divide(cross, torch.linalg.vector_norm(cross, dim=dim, keepdim=True), tol_cross, dim)
    n2 = torch.cross(n0, n1, dim=dim)
    rotation = torch.stack([n0, n1, n2], dim=-1 if dim < 0 else dim + 1)  # [..., 3, 3], columns are the axes
    return rotation, scale


def triangle_size(rotation: torch.Tensor, v0: torch.Tensor, v1: torch.Tensor, v2: torch.Tensor, dim: int = -1
                  ) -> torch.Tensor:
    """GaussianAvatars' triangle size k = (|e01| + |n2 · e02|) / 2 [...]: half the first edge plus the triangle's
    height over it, with n2 the third axis of `triangle_frame`'s `rotation` (same `dim` layout). No division."""
    n2 = rotation.select(-1 if dim < 0 else dim + 1, 2)  # [..., 3] (or [B, 3, N] with dim=1)
    e01, e02 = v1 - v0, v2 - v0
    height = (n2 * e02).sum(dim).abs()
    return 0.5 * (torch.linalg.vector_norm(e01, dim=dim) + height)


class LatentPoseMLP(nn.Module):
    """W_gamma: FLAME pose psi (neck, jaw, eyes; [B, 12]) -> latent pose gamma [B, latent_dim]."""

    def __init__(self, latent_dim: int, hidden: int) -> None:
        super().__init__()
        self.net = nn.Sequential(nn.Linear(LATENT_POSE_INPUT_DIM, hidden), nn.SiLU(), nn.Linear(hidden, latent_dim))

    def forward(self, psi: torch.Tensor) -> torch.Tensor:
        return self.net(psi)


class BoundGaussians(nn.Module):
    """Gaussian attributes in triangle-local space plus the speaker-specific blendshape weights."""

    def __init__(self, parent: torch.Tensor, faces: torch.Tensor, sh_degree: int, latent_dim: int,
                 binding: str = TRIANGLE_BINDING) -> None:
        super().__init__()
        if binding not in TRIANGLE_BINDINGS:
            raise ValueError(f"binding must be one of {', '.join(TRIANGLE_BINDINGS)}, got {binding!r}")
        n = int(parent.shape[0])
        k = sh_coeff_count(sh_degree)
        self.sh_degree = sh_degree
        self.binding = binding
        self.register_buffer("parent", parent.long())  # [N] parent triangle index
        self.register_buffer("vertex_ids", faces.long()[parent.long()])  # [N, 3] parent triangle's vertices
        self.barycentric = nn.Parameter(torch.full((n, 3), 1.0 / 3.0))  # eta [N, 3]
        self.local_position = nn.Parameter(torch.zeros(n, 3))  # u_bar [N, 3]
        self.local_rotation = nn.Parameter(torch.tensor([1.0, 0.0, 0.0, 0.0]).repeat(n, 1))  # r_bar quat [N, 4]
        self.log_scale = nn.Parameter(torch.zeros(n, 3))  # log s_bar [N, 3]
        self.opacity_logit = nn.Parameter(torch.zeros(n))  # [N]
        self.sh = nn.Parameter(torch.zeros(n, k, 3))  # kappa [N, K, 3]
        self.w_pos = nn.Parameter(torch.zeros(n, 3, latent_dim))  # W_pos [N, 3, D]
        self.w_rot = nn.Parameter(torch.zeros(n, 4, latent_dim))  # W_rot [N, 4, D] (quaternion offsets)
        self.w_color = nn.Parameter(torch.zeros(n, 3, latent_dim))  # W_color [N, 3, D]
        # Rest-pose mean edge length of each parent triangle [N]: the reference size of `triangle_frame`'s guards.
        # Derived from the FLAME model and shape (`set_rest_vertices`), so not saved in checkpoints; 0 = unknown.
        self.register_buffer("rest_scale", torch.zeros(n), persistent=False)

    @property
    def count(self) -> int:
        return int(self.parent.shape[0])

    @torch.no_grad()
    def set_rest_vertices(self, vertices: torch.Tensor) -> None:
        """Record each parent triangle's mean edge length in the rest mesh [V, 3] (reference of the frame guards)."""
        corners = vertices.index_select(0, self.vertex_ids.reshape(-1)).reshape(-1, 3, 3)  # [N, 3, 3]
        self.rest_scale.copy_(triangle_frame(corners[:, 0], corners[:, 1], corners[:, 2])[1])

    def forward(self, vertices: torch.Tensor, gamma: torch.Tensor, camera_center: torch.Tensor
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """vertices [B, V, 3], gamma [B, D], camera_center [B, 3] -> means, cov3d [B,N,6], rgb, opacity [N]."""
        batch = vertices.shape[0]
        corners = vertices.index_select(1, self.vertex_ids.reshape(-1)).reshape(batch, -1, 3, 3)  # [B, N, 3, 3]
        rotation, scale = triangle_frame(corners[:, :, 0], corners[:, :, 1], corners[:, :, 2], self.rest_scale)
        origin = (self.barycentric.unsqueeze(-1) * corners).sum(2)  # P [B, N, 3]

        local_position = self.local_position + torch.einsum("nkd,bd->bnk", self.w_pos, gamma)  # [B, N, 3]
        if self.binding == SCALED_TRIANGLE_BINDING:  # position and scale in units of the triangle's size k
            scale = triangle_size(rotation, corners[:, :, 0], corners[:, :, 1], corners[:, :, 2])  # [B, N]
            local_position = local_position * scale.unsqueeze(-1)
        means = (rotation * local_position.unsqueeze(-2)).sum(-1) + origin  # R u_bar' + P

        # r_bar' = r_bar * BS(gamma; W_rot): composed as quaternions (|q1 q2| = |q1||q2|, so normalising the
        # product inside quat_to_rotmat equals multiplying the two normalised rotations), one 3x3 product less.
        identity = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=gamma.dtype)
        delta = identity + torch.einsum("nkd,bd->bnk", self.w_rot, gamma)  # [B, N, 4]
        world_rotation = rotation @ quat_to_rotmat(quat_multiply(self.local_rotation, delta))  # [B, N, 3, 3]
        world_scale = scale.unsqueeze(-1) * torch.exp(self.log_scale)  # [B, N, 3]
        cov3d = cov3d_from_rotation_scale(world_rotation, world_scale)

        dc = self.sh[:, 0] + torch.einsum("nkd,bd->bnk", self.w_color, gamma)  # kappa0' [B, N, 3]
        rgb = sh_to_rgb(self.sh, means - camera_center.unsqueeze(1), self.sh_degree, dc=dc)
        opacity = torch.sigmoid(self.opacity_logit)
        return means, cov3d, rgb, opacity
