"""How opaque a speaker's surface is, seen from around the head (docs/demo-speaker.md, "Surface").

For each yaw the torch reference renders the speaker twice: whole, and without its *hidden half* (Gaussians behind
the plane through the head's centre facing the camera whose triangle faces away from it). On a closed, opaque
head like a trained one, the two frames agree inside the silhouette; on a see-through one the hidden half shows,
and scene pruning (docs/scene.md) cannot remove it. Also measured: how many pixels saturate (T < 1/255) and how
many Gaussians a pixel blends before it stops (what early termination saves a tile splatter).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import torch
import torch.nn.functional as F

from gaussiantalker.exporter.model.rasterizer import render_reference
from gaussiantalker.exporter.model.speaker import Speaker
from gaussiantalker.sdk.drive import FrameDrive, HeadPose

SURFACE_YAWS_DEG = (-90, -60, -30, 0, 30, 60, 90)
# A Gaussian is hidden-half when its triangle's normal points away from the camera by more than this cosine (so
# triangles seen edge-on at the silhouette, legitimately visible, are not counted).
BACK_FACING_COS = -0.2
# Pixels this far inside the silhouette are "interior": the silhouette's own anti-aliased edge is left out.
INTERIOR_MARGIN_PX = 3
# A pixel "shows the hidden half" when removing it changes a channel by more than this (2 of 255 levels: beyond
# 8-bit rounding of two renders).
SEE_THROUGH_LEVELS = 2.0 / 255.0
SURFACE_JAW = 0.2  # rad: the mouth open, so the mouth pocket is measured too
SATURATED_T = 1.0 / 255.0  # a pixel is saturated when what lies behind it can change it by less than one level


@dataclass(frozen=True)
class SurfaceView:
    """The surface seen from one yaw (fractions are of the silhouette's interior pixels)."""

    yaw_deg: float
    interior_pixels: int
    see_through: float  # fraction changed by more than SEE_THROUGH_LEVELS when the hidden half is removed
    hidden_visible: int  # hidden-half Gaussians whose largest blend weight reaches 1/255
    hidden_gaussians: int
    saturated: float  # fraction with final T < SATURATED_T
    blend_depth_median: float  # Gaussians blended per interior pixel before the contract stops it (T_MIN)
    blend_depth_p90: float
    saturation_depth_median: float  # of those, Gaussians blended before the pixel saturates (T < SATURATED_T)

    def to_dict(self) -> dict:
        return asdict(self)


def _interior(transmittance: torch.Tensor) -> torch.Tensor:
    """Pixels of the silhouette (T < 0.5) at least INTERIOR_MARGIN_PX from its edge [H, W] bool."""
    outside = (transmittance >= 0.5).float()[None, None]
    k = 2 * INTERIOR_MARGIN_PX + 1
    near_outside = F.max_pool2d(outside, k, stride=1, padding=INTERIOR_MARGIN_PX)[0, 0] > 0
    return ~near_outside


def _hidden_half(speaker: Speaker, drive: FrameDrive, means: np.ndarray, eye: np.ndarray) -> np.ndarray:
    """[N] bool: behind the head centre's plane facing the camera, on a triangle facing away from it."""
    inputs = drive.graph_inputs()
    verts = speaker.vertices(*(torch.from_numpy(inputs[k]) for k in ("expression", "flame_pose",
                                                                       "head_translation")))[0].numpy()
    tri = verts[speaker.flame.faces.numpy()[speaker.gaussians.parent.numpy()]]  # [N, 3, 3]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
    to_eye = eye - means
    to_eye /= np.maximum(np.linalg.norm(to_eye, axis=1, keepdims=True), 1e-12)
    centre = means.mean(0)
    view = (eye - centre) / np.linalg.norm(eye - centre)
    return ((normal * to_eye).sum(1) < BACK_FACING_COS) & ((means - centre) @ view < 0)


@torch.no_grad()
def surface_view(speaker: Speaker, yaw_deg: float, resolution: int = 160) -> SurfaceView:
    """Measure the surface from one yaw (head turned about y, mouth open) at resolution² with the speaker's camera."""
    camera = speaker.camera.resized(resolution, resolution)
    drive = FrameDrive.make(speaker.config.n_expr, jaw_pose=[SURFACE_JAW, 0.0, 0.0],
                            head_pose=HeadPose.make([0.0, np.deg2rad(yaw_deg), 0.0]))
    eye = camera.center.astype(np.float64)
    means, cov3d, rgb, opacity = speaker.deform_drive(drive, torch.from_numpy(eye.astype(np.float32))[None])
    means, cov3d, rgb = means[0], cov3d[0], rgb[0]
    weight = torch.zeros(means.shape[0])
    depth = torch.zeros(2, resolution, resolution, dtype=torch.int64)
    image, trans = render_reference(means, cov3d, rgb, opacity, camera, (1.0, 1.0, 1.0), max_weight=weight,
                                    blend_count=depth)
    hidden = _hidden_half(speaker, drive, means.double().numpy(), eye)
    keep = torch.from_numpy(~hidden)
    front, _ = render_reference(means[keep], cov3d[keep], rgb[keep], opacity[keep], camera, (1.0, 1.0, 1.0))
    interior = _interior(trans)
    count = int(interior.sum())
    changed = (image - front).abs().amax(-1) > SEE_THROUGH_LEVELS
    blended = depth[0][interior].double().numpy() if count else np.zeros(1)
    to_saturation = depth[1][interior].double().numpy() if count else np.zeros(1)
    return SurfaceView(
        yaw_deg=float(yaw_deg),
        interior_pixels=count,
        see_through=float(changed[interior].double().mean()) if count else 0.0,
        hidden_visible=int((weight[torch.from_numpy(hidden)] >= 1.0 / 255.0).sum()),
        hidden_gaussians=int(hidden.sum()),
        saturated=float((trans[interior] < SATURATED_T).double().mean()) if count else 0.0,
        blend_depth_median=float(np.median(blended)),
        blend_depth_p90=float(np.percentile(blended, 90)),
        saturation_depth_median=float(np.median(to_saturation)),
    )


def measure_surface(speaker: Speaker, yaws_deg: tuple[float, ...] = SURFACE_YAWS_DEG, resolution: int = 160
                    ) -> list[SurfaceView]:
    """`surface_view` at each yaw."""
    return [surface_view(speaker, yaw, resolution) for yaw in yaws_deg]


def surface_table(views: list[SurfaceView]) -> str:
    """Markdown table of the views."""
    lines = ["| yaw | see-through | hidden Gaussians seen | saturated | Gaussians blended per pixel: to saturation, "
             "to the contract's stop (median / p90) |", "|---|---|---|---|---|"]
    for v in views:
        lines.append(f"| {v.yaw_deg:+.0f}° | {100 * v.see_through:.2f}% | {v.hidden_visible} of "
                     f"{v.hidden_gaussians} | {100 * v.saturated:.1f}% | {v.saturation_depth_median:.0f}; "
                     f"{v.blend_depth_median:.0f} / {v.blend_depth_p90:.0f} |")
    return "\n".join(lines)
