"""The `deform` ONNX graph of an ARKit speaker: `ArkitSpeaker.deform` with its constants folded at export.

Folded once (each exact up to float32 rounding; docs/deformation.md, "ARKit speakers"):
* the bound vertex, the offset and the head pivot into one rest point per Gaussian, x̄_v(i) + o_i - p, so a frame's
  centre is R (rest + w · morphs) + p + t;
* the morph targets into one [K, 3S] matrix (`morph_basis`) over the vertices whose targets are stored, component-major
  like the FLAME graph's bases, leaving out blendshapes whose morph target is zero everywhere (tongueOut in LAM
  avatars); a vertex that moves as the midpoint of two stored ones (a subdivided mesh's edge vertex,
  exporter/export/morph_midpoints.py) is derived from them in the graph instead of stored;
* covariance, colour and opacity depend on no input when the covariance is static and the SH degree 0 (LAM): the
  graph computes them from the stored quaternions, log-scales and SH, and onnxruntime folds them at load.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from gaussiantalker.sdk.numerics import SH_C0, sh_coeff_count

from ..model.arkit_speaker import ArkitSpeaker
from ..model.flame_lbs import rodrigues
from ..model.splat_math import quat_to_rotmat, sh_basis
from .morph_midpoints import find_midpoints, morph_rows

ARKIT_DEFORM_INPUTS = ["blendshapes", "head_rotation", "head_translation", "camera_center"]
_COV_ENTRIES = (0, 1, 2, 4, 5, 8)  # packed (xx, xy, xz, yy, yz, zz) in a row-major 3x3


class ArkitDeformationGraph(nn.Module):
    """Per-frame ARKit drive -> world-space Gaussians (means [B,N,3], cov3d [B,N,6], rgb [B,N,3], opacity [N]);
    same inputs, outputs and meaning as `ArkitSpeaker.deform`. `sh_degree` keeps the SH bands up to that degree;
    `midpoints` derives the rig's midpoint vertices from their ends (where the rig knows its triangles)."""

    def __init__(self, speaker: ArkitSpeaker, *, sh_degree: int | None = None, midpoints: bool = False) -> None:
        super().__init__()
        speaker = speaker.eval()
        g, rig = speaker.gaussians, speaker.rig
        self.n_gaussians = n = g.count
        self.sh_degree = g.sh_degree if sh_degree is None else min(int(sh_degree), g.sh_degree)
        self.head_covariance = g.covariance == "head"
        with torch.no_grad():
            vertex = g.vertex
            rest = (rig.rest.double()[vertex] + g.offset.double() - rig.pivot.double())  # [N, 3]
            derived = (find_midpoints(rig.rest.numpy(), rig.morphs.numpy(), rig.faces.numpy())
                       if midpoints and rig.faces is not None else np.zeros((0, 3), np.int64))
            rows = morph_rows(vertex.numpy(), derived)
            self.n_sources = len(rows.sources)
            self.kept_prefix = rows.kept_prefix
            morphs = rig.morphs.double()[:, torch.from_numpy(rows.sources)]  # [K, S, 3]
            basis = morphs.permute(0, 2, 1).reshape(morphs.shape[0], 3 * self.n_sources)  # [K, 3S] component-major
            keep = basis.abs().amax(1) > 0
            keep[0] |= not bool(keep.any())  # an all-zero rig keeps one row, so no tensor has a zero-size axis
            self.register_buffer("drive_rows", None if bool(keep.all()) else torch.nonzero(keep).reshape(-1))
            self.register_buffer("rest_points", rest.T.contiguous().float())  # [3, N]
            self.register_buffer("morph_basis", basis[keep].float().contiguous())  # [K kept, 3S]
            self.register_buffer("midpoint_ends", torch.from_numpy(rows.ends) if len(rows.derived) else None)
            identity = np.array_equal(rows.gaussian_rows, np.arange(n))
            self.register_buffer("gaussian_rows", None if identity or rows.kept_prefix is not None
                                 else torch.from_numpy(rows.gaussian_rows))
            self.register_buffer("pivot", rig.pivot.float().reshape(1, 3, 1).clone())
            self.register_buffer("rotation", g.rotation.detach().T.contiguous())  # [4, N] (w, x, y, z)
            self.register_buffer("log_scale", g.log_scale.detach().T.contiguous())  # [3, N]
            self.register_buffer("opacity", torch.sigmoid(g.opacity_logit.detach()).clone())  # [N]
            self.register_buffer("sh_dc", g.sh.detach()[:, 0].T.contiguous())  # [3, N]
            self.register_buffer("cov_entries", torch.tensor(_COV_ENTRIES))
            k = sh_coeff_count(self.sh_degree)
            if self.sh_degree > 0:
                self.register_buffer("sh_rest", g.sh.detach()[:, 1:k].permute(2, 1, 0).contiguous())  # [3, K-1, N]

    def forward(self, blendshapes: torch.Tensor, head_rotation: torch.Tensor, head_translation: torch.Tensor,
                camera_center: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        batch, n = blendshapes.shape[0], self.n_gaussians
        weights = blendshapes if self.drive_rows is None else blendshapes.index_select(1, self.drive_rows)
        points = self.rest_points + self._morphed(weights @ self.morph_basis, batch, n)  # x + o - p  [B, 3, N]
        rotation = rodrigues(head_rotation)  # [B, 3, 3]
        means = torch.matmul(rotation, points) + self.pivot + head_translation.unsqueeze(2)  # [B, 3, N]

        local = quat_to_rotmat(self.rotation, dim=0)  # [3, 3, N]
        m = local * torch.exp(self.log_scale).unsqueeze(0)  # R̄ diag(s)  [3, 3, N]
        if self.head_covariance:
            m = torch.matmul(rotation, m.reshape(3, 3 * n)).reshape(batch, 3, 3, n)  # R R̄ diag(s)
        else:
            m = m.unsqueeze(0).expand(batch, -1, -1, -1)
        cov = (m.unsqueeze(2) * m.unsqueeze(1)).sum(3).reshape(batch, 9, n)  # m mᵀ row-major [B, 9, N]
        cov3d = cov.index_select(1, self.cov_entries)  # [B, 6, N]

        rgb = (SH_C0 * self.sh_dc).unsqueeze(0).expand(batch, -1, -1)  # [B, 3, N]
        if self.sh_degree > 0:
            basis = sh_basis(means - camera_center.unsqueeze(2), self.sh_degree, dim=1, skip_dc=True)
            rgb = rgb + (basis.unsqueeze(1) * self.sh_rest).sum(2)
        rgb = torch.clamp_min(rgb + 0.5, 0.0)
        return means.transpose(1, 2), cov3d.transpose(1, 2), rgb.transpose(1, 2), self.opacity

    def _morphed(self, stored: torch.Tensor, batch: int, n: int) -> torch.Tensor:
        """Each Gaussian's morph offset [B, 3, N] from the stored vertices' [B, 3S]: derived (midpoint) vertices as
        the mean of their two ends, then each Gaussian's row (docs/deformation.md, "Midpoint vertices")."""
        offsets = stored.reshape(batch, 3, self.n_sources)
        if self.midpoint_ends is None:
            return offsets if self.gaussian_rows is None else offsets.index_select(2, self.gaussian_rows)
        first, second = self.midpoint_ends
        derived = 0.5 * (offsets.index_select(2, first) + offsets.index_select(2, second))
        if self.gaussian_rows is not None:
            return torch.cat([offsets, derived], 2).index_select(2, self.gaussian_rows)
        if self.kept_prefix == self.n_sources:
            return torch.cat([offsets, derived], 2)
        return torch.cat([offsets[:, :, :self.kept_prefix], derived], 2)


def arkit_deform_example(speaker: ArkitSpeaker) -> tuple[tuple, dict]:
    """Example inputs (a batch of 2) and the dynamic batch axis of the ARKit deformation graph's export."""
    batch = 2
    args = (torch.zeros(batch, speaker.n_blendshapes), torch.zeros(batch, 3), torch.zeros(batch, 3),
            torch.zeros(batch, 3))
    dim = torch.export.Dim("batch", min=1, max=4096)
    return args, {name: {0: dim} for name in ARKIT_DEFORM_INPUTS}


__all__ = ["ARKIT_DEFORM_INPUTS", "ArkitDeformationGraph", "arkit_deform_example"]
