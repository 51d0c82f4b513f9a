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
from gaussiantalker.sdk.drive import FrameDrive, track_row
from gaussiantalker.sdk.flame_motion import TABLE_POSE_COLUMNS as MOTION_POSE_COLUMNS
from gaussiantalker.sdk.flame_motion import FlameMotion
from gaussiantalker.sdk.reference_clip import EncodedClip
from gaussiantalker.sdk.rig import FLAME_RIG

from .flame import FlameArrays
from .flame_lbs import FlameLayer
from .gaussians import BoundGaussians, LatentPoseMLP
from .inpainter import InpainterNet
from .reference_render import ReferenceRendering
from .translator import MotionTranslator


class Speaker(ReferenceRendering, nn.Module):
    """One trained speaker. Non-tensor state (camera, background, FLAME arrays) travels in the checkpoint too.

    Optional: `reference` (the original video clip the face is composited into, aligned with `pose_track`) and
    `inpaint` (the trained inpainting generator F; None: the runtime's non-learned fallback), docs/compositing.md.
    An imported avatar (docs/import.md) may have no trained translator (`translator=False`: `self.translator` is
    None), an attached audio-to-FLAME ONNX model instead (`audio_model`), and the motion it was tracked with
    (`motion_track` [T, n_expr + 18]: expression | flame_pose | head translation, `sdk.flame_motion`).
    """

    rig_kind = FLAME_RIG
    drive_inputs = ("expression", "flame_pose", "head_translation")

    def __init__(self, config: SpeakerConfig, flame: FlameArrays, shape: torch.Tensor, parent: torch.Tensor,
                 camera: Camera, background=(1.0, 1.0, 1.0), pose_track: torch.Tensor | None = None, *,
                 translator: bool = True, motion_track: torch.Tensor | None = None) -> None:
        super().__init__()
        self.config = config
        self.flame_arrays = flame
        self.flame = FlameLayer(flame)
        self.register_buffer("shape", torch.as_tensor(shape, dtype=torch.float32).reshape(config.n_shape))
        self.translator = (MotionTranslator(config.translator, config.n_expr, config.speaker_id) if translator
                           else None)
        self.latent_pose = LatentPoseMLP(config.latent_dim, config.latent_hidden)
        self.gaussians = BoundGaussians(torch.as_tensor(parent), torch.as_tensor(flame.faces), config.sh_degree,
                                        config.latent_dim, config.binding)
        self.camera = camera
        self.background = tuple(float(c) for c in background)
        self.pose_track = None if pose_track is None else torch.as_tensor(pose_track, dtype=torch.float32)
        self.motion_track = None if motion_track is None else torch.as_tensor(motion_track, dtype=torch.float32)
        if self.motion_track is not None and (self.motion_track.ndim != 2
                                              or self.motion_track.shape[1] != config.n_expr + MOTION_POSE_COLUMNS):
            raise ValueError(f"motion_track has shape {list(self.motion_track.shape)}, expected "
                             f"[T, {config.n_expr + MOTION_POSE_COLUMNS}] (expression | flame_pose | translation)")
        # An attached audio-to-FLAME ONNX model (serialised; exporter/imports/audio_model.py), or None.
        self.audio_model: bytes | None = None
        self.source: dict = {}
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
        if self.translator is None:
            raise ValueError("this speaker has no trained translator (an imported avatar): it is driven by FLAME "
                             "parameters or its motion track")
        return self.translator(audio)

    def motion_drive(self, index: int) -> FrameDrive:
        """Frame `index` of the motion track (played forth and back like every track) as a FrameDrive."""
        if self.motion_track is None:
            raise ValueError("this speaker has no motion track (only imported avatars ship one)")
        table = self.motion_track.numpy()
        return FlameMotion.from_table(table, self.config.fps).drive(track_row(table.shape[0], index))

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

