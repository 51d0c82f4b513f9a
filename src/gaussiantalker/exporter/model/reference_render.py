"""What every torch speaker does with one drive, whatever its rig: the deformation and the reference frame."""

from __future__ import annotations

import numpy as np
import torch

from gaussiantalker.sdk.camera import Camera
from gaussiantalker.sdk.rig import check_drive_rig

from .rasterizer import render_reference


class ReferenceRendering:
    """Mixin of a speaker with `rig_kind`, `drive_inputs` (its deformation graph's drive inputs, in `deform`'s
    argument order), `deform(*drive, camera_center)`, `camera` and `background`."""

    rig_kind: str
    drive_inputs: tuple[str, ...]

    def deform_drive(self, drive, camera_center: torch.Tensor):
        """`deform` of one validated drive of this speaker's rig (batch of one)."""
        check_drive_rig(self.rig_kind, drive.rig)
        inputs = drive.graph_inputs()
        return self.deform(*(torch.from_numpy(inputs[name]) for name in self.drive_inputs), camera_center)

    @torch.no_grad()
    def render(self, drive, camera: Camera | None = None, background=None, *,
               transmittance: bool = False) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
        """Reference frame [H, W, 3] float32 (C + T * background) for one validated drive (and its transmittance
        T [H, W] with `transmittance=True`)."""
        camera = camera or self.camera
        center = torch.from_numpy(camera.center.astype(np.float32))[None]
        means, cov3d, rgb, opacity = self.deform_drive(drive, center)
        bg = torch.as_tensor(self.background if background is None else background, dtype=torch.float32)
        image, trans = render_reference(means[0], cov3d[0], rgb[0], opacity, camera, bg)
        return (image, trans) if transmittance else image


__all__ = ["ReferenceRendering"]
