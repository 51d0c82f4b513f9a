"""An ARKit speaker: a blendshape rig driven by the 52 ARKit weights, with vertex-bound Gaussians (LAM avatars).

The torch reference of an imported avatar (docs/import.md): `deform` is what its deformation graph computes
(exporter/export/arkit_graph.py exports it with its constants folded) and `render` draws with the same pure-torch
reference rasterizer as a FLAME speaker.
"""

from __future__ import annotations

import copy

import torch
from torch import nn

from gaussiantalker.sdk.camera import Camera
from gaussiantalker.sdk.drive import BlendshapeDrive, HeadPose, track_row
from gaussiantalker.sdk.rig import ARKIT_RIG, ArkitRig

from .blendshape_rig import BlendshapeRig
from .reference_render import ReferenceRendering
from .vertex_binding import VertexBoundGaussians


class ArkitSpeaker(ReferenceRendering, nn.Module):
    """Rig + vertex-bound Gaussians + camera, and the motion the avatar ships (ARKit weights and head pose)."""

    rig_kind = ARKIT_RIG
    drive_inputs = ("blendshapes", "head_rotation", "head_translation")

    def __init__(self, config: ArkitRig, rig: BlendshapeRig, gaussians: VertexBoundGaussians, camera: Camera,
                 background=(1.0, 1.0, 1.0), pose_track: torch.Tensor | None = None,
                 motion_track: torch.Tensor | None = None, source: dict | None = None) -> None:
        super().__init__()
        if rig.morphs.shape[0] != len(config.blendshapes):
            raise ValueError(f"the rig has {rig.morphs.shape[0]} morph targets but the config names "
                             f"{len(config.blendshapes)} blendshapes")
        self.config = config
        self.rig = rig
        self.gaussians = gaussians
        self.camera = camera
        self.background = tuple(float(c) for c in background)
        self.pose_track = None if pose_track is None else torch.as_tensor(pose_track, dtype=torch.float32)
        self.motion_track = None if motion_track is None else torch.as_tensor(motion_track, dtype=torch.float32)
        self.source = dict(source or {})
        # An attached audio-to-ARKit ONNX model (serialised; exporter/imports/audio_model.py), or None.
        self.audio_model: bytes | None = None

    @property
    def n_blendshapes(self) -> int:
        return len(self.config.blendshapes)

    def deform(self, blendshapes: torch.Tensor, head_rotation: torch.Tensor, head_translation: torch.Tensor,
               camera_center: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """Drive -> world-space Gaussians: means [B,N,3], cov3d [B,N,6], rgb [B,N,3], opacity [N]."""
        vertices = self.rig.vertices(blendshapes)
        rotation = self.rig.head_rotation(head_rotation)
        return self.gaussians(vertices, rotation, self.rig.pivot, head_translation, camera_center)

    def motion_drive(self, index: int) -> BlendshapeDrive:
        """Frame `index` of the shipped motion: its weights (neutral without a motion track) and head pose (the
        pose track's, played forth and back like every track)."""
        weights = None
        if self.motion_track is not None:
            weights = self.motion_track[track_row(self.motion_track.shape[0], index)].numpy()
        pose = HeadPose.make()
        if self.pose_track is not None:
            row = self.pose_track[track_row(self.pose_track.shape[0], index)].numpy()
            pose = HeadPose.make(row[:3], row[3:])
        return BlendshapeDrive.make(weights, pose, self.config.blendshapes)

    def subset(self, index: torch.Tensor) -> ArkitSpeaker:
        """A copy holding the Gaussians `index` in that order: a Gaussian budget's survivors, or a new order."""
        kept = copy.deepcopy(self)
        old = self.gaussians
        new = VertexBoundGaussians(old.vertex[index], old.sh_degree, old.covariance)
        with torch.no_grad():
            for name, value in old.named_parameters():
                getattr(new, name).copy_(value[index])
        kept.gaussians = new
        return kept.eval()


__all__ = ["ArkitSpeaker"]
