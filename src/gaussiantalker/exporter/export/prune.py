"""Gaussian budget: keep the N Gaussians that contribute most to the frames a speaker is driven through.

A Gaussian's contribution is its summed blend weight alpha_i * T_i over every pixel of a set of frames: a driven
clip plus a head-pose sweep (docs/precision.md). Measured, never guessed: the frames are drawn by the reference
rasterizer, and because a frame's colour is sum_i alpha_i T_i rgb_i (+ T * background, which does not depend on
rgb), the summed weight of Gaussian i is d(sum of a colour channel over the frame) / d(rgb_i), one backward pass.
"""

from __future__ import annotations

import copy

import numpy as np
import torch

from gaussiantalker.sdk.drive import BlendshapeDrive, FrameDrive, HeadPose
from gaussiantalker.sdk.progress import progress_bar

from ..export.probes import driven_clip, motion_clip, plays_audio
from ..model.arkit_speaker import ArkitSpeaker
from ..model.gaussians import BoundGaussians
from ..model.rasterizer import render_reference
from ..model.speaker import Speaker

# Head rotations (radians, axis-angle about x then y) of the pose sweep, beside the driven clip's own poses.
SWEEP_ANGLES = (-0.3, 0.0, 0.3)
MEASURE_RESOLUTION = 192  # contributions are pixel-area weighted, so a small frame measures them well
MEASURE_FRAMES = 12


def measurement_drives(speaker: Speaker | ArkitSpeaker, frames: int = MEASURE_FRAMES
                       ) -> list[FrameDrive | BlendshapeDrive]:
    """A driven clip (speech for a FLAME speaker, its motion for an ARKit one or an imported FLAME avatar; the pose
    track applied) plus a 3x3 sweep of head pitch and yaw with the mouth open."""
    if isinstance(speaker, ArkitSpeaker):
        drives: list = motion_clip(speaker, frames, seed=7)
        open_mouth = {"jawOpen": 0.6} if "jawOpen" in speaker.config.blendshapes else None
        return drives + [BlendshapeDrive.make(open_mouth, HeadPose.make([pitch, yaw, 0.0]), speaker.config.blendshapes)
                         for pitch in SWEEP_ANGLES for yaw in SWEEP_ANGLES]
    drives = driven_clip(speaker, frames, seed=7)[1] if plays_audio(speaker) else motion_clip(speaker, frames, seed=7)
    jaw_open = np.array([0.25, 0.0, 0.0], np.float32)
    for pitch in SWEEP_ANGLES:
        for yaw in SWEEP_ANGLES:
            pose = HeadPose.make([pitch, yaw, 0.0])
            drives.append(FrameDrive.make(speaker.config.n_expr, jaw_pose=jaw_open, head_pose=pose))
    return drives


def gaussian_contributions(speaker: Speaker | ArkitSpeaker, drives: list, resolution: int = MEASURE_RESOLUTION,
                           progress: bool = False) -> torch.Tensor:
    """[N] summed blend weight of each Gaussian over the frames of `drives` (pixels of a resolution² frame)."""
    camera = speaker.camera.resized(resolution, resolution)
    center = torch.from_numpy(camera.center.astype(np.float32))[None]
    total = torch.zeros(speaker.gaussians.count, dtype=torch.float64)
    for drive in progress_bar(drives, desc="measuring contributions", unit="frame", disable=not progress):
        with torch.no_grad():
            means, cov3d, rgb, opacity = speaker.deform_drive(drive, center)
        probe = rgb[0].clone().requires_grad_(True)
        image, _ = render_reference(means[0], cov3d[0], probe, opacity, camera, (0.0, 0.0, 0.0))
        (gradient,) = torch.autograd.grad(image[..., 0].sum(), probe)
        total += gradient[:, 0].double()
    return total


def budget_count(budget: float, count: int) -> int:
    """Gaussians kept for a budget: a fraction of them (0 < budget <= 1) or a number (> 1), at most all."""
    if budget <= 0:
        raise ValueError(f"gaussian budget must be positive, got {budget}")
    kept = round(budget * count) if budget <= 1 else int(budget)
    return max(1, min(count, kept))


def prune_speaker(speaker: Speaker | ArkitSpeaker, keep: int, contributions: torch.Tensor) -> Speaker:
    """A copy of `speaker` with only its `keep` largest contributors (in their original order)."""
    order = torch.argsort(contributions, descending=True, stable=True)[:keep]
    return gaussian_subset(speaker, torch.sort(order).values)


def gaussian_subset(speaker: Speaker | ArkitSpeaker, index: torch.Tensor) -> Speaker | ArkitSpeaker:
    """A copy of `speaker` holding its Gaussians `index` in that order (a subset, or a permutation of them all)."""
    if isinstance(speaker, ArkitSpeaker):
        return speaker.subset(index)
    pruned = copy.deepcopy(speaker)
    old = speaker.gaussians
    faces = torch.as_tensor(speaker.flame_arrays.faces)
    new = BoundGaussians(old.parent[index], faces, old.sh_degree, speaker.config.latent_dim, binding=old.binding)
    with torch.no_grad():
        for name, value in old.named_parameters():
            getattr(new, name).copy_(value[index])
        new.rest_scale.copy_(old.rest_scale[index])
    pruned.gaussians = new
    return pruned.eval()


def apply_budget(speaker: Speaker | ArkitSpeaker, budget: float, progress: bool = False) -> Speaker:
    """`speaker` with its Gaussian budget applied (itself when the budget keeps every Gaussian)."""
    keep = budget_count(budget, speaker.gaussians.count)
    if keep >= speaker.gaussians.count:
        return speaker
    contributions = gaussian_contributions(speaker, measurement_drives(speaker), progress=progress)
    return prune_speaker(speaker, keep, contributions)


__all__ = ["apply_budget", "budget_count", "gaussian_contributions", "gaussian_subset", "measurement_drives",
           "prune_speaker"]
