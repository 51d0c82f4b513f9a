"""A blendshape rig: a rest mesh, morph targets named by ARKit blendshape, and a rigid head bone (docs/import.md).

x_v = x̄_v + sum_k w_k Δ_k,v in the rig's rest frame; the head bone then turns and moves the whole head about its
pivot (`vertex_binding.rigid_head`). LAM's skin.glb holds such a rig: its morph targets, and a skeleton of which
only the head bone moves Gaussians in LAM's renderer.
"""

from __future__ import annotations

import torch
from torch import nn

from .flame_lbs import rodrigues


class BlendshapeRig(nn.Module):
    """Rest vertices [V, 3], morph deltas [K, V, 3] (K = the rig's blendshape names), head pivot [3]."""

    def __init__(self, rest: torch.Tensor, morphs: torch.Tensor, pivot: torch.Tensor) -> None:
        super().__init__()
        if rest.ndim != 2 or rest.shape[1] != 3 or morphs.ndim != 3 or morphs.shape[1:] != rest.shape:
            raise ValueError(f"rig shapes do not fit: rest {list(rest.shape)} (want [V, 3]), morphs "
                             f"{list(morphs.shape)} (want [K, V, 3])")
        self.register_buffer("rest", rest.float().clone())
        self.register_buffer("morphs", morphs.float().clone())
        self.register_buffer("pivot", pivot.float().reshape(3).clone())

    @property
    def n_vertices(self) -> int:
        return int(self.rest.shape[0])

    def vertices(self, weights: torch.Tensor) -> torch.Tensor:
        """Morphed rest-frame vertices [B, V, 3] for weights [B, K]."""
        return self.rest + torch.einsum("bk,kvc->bvc", weights, self.morphs)

    def head_rotation(self, rotvec: torch.Tensor) -> torch.Tensor:
        """Axis-angle head rotations [B, 3] -> matrices [B, 3, 3] (FLAME's `rodrigues`, finite at 0)."""
        return rodrigues(rotvec)


__all__ = ["BlendshapeRig"]
