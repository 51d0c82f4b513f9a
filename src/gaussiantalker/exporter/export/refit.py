"""Refit a Gaussian budget's survivors: the kept Gaussians' colours, opacities and sizes fitted to the full speaker's
frames, so that they draw what the dropped ones did (docs/precision.md, "Refit").

A budget keeps the Gaussians that contribute most (exporter/export/prune.py) and leaves holes where the dropped ones
drew: on a photo-real avatar, whose Gaussians are translucent layers, 60% of them alone lose 9 dB of head PSNR. Each
step draws one frame of the measurement drives through the differentiable reference rasterizer, with the alpha cut
the bundle will be drawn with, and takes one Adam step on the L1 distance to the full speaker's frame. The drives
are the budget's own (a driven clip and a head-pose sweep), never the frames a bench scores.
"""

from __future__ import annotations

import copy
import warnings

import numpy as np
import torch

from gaussiantalker.sdk.numerics import ALPHA_MIN
from gaussiantalker.sdk.progress import progress_bar

from ..model.arkit_speaker import ArkitSpeaker
from ..model.rasterizer import render_reference
from ..model.speaker import Speaker
from .presets import check_refit_steps
from .prune import measurement_drives

# Frame side the fit draws at: a 512x512 frame's texture is kept at this size (measured on LAM's p2-1 at 60% of its
# Gaussians, 200 steps: 46.8 dB min against 38.5 unfitted at 512², docs/precision.md), at a quarter of the cost.
REFIT_RESOLUTION = 256
REFIT_CLIP_FRAMES = 40  # driven-clip frames beside the 3x3 pose sweep (measurement_drives)
# Adam step sizes per fitted attribute (those of 3D Gaussian Splatting's training): colour coefficients, opacity
# logits and log-scales. Positions and rotations stay where the rig binds them.
LEARNING_RATES = {"sh": 2.5e-3, "opacity_logit": 0.05, "log_scale": 5e-3}


def refit_kept(full: Speaker | ArkitSpeaker, kept: Speaker | ArkitSpeaker, steps: int, *,
               alpha_min: float = ALPHA_MIN, resolution: int = REFIT_RESOLUTION, progress: bool = False
               ) -> Speaker | ArkitSpeaker:
    """A copy of `kept` (a subset of `full`'s Gaussians) whose colours, opacities and scales are fitted for `steps`
    steps to `full`'s frames, drawn with the alpha cut `alpha_min`. Deterministic: the frames' order is seeded.
    Should a step go non-finite (it has not been seen), the fit stops and the unfitted Gaussians are kept."""
    steps = check_refit_steps(steps)
    fitted = copy.deepcopy(kept)
    if steps == 0:
        return fitted
    camera = full.camera.resized(resolution, resolution)
    center = torch.from_numpy(camera.center.astype(np.float32))[None]
    background = torch.as_tensor(full.background, dtype=torch.float32)
    drives = measurement_drives(full, REFIT_CLIP_FRAMES)
    gaussians = fitted.gaussians
    names = [name for name in LEARNING_RATES if hasattr(gaussians, name)]
    start = {name: getattr(gaussians, name).detach().clone() for name in names}
    for parameter in fitted.parameters():  # the rig, translator and MLPs stay as they are
        parameter.requires_grad_(False)
    for name in names:
        getattr(gaussians, name).requires_grad_(True)
    optimiser = torch.optim.Adam([{"params": [getattr(gaussians, name)], "lr": LEARNING_RATES[name]}
                                  for name in names], eps=1e-15)
    order = np.random.default_rng(0).permutation(np.resize(np.arange(len(drives)), steps))
    bar = progress_bar(total=len(drives) + steps, desc="refitting kept Gaussians", unit="step", disable=not progress)
    try:
        with torch.no_grad():
            targets = []
            for drive in drives:
                targets.append(full.render(drive, camera))
                bar.update()
        for index in order:
            means, cov3d, rgb, opacity = fitted.deform_drive(drives[index], center)
            image, _ = render_reference(means[0], cov3d[0], rgb[0], opacity, camera, background, alpha_min=alpha_min)
            loss = (image - targets[index]).abs().mean()
            if not torch.isfinite(loss):
                break
            optimiser.zero_grad(set_to_none=True)
            loss.backward()
            optimiser.step()
            bar.update()
            bar.set_postfix_str(f"L1 {loss.item():.2e}", refresh=False)
    finally:
        bar.close()
        for name in names:
            getattr(gaussians, name).requires_grad_(False)
    if not all(torch.isfinite(getattr(gaussians, name)).all() for name in names) or not torch.isfinite(loss):
        warnings.warn("the Gaussian budget's refit went non-finite; the kept Gaussians are exported unfitted",
                      RuntimeWarning, stacklevel=2)
        with torch.no_grad():
            for name, value in start.items():
                getattr(gaussians, name).copy_(value)
    return fitted.eval()


__all__ = ["LEARNING_RATES", "REFIT_CLIP_FRAMES", "REFIT_RESOLUTION", "refit_kept"]
