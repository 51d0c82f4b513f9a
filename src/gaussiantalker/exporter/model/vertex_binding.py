"""Gaussians bound to mesh vertices, as LAM binds them (docs/numerics.md, "Vertex binding"), in torch.

Gaussian i sits at mesh vertex v(i) plus a fixed offset o_i, and the head bone carries both rigidly:
    u_i = R (x_v(i) + o_i - p) + p + t,    x_v = x̄_v + sum_k w_k Δ_k,v   (the blendshape rig's morphed vertex)
with the head rotation R about the bone's pivot p and translation t. Rotation, scale and colour do not follow the
mesh: the covariance is the rest one, Σ = (R̄ S)(R̄ S)ᵀ ("static", as LAM's web renderer draws it) or R Σ Rᵀ
("head"); colour is `sh_to_rgb` of the stored coefficients (LAM's f_dc are RGB: imported as SH degree 0).
"""

from __future__ import annotations

import torch
from torch import nn

from gaussiantalker.sdk.numerics import sh_coeff_count
from gaussiantalker.sdk.rig import COVARIANCE_MODES

from .splat_math import cov3d_from_rotation_scale, quat_to_rotmat, sh_to_rgb


def rigid_head(points: torch.Tensor, rotation: torch.Tensor, pivot: torch.Tensor, translation: torch.Tensor
               ) -> torch.Tensor:
    """points [B, N, 3] turned by rotation [B, 3, 3] about pivot [3], then moved by translation [B, 3].

    No GLSL twin: part of the deformation graph, which the runtime runs as the ONNX export of this code."""
    return torch.einsum("bij,bnj->bni", rotation, points - pivot) + pivot + translation.unsqueeze(1)


def rotate_covariance(cov3d: torch.Tensor, rotation: torch.Tensor) -> torch.Tensor:
    """Packed covariances [B, N, 6] (xx, xy, xz, yy, yz, zz) -> R Σ Rᵀ, packed, for rotations [B, 3, 3]."""
    xx, xy, xz, yy, yz, zz = cov3d.unbind(-1)
    sigma = torch.stack([torch.stack([xx, xy, xz], -1), torch.stack([xy, yy, yz], -1),
                         torch.stack([xz, yz, zz], -1)], -2)  # [B, N, 3, 3]
    turned = torch.einsum("bij,bnjk,blk->bnil", rotation, sigma, rotation)
    return torch.stack([turned[..., 0, 0], turned[..., 0, 1], turned[..., 0, 2], turned[..., 1, 1],
                        turned[..., 1, 2], turned[..., 2, 2]], -1)


class VertexBoundGaussians(nn.Module):
    """Per-Gaussian attributes of the vertex binding: bound vertex, offset, rest rotation/scale, opacity, SH."""

    def __init__(self, vertex: torch.Tensor, sh_degree: int, covariance: str = "static") -> None:
        super().__init__()
        if covariance not in COVARIANCE_MODES:
            raise ValueError(f"covariance must be one of {', '.join(COVARIANCE_MODES)}, got {covariance!r}")
        n = int(vertex.shape[0])
        self.sh_degree = sh_degree
        self.covariance = covariance
        self.register_buffer("vertex", vertex.long().clone())  # [N] bound mesh vertex
        self.offset = nn.Parameter(torch.zeros(n, 3))  # o [N, 3], world units
        self.rotation = nn.Parameter(torch.tensor([1.0, 0.0, 0.0, 0.0]).repeat(n, 1))  # quaternion (w,x,y,z) [N, 4]
        self.log_scale = nn.Parameter(torch.zeros(n, 3))  # [N, 3]
        self.opacity_logit = nn.Parameter(torch.zeros(n))  # [N]
        self.sh = nn.Parameter(torch.zeros(n, sh_coeff_count(sh_degree), 3))  # [N, K, 3]

    @property
    def count(self) -> int:
        return int(self.vertex.shape[0])

    def rest_covariance(self) -> torch.Tensor:
        """Σ = (R̄ S)(R̄ S)ᵀ packed [N, 6]."""
        return cov3d_from_rotation_scale(quat_to_rotmat(self.rotation), torch.exp(self.log_scale))

    def forward(self, vertices: torch.Tensor, rotation: torch.Tensor, pivot: torch.Tensor,
                translation: torch.Tensor, camera_center: torch.Tensor
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """Morphed rest-frame vertices [B, V, 3], head rotation [B, 3, 3], pivot [3], translation [B, 3], camera
        centre [B, 3] -> means [B, N, 3], cov3d [B, N, 6], rgb [B, N, 3], opacity [N]."""
        batch = vertices.shape[0]
        bound = vertices.index_select(1, self.vertex) + self.offset  # x_v(i) + o_i [B, N, 3]
        means = rigid_head(bound, rotation, pivot, translation)
        cov3d = self.rest_covariance().unsqueeze(0).expand(batch, -1, -1)
        if self.covariance == "head":
            cov3d = rotate_covariance(cov3d, rotation)
        rgb = sh_to_rgb(self.sh, means - camera_center.unsqueeze(1), self.sh_degree)
        return means, cov3d, rgb, torch.sigmoid(self.opacity_logit)


__all__ = ["VertexBoundGaussians", "rigid_head", "rotate_covariance"]
