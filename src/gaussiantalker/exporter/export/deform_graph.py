"""The `deform` ONNX graph: `Speaker.deform` rewritten as a few large ops over constants folded at export.

`Speaker.deform` (FLAME layer + latent-pose MLP + `BoundGaussians`) is the readable reference, written as the
paper states it. Run per frame as exported, it re-applies the fixed shape β, forms per-Gaussian 3×3 products
with small broadcast reductions and spends ~380 onnxruntime nodes on ~5 M multiply-adds. `DeformationGraph`
computes the same function (equal up to float32 rounding, verified against the reference by the graph parity
tests and `gt-export --verify`) with everything that does not change per frame folded in once, at export:

* the shape blendshapes into the rest template; the joint regressor into a [5, 3] rest position plus a linear
  map of the expression; the expression and pose-corrective bases into one matrix, so a frame's posed mesh and
  joints are one matrix product;
* the quaternion composition r̄ ⊗ (1 + W_rot γ) into the blendshape weights (the Hamilton product is linear in
  its second factor), and the three speaker blendshapes (W_pos, W_rot, W_color) into one [D, 10 N] matrix;
* exp(log-scale), sigmoid(opacity logit) and the triangle-frame guards, which do not depend on the frame.

Per-Gaussian values are laid out component-major ([B, 3, N] rather than [B, N, 3]), so every elementwise step
runs over long contiguous rows and every 3-vector reduction sums three rows. docs/deformation.md lists each
folding with the reason it is exact (up to rounding); the numerics rules are those of docs/numerics.md.

Every tensor this module derives from the speaker is a buffer or a parameter (a named initializer of the
exported graph), so the graph holds no speaker-specific inline constant.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from gaussiantalker.sdk.numerics import SH_C0, sh_coeff_count
from gaussiantalker.sdk.rig import SCALED_TRIANGLE_BINDING

from ..model.flame import N_JOINTS, POSE_FEATURE_DIM
from ..model.flame_lbs import forward_kinematics, rodrigues
from ..model.gaussians import triangle_frame, triangle_size
from ..model.speaker import Speaker
from ..model.splat_math import quat_to_rotmat, sh_basis

# Rows of the latent blendshape product per Gaussian: local position (3), quaternion (4), SH DC colour (3).
LATENT_ROWS = (3, 4, 3)
# Packed covariance entries (xx, xy, xz, yy, yz, zz) as indices into a row-major 3x3.
_COV_ENTRIES = (0, 1, 2, 4, 5, 8)


def hamilton_left_matrix(a: torch.Tensor) -> torch.Tensor:
    """L(a) [..., 4, 4] with L(a) b = a ⊗ b for (w, x, y, z) quaternions a [..., 4] (`gaussians.quat_multiply`)."""
    w, x, y, z = a.unbind(-1)
    rows = ((w, -x, -y, -z), (x, w, -z, y), (y, z, w, -x), (z, -y, x, w))
    return torch.stack([torch.stack(row, dim=-1) for row in rows], dim=-2)


def low_rank_factors(weight: torch.Tensor, rank: int, groups: tuple[int, ...], n: int
                     ) -> tuple[torch.Tensor, torch.Tensor]:
    """weight [D, sum(groups) * n] ~ basis [D, rank] @ factor [rank, sum(groups) * n], the rank-`rank` truncated SVD
    after scaling each row group (position, quaternion, colour: different units) to unit RMS, so that no group's
    error is traded for another's merely because its numbers are smaller (docs/precision.md)."""
    sizes = [g * n for g in groups]
    rms = torch.stack([block.pow(2).mean().sqrt() for block in weight.split(sizes, dim=1)])
    rms = torch.where(rms > 0, rms, torch.ones_like(rms))
    column_scale = torch.cat([r.expand(size) for r, size in zip(rms, sizes, strict=True)])  # [10 n]
    u, s, vh = torch.linalg.svd(weight / column_scale, full_matrices=False)
    return u[:, :rank] * s[:rank], vh[:rank] * column_scale


