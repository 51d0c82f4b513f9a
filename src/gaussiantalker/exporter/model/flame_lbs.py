"""FLAME in torch: blendshapes and linear blend skinning (`rodrigues`, `lbs`, `FlameLayer`).

A pure function of tensors built from common ONNX ops (matmul, sin, sqrt, reshape, stack), so it exports with a
dynamic batch and mirrors smplx/FLAME numerically:

    v_shaped = v_template + shapedirs·β + exprdirs·ε                      # [B, V, 3]
    J        = J_regressor · v_shaped                                     # [B, 5, 3]
    v_posed  = v_shaped + ((R_j − I) for the 4 non-root joints)·posedirs  # [B, V, 3]
    v        = Σ_k w_k (G_k · v_posed)                                    # forward kinematics along parents
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from torch import nn

from .flame import FLAME_FLOAT_KEYS, FlameArrays

# Rodrigues guard: angle = sqrt(|r|^2 + eps) keeps the axis, the angle and their gradients finite at r = 0.
ANGLE_EPS = 1e-16


def rodrigues(rotvec: torch.Tensor) -> torch.Tensor:
    """Axis-angle [N, 3] -> rotation matrices [N, 3, 3]; finite (with finite gradients) at 0 and any angle."""
    angle = torch.sqrt((rotvec * rotvec).sum(dim=1, keepdim=True) + ANGLE_EPS)  # [N, 1]
    axis = rotvec / angle  # [N, 3]; ~0 (not NaN) at zero rotation, where sin(angle) ~ angle restores scale
    x, y, z = axis[:, 0], axis[:, 1], axis[:, 2]
    zero = torch.zeros_like(x)
    k = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], dim=1).reshape(-1, 3, 3)  # [N, 3, 3] [axis]x
    sin = torch.sin(angle).unsqueeze(2)  # [N, 1, 1]
    half = torch.sin(0.5 * angle).unsqueeze(2)
    eye = torch.eye(3, dtype=rotvec.dtype, device=rotvec.device)
    return eye + sin * k + (2.0 * half * half) * torch.matmul(k, k)  # 1 - cos = 2 sin^2(a/2), no cancellation


def blend_shapes(coeffs: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """Linear blendshape offsets: coeffs [B, L] · dirs [V, 3, L] -> [B, V, 3]."""
    n_v = dirs.shape[0]
    flat = dirs.reshape(n_v * 3, dirs.shape[2])  # [V*3, L]
    return torch.matmul(coeffs, flat.transpose(0, 1)).reshape(coeffs.shape[0], n_v, 3)


def forward_kinematics(
    rot: torch.Tensor, joints: torch.Tensor, parents: Sequence[int]
) -> tuple[torch.Tensor, torch.Tensor]:
    """World rotations [B, J, 3, 3] and posed joints [B, J, 3] from local rotations and rest joints."""
    world_rot = [rot[:, 0]]
    world_pos = [joints[:, 0]]
    for i in range(1, len(parents)):
        p = parents[i]
        offset = (joints[:, i] - joints[:, p]).unsqueeze(2)  # [B, 3, 1]
        world_rot.append(torch.matmul(world_rot[p], rot[:, i]))
        world_pos.append(torch.matmul(world_rot[p], offset).squeeze(2) + world_pos[p])
    return torch.stack(world_rot, dim=1), torch.stack(world_pos, dim=1)


def lbs(
    v_template: torch.Tensor,
    shapedirs: torch.Tensor,
    exprdirs: torch.Tensor,
    posedirs: torch.Tensor,
    J_regressor: torch.Tensor,
    parents: Sequence[int],
    lbs_weights: torch.Tensor,
    shape: torch.Tensor,
    expression: torch.Tensor,
    pose: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """FLAME blendshapes + linear blend skinning -> (vertices [B, V, 3], posed joints [B, 5, 3]).

    shape [B, n_shape], expression [B, n_expr], pose [B, 15] axis-angle per joint in FLAME_JOINTS order.
    `parents` is the static kinematic tree (python ints), so the graph has no data-dependent control flow.
    """
    _check_parents(parents)
    batch = pose.shape[0]
    n_v = v_template.shape[0]
    n_j = len(parents)
    v_shaped = v_template.unsqueeze(0) + blend_shapes(shape, shapedirs) + blend_shapes(expression, exprdirs)
    joints = torch.matmul(J_regressor, v_shaped)  # [J, V] @ [B, V, 3] -> [B, J, 3]
    rot = rodrigues(pose.reshape(-1, 3)).reshape(batch, n_j, 3, 3)  # [B, J, 3, 3]
    eye = torch.eye(3, dtype=pose.dtype, device=pose.device)
    pose_feature = (rot[:, 1:] - eye).reshape(batch, 9 * (n_j - 1))  # [B, 36]
    v_posed = v_shaped + torch.matmul(pose_feature, posedirs).reshape(batch, n_v, 3)  # [B, V, 3]
    world_rot, world_pos = forward_kinematics(rot, joints, parents)
    # Joint k moves a rest point v to world_rot_k (v - J_k) + world_pos_k.
    skin_t = world_pos - torch.matmul(world_rot, joints.unsqueeze(3)).squeeze(3)  # [B, J, 3]
    blend_rot = torch.matmul(lbs_weights, world_rot.reshape(batch, n_j, 9)).reshape(batch, n_v, 3, 3)
    blend_t = torch.matmul(lbs_weights, skin_t)  # [V, J] @ [B, J, 3] -> [B, V, 3]
    vertices = torch.matmul(blend_rot, v_posed.unsqueeze(3)).squeeze(3) + blend_t
    return vertices, world_pos


def _check_parents(parents: Sequence[int]) -> None:
    """The tree must be topologically ordered with the root first (static check, not traced)."""
    if len(parents) < 1 or parents[0] != -1 or any(not 0 <= p < i for i, p in enumerate(parents) if i):
        raise ValueError(f"parents {tuple(parents)} is not a root-first kinematic tree")


class FlameLayer(nn.Module):
    """FLAME as a torch module: every basis a buffer; forward(shape, expression, pose, translation)."""

    def __init__(self, arrays: FlameArrays) -> None:
        super().__init__()
        arrays.validate()
        for key in FLAME_FLOAT_KEYS:
            self.register_buffer(key, torch.from_numpy(np.array(getattr(arrays, key), dtype=np.float32)))
        self.register_buffer("faces", torch.from_numpy(np.array(arrays.faces, dtype=np.int64)))
        self.parents = tuple(int(p) for p in arrays.parents)
        self.n_shape = arrays.n_shape
        self.n_expr = arrays.n_expr

    def posed(
        self, shape: torch.Tensor, expression: torch.Tensor, pose: torch.Tensor, translation: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Vertices [B, V, 3] and posed joints [B, 5, 3], both shifted by translation [B, 3]."""
        vertices, joints = lbs(
            self.v_template,
            self.shapedirs,
            self.exprdirs,
            self.posedirs,
            self.J_regressor,
            self.parents,
            self.lbs_weights,
            shape,
            expression,
            pose,
        )
        offset = translation.unsqueeze(1)  # [B, 1, 3]
        return vertices + offset, joints + offset

    def forward(
        self, shape: torch.Tensor, expression: torch.Tensor, pose: torch.Tensor, translation: torch.Tensor
    ) -> torch.Tensor:
        """Posed mesh vertices [B, V, 3] (translation added after LBS)."""
        return self.posed(shape, expression, pose, translation)[0]
