"""The torch GaussianTalker speaker: translator + FLAME layer + latent-pose MLP + bound Gaussians.

This is the reference the exported bundle is verified against: `deform` is what the deformation graph computes
(exporter/export/deform_graph.py exports it with its constants folded) and `render` draws with the pure-torch reference
rasterizer.
"""

from __future__ import annotations

import torch
from torch import nn

from gaussiantalker.sdk.camera import Camera
from gaussiantalker.sdk.config import POSE_DIM, SpeakerConfig
from gaussiantalker.sdk.reference_clip import EncodedClip
from gaussiantalker.sdk.rig import FLAME_RIG

from .flame import FlameArrays, FlameLayer
from .gaussians import BoundGaussians, LatentPoseMLP
from .inpainter import InpainterNet
from .reference_render import ReferenceRendering
from .translator import MotionTranslator


class Speaker(ReferenceRendering, nn.Module):
    """One trained speaker. Non-tensor state (camera, background, FLAME arrays) travels in the checkpoint too.

    Optional: `reference` (the original video clip the face is composited into, aligned with `pose_track`) and
    `inpaint` (the trained inpainting generator F; None: the runtime's non-learned fallback), docs/compositing.md.
    """

    rig_kind = FLAME_RIG
    drive_inputs = ("expression", "flame_pose", "head_translation")

    def __init__(self, config: SpeakerConfig, flame: FlameArrays, shape: torch.Tensor, parent: torch.Tensor,
                 camera: Camera, background=(1.0, 1.0, 1.0), pose_track: torch.Tensor | None = None) -> None:
        super().__init__()
        self.config = config
        self.flame_arrays = flame
        self.flame = FlameLayer(flame)
        self.register_buffer("shape", torch.as_tensor(shape, dtype=torch.float32).reshape(config.n_shape))
        self.translator = MotionTranslator(config.translator, config.n_expr, config.speaker_id)
        self.latent_pose = LatentPoseMLP(config.latent_dim, config.latent_hidden)
        self.gaussians = BoundGaussians(torch.as_tensor(parent), torch.as_tensor(flame.faces), config.sh_degree,
                                        config.latent_dim)
        self.camera = camera
        self.background = tuple(float(c) for c in background)
        self.pose_track = None if pose_track is None else torch.as_tensor(pose_track, dtype=torch.float32)
        self.reference: EncodedClip | None = None
        self.inpaint: InpainterNet | None = None
        self.refresh_rest_geometry()

    @torch.no_grad()
    def refresh_rest_geometry(self) -> None:
        """Recompute what the Gaussians derive from the rest mesh (call after editing FLAME buffers or shape)."""
        zeros = torch.zeros(1, self.config.n_expr), torch.zeros(1, POSE_DIM), torch.zeros(1, 3)
        self.gaussians.set_rest_vertices(self.vertices(*zeros)[0])

    def translate(self, audio: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """audio [B, S] (S a multiple of samples_per_frame) -> expression [B, T, n_expr], jaw_pose [B, T, 3]."""
        return self.translator(audio)

    def vertices(self, expression: torch.Tensor, flame_pose: torch.Tensor, head_translation: torch.Tensor
                 ) -> torch.Tensor:
        """FLAME mesh (with teeth) for a batch of frames -> [B, V, 3]."""
        shape = self.shape.unsqueeze(0).expand(expression.shape[0], -1)
        return self.flame(shape, expression, flame_pose, head_translation)

    def deform(self, expression: torch.Tensor, flame_pose: torch.Tensor, head_translation: torch.Tensor,
               camera_center: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """Drive -> world-space Gaussians: means [B,N,3], cov3d [B,N,6], rgb [B,N,3], opacity [N]."""
        vertices = self.vertices(expression, flame_pose, head_translation)
        gamma = self.latent_pose(flame_pose[:, 3:])
        return self.gaussians(vertices, gamma, camera_center)