class DeformationGraph(nn.Module):
    """Per-frame drive -> world-space Gaussians (means [B,N,3], cov3d [B,N,6], rgb [B,N,3], opacity [N]), as the
    runtime runs it; same inputs, outputs and meaning as `Speaker.deform`.

    Two model-size knobs (docs/precision.md), both off by default: `sh_degree` keeps only the SH bands up to that
    degree; `blendshape_rank` replaces the [D, 10 N] speaker blendshape matrix by a rank-r product."""

    def __init__(self, speaker: Speaker, *, sh_degree: int | None = None, blendshape_rank: int | None = None,
                 drive_allowed: np.ndarray | None = None, latent_subspace: tuple | None = None,
                 vertex_subset: bool = False) -> None:
        """Scene options (specialise.py, docs/scene.md): `drive_allowed` [E + 36] bool leaves out the FLAME
        basis rows of drive entries the scene keeps at 0; `latent_subspace` (mean [D], orthonormal basis [D, r])
        stores the speaker blendshapes projected onto the affine subspace γ stays in; `vertex_subset` computes only
        the vertices the Gaussians' triangles use."""
        super().__init__()
        speaker = speaker.eval()
        flame, gaussians = speaker.flame_arrays, speaker.gaussians
        self.n_vertices, self.n_gaussians = flame.n_vertices, gaussians.count
        self.sh_degree = gaussians.sh_degree if sh_degree is None else min(int(sh_degree), gaussians.sh_degree)
        self.parents = tuple(int(p) for p in flame.parents)
        self.scaled_binding = gaussians.binding == SCALED_TRIANGLE_BINDING
        self.latent_pose = speaker.latent_pose
        self.blendshape_rank = blendshape_rank
        with torch.no_grad():
            self._fold_flame(speaker, drive_allowed, vertex_subset)
            self._fold_gaussians(speaker, latent_subspace)

    def _fold_flame(self, speaker: Speaker, drive_allowed: np.ndarray | None, vertex_subset: bool) -> None:
        """Rest mesh and joints with β applied, and one basis [E + 36, 3V + 15] for expression and pose correctives.

        Vertex columns are component-major (x of every vertex, then y, then z), so the product reshapes to
        [B, 3, V] without a transpose; the last 15 columns are the joints' expression offsets (zero for the pose
        rows: FLAME regresses joints from the shaped, unposed mesh).
        """
        flame = speaker.flame
        n_v = self.n_vertices
        shape = speaker.shape.double()
        rest = flame.v_template.double() + torch.einsum("vcl,l->vc", flame.shapedirs.double(), shape)  # [V, 3]
        regressor = flame.J_regressor.double()  # [5, V]
        rest_joints = regressor @ rest  # [5, 3]
        exprdirs = flame.exprdirs.double()  # [V, 3, E]
        joint_dirs = torch.einsum("jv,vce->ejc", regressor, exprdirs).reshape(-1, 3 * N_JOINTS)  # [E, 15]
        expr_rows = exprdirs.permute(2, 1, 0).reshape(-1, 3 * n_v)  # [E, 3V] component-major
        pose_rows = flame.posedirs.double().reshape(POSE_FEATURE_DIM, n_v, 3).permute(0, 2, 1).reshape(
            POSE_FEATURE_DIM, 3 * n_v)  # [36, 3V]
        basis = torch.cat([torch.cat([expr_rows, joint_dirs], 1),
                           torch.cat([pose_rows, pose_rows.new_zeros(POSE_FEATURE_DIM, 3 * N_JOINTS)], 1)], 0)
        # Rows that are exactly zero (e.g. pose correctives of joints the head model never corrects) add nothing:
        # they are left out, and the drive's matching entries are not gathered (exact, docs/deformation.md).
        keep = basis.abs().amax(1) > 0
        if drive_allowed is not None:  # drive entries the scene keeps at 0 add nothing either (docs/scene.md)
            keep &= torch.as_tensor(drive_allowed, dtype=torch.bool)
        keep[0] |= not bool(keep.any())  # an all-zero basis keeps one row, so no tensor has a zero-size axis
        self.register_buffer("drive_rows", None if bool(keep.all()) else torch.nonzero(keep).reshape(-1))  # [kept]
        basis = basis[keep]
        rest_points = torch.cat([rest.T.reshape(-1), rest_joints.reshape(-1)])  # [3V + 15]
        lbs_weights = flame.lbs_weights.T  # [5, V]
        # The triangles the Gaussians are bound to, and (with vertex_subset) only the vertices those use: columns
        # of the basis, rest points and skinning weights of other vertices never reach a Gaussian.
        triangles, parent = torch.unique(speaker.gaussians.parent, return_inverse=True)
        faces = torch.as_tensor(speaker.flame_arrays.faces).long()[triangles]  # [F used, 3]
        if vertex_subset:
            vertices, faces = torch.unique(faces, return_inverse=True)  # [V used], faces renumbered
            columns = torch.cat([vertices + c * n_v for c in range(3)] +
                                [torch.arange(3 * n_v, 3 * n_v + 3 * N_JOINTS)])
            basis, rest_points, lbs_weights = basis[:, columns], rest_points[columns], lbs_weights[:, vertices]
            self.n_vertices = n_v = int(vertices.numel())
        self.register_buffer("rest_points", rest_points.float())
        self.register_buffer("blend_basis", basis.float())  # [rows kept of E + 36, 3V + 15]
        self.register_buffer("lbs_weights", lbs_weights.reshape(N_JOINTS, 1, n_v).contiguous())  # [5, 1, V]
        # Triangle ids and the face table (stored with the `index` codec); onnxruntime folds the gather at load.
        self.register_buffer("parent_triangle", parent.reshape(-1).clone())  # [N] into `faces`
        self.register_buffer("faces", faces.contiguous())  # [F used, 3]

    def _fold_gaussians(self, speaker: Speaker, latent_subspace: tuple | None) -> None:
        """Per-Gaussian constants, component-major, and the three speaker blendshapes as one [D, 10 N] matrix
        (projected onto the scene's latent subspace, and/or a low-rank product, when asked)."""
        g = speaker.gaussians
        n = self.n_gaussians
        self.register_buffer("barycentric", g.barycentric.T.contiguous())  # [3 corners, N]
        self.register_buffer("rest_scale", g.rest_scale.clone())  # [N] reference size of the frame guards
        # Stored as logs (uniform relative error when quantised); exp is folded by onnxruntime at load.
        self.register_buffer("log_scale", g.log_scale.T.contiguous())  # [3, N]
        self.register_buffer("opacity", torch.sigmoid(g.opacity_logit).clone())  # [N]
        self.register_buffer("cov_entries", torch.tensor(_COV_ENTRIES))  # upper triangle of a row-major 3x3
        k = sh_coeff_count(self.sh_degree)
        if self.sh_degree > 0:
            self.register_buffer("sh_rest", g.sh[:, 1:k].permute(2, 1, 0).contiguous())  # [3, K-1, N]

        # r̄ ⊗ (1 + W_rot γ) = r̄ + L(r̄) W_rot γ (the identity is (1, 0, 0, 0) and L(r̄)(1, 0, 0, 0) = r̄).
        w_quat = hamilton_left_matrix(g.local_rotation.double()) @ g.w_rot.double()  # [N, 4, D]
        weights = torch.cat([g.w_pos.double(), w_quat, g.w_color.double()], 1)  # [N, 10, D]
        bias = torch.cat([g.local_position, g.local_rotation, g.sh[:, 0]], 1)  # [N, 10]
        weight = weights.permute(2, 1, 0).reshape(-1, 10 * n)  # [D, 10N]
        bias = bias.T.reshape(-1).double()  # [10N]
        basis = None
        if latent_subspace is not None:
            # γ = m + U Uᵀ(γ - m) on the subspace, so γ W = (γ U)(Uᵀ W) + (m - m U Uᵀ) W (docs/scene.md).
            mean, basis = (t.double() for t in latent_subspace)  # [D], [D, r]
            bias = bias + (mean - (mean @ basis) @ basis.T) @ weight
            weight = basis.T @ weight  # [r, 10N]
        # Speaker blendshapes that are exactly zero (an imported avatar has none) add nothing: the graph leaves out
        # the latent-pose MLP and the product, and the per-Gaussian values are the constant bias (exact).
        self.has_latent = bool(weight.abs().max() > 0)
        if not self.has_latent:
            self.latent_pose = None
            self.blendshape_rank = None
            self.has_latent_basis = False
            self.register_buffer("latent_bias", bias.float().contiguous())  # [10N]
            return
        if self.blendshape_rank is not None and self.blendshape_rank < weight.shape[0]:
            factor, weight = low_rank_factors(weight, int(self.blendshape_rank), LATENT_ROWS, n)
            basis = factor if basis is None else basis @ factor
        else:
            self.blendshape_rank = None
        self.has_latent_basis = basis is not None
        if basis is not None:
            self.register_buffer("latent_basis", basis.float())  # [D, r]
        self.register_buffer("latent_weight", weight.float())  # [D or r, 10N]
        self.register_buffer("latent_bias", bias.float().contiguous())  # [10N]

    def forward(self, expression: torch.Tensor, flame_pose: torch.Tensor, head_translation: torch.Tensor,
                camera_center: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        vertices = self.posed_vertices(expression, flame_pose, head_translation)  # [B, 3, V]
        batch, n = vertices.shape[0], self.n_gaussians
        # Gathered as [B, 3N, 3] and then transposed: onnxruntime copies a gathered row of 3 floats at the cost
        # of one float, so this is faster than gathering along the last axis of [B, 3, V] (docs/deformation.md).
        corner_ids = self.faces.index_select(0, self.parent_triangle).T.reshape(-1)  # [3N]: all v0, v1, v2
        corners = vertices.transpose(1, 2).index_select(1, corner_ids)  # [B, 3N, 3]
        corners = corners.transpose(1, 2).reshape(batch, 3, 3, n)  # [B, xyz, corner, N]
        v0, v1, v2 = corners[:, :, 0], corners[:, :, 1], corners[:, :, 2]  # [B, 3, N] each
        rotation, scale = triangle_frame(v0, v1, v2, self.rest_scale, dim=1)  # [B, 3, 3, N], [B, N]
        origin = (corners * self.barycentric).sum(2)  # P [B, 3, N]

        if self.has_latent:
            gamma = self.latent_pose(flame_pose[:, 3:])  # [B, D]
            if self.has_latent_basis:
                gamma = gamma @ self.latent_basis  # [B, r]
            latent = (gamma @ self.latent_weight + self.latent_bias).reshape(batch, sum(LATENT_ROWS), n)
        else:
            latent = self.latent_bias.reshape(1, sum(LATENT_ROWS), n).expand(batch, -1, -1)
        local_position, quaternion, dc = latent.split(LATENT_ROWS, dim=1)  # [B, 3|4|3, N]
        if self.scaled_binding:  # position and scale in units of the triangle's size k (docs/numerics.md)
            scale = triangle_size(rotation, v0, v1, v2, dim=1)  # [B, N]
            local_position = local_position * scale.unsqueeze(1)

        means = (rotation * local_position.unsqueeze(1)).sum(2) + origin  # R u_bar' + P  [B, 3, N]
        local_rotation = quat_to_rotmat(quaternion, dim=1)  # [B, 3, 3, N]
        world_rotation = (rotation.unsqueeze(3) * local_rotation.unsqueeze(1)).sum(2)  # R R_local [B, 3, 3, N]
        scale_bar = torch.exp(self.log_scale)  # [3, N]
        m = world_rotation * (scale.unsqueeze(1) * scale_bar).unsqueeze(1)  # R R_local diag(s) [B, 3, 3, N]
        cov = (m.unsqueeze(2) * m.unsqueeze(1)).sum(3).reshape(batch, 9, n)  # m m^T, row-major [B, 9, N]
        cov3d = cov.index_select(1, self.cov_entries)  # [B, 6, N]

        rgb = SH_C0 * dc  # [B, 3, N]
        if self.sh_degree > 0:
            basis = sh_basis(means - camera_center.unsqueeze(2), self.sh_degree, dim=1, skip_dc=True)  # [B, K-1, N]
            # Channel-major coefficients: onnxruntime reduces over the middle axis of [B, 3, K-1, N] faster than
            # over the leading axis of [B, K-1, 3, N] (docs/deformation.md, "Layout").
            rgb = rgb + (basis.unsqueeze(1) * self.sh_rest).sum(2)
        rgb = torch.clamp_min(rgb + 0.5, 0.0)
        return means.transpose(1, 2), cov3d.transpose(1, 2), rgb.transpose(1, 2), self.opacity

    def posed_vertices(self, expression: torch.Tensor, flame_pose: torch.Tensor, head_translation: torch.Tensor
                       ) -> torch.Tensor:
        """FLAME blendshapes + linear blend skinning with the folded constants -> vertices [B, 3, V]."""
        batch, n_v = expression.shape[0], self.n_vertices
        rot = rodrigues(flame_pose.reshape(-1, 3)).reshape(batch, N_JOINTS, 3, 3)  # [B, 5, 3, 3]
        eye = torch.eye(3, dtype=flame_pose.dtype)
        pose_feature = (rot[:, 1:] - eye).reshape(batch, POSE_FEATURE_DIM)  # [B, 36]
        drive = torch.cat([expression, pose_feature], 1)  # [B, E + 36]
        if self.drive_rows is not None:
            drive = drive.index_select(1, self.drive_rows)
        points = self.rest_points + drive @ self.blend_basis  # [B, 3V + 15]
        v_posed = points[:, : 3 * n_v].reshape(batch, 3, n_v)
        joints = points[:, 3 * n_v:].reshape(batch, N_JOINTS, 3)
        world_rot, world_pos = forward_kinematics(rot, joints, self.parents)  # [B, 5, 3, 3], [B, 5, 3]
        # Joint k moves a rest point v to world_rot_k (v - J_k) + world_pos_k; blended by the skinning weights.
        skin_t = world_pos - torch.matmul(world_rot, joints.unsqueeze(3)).squeeze(3)  # [B, 5, 3]
        transform = torch.cat([world_rot, skin_t.unsqueeze(3)], 3).reshape(batch, 3 * N_JOINTS, 4)  # [B, 15, 4]
        homogeneous = torch.cat([v_posed, torch.ones_like(v_posed[:, :1])], 1)  # [B, 4, V]
        per_joint = torch.matmul(transform, homogeneous).reshape(batch, N_JOINTS, 3, n_v)  # [B, 5, 3, V]
        return (per_joint * self.lbs_weights).sum(1) + head_translation.unsqueeze(2)  # [B, 3, V]


__all__ = ["DeformationGraph", "hamilton_left_matrix"]
