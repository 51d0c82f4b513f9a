"""Quality of a reduced bundle's frames against the fp32 bundle's frames of the same audio, for `gt-bench sweep`.

Regions (docs/precision.md, "How the sweep measures"):
* head: pixels the fp32 frame covers (8-bit alpha >= 1), so the plain background does not inflate the score;
* mouth: the head pixels inside the box around the Gaussians that speech moves (those a jaw opening displaces by
  more than MOUTH_MOTION_FRACTION of the largest displacement), projected with the fp32 frame's deformation.

Metrics per region: 8-bit PSNR and SSIM (Gaussian window, the standard constants), each frame, then the minimum
(PSNR) and mean (SSIM) over the clip; and the translator's FLAME error (expression and jaw pose against the fp32
translator's on the same audio).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gaussiantalker.sdk.camera import Camera
from gaussiantalker.sdk.drive import FrameDrive
from gaussiantalker.sdk.image import psnr_db

MOUTH_JAW_OPENING = 0.25  # rad: the probe drive that finds the Gaussians speech moves
MOUTH_MOTION_FRACTION = 0.25  # of the largest displacement under that opening
MOUTH_BOX_PAD = 0.03  # of the frame's larger side, around the projected mouth Gaussians
SSIM_SIGMA, SSIM_RADIUS = 1.5, 5  # the usual 11-tap Gaussian window
SSIM_C1, SSIM_C2 = 0.01**2, 0.03**2  # for values in [0, 1]


def mouth_gaussians(head) -> np.ndarray:
    """Boolean [N]: the Gaussians of `head` (the fp32 TalkingHead) that a jaw opening moves (see the docstring)."""
    n_expr = head.driver.config.n_expr
    rest = head.frame_renderer.deform(FrameDrive.make(n_expr))["means"]
    opened = head.frame_renderer.deform(FrameDrive.make(n_expr, jaw_pose=[MOUTH_JAW_OPENING, 0.0, 0.0]))["means"]
    moved = np.linalg.norm(opened - rest, axis=1)
    return moved > MOUTH_MOTION_FRACTION * float(moved.max(initial=0.0))


def mouth_box(means: np.ndarray, camera: Camera) -> tuple[int, int, int, int]:
    """(row0, row1, col0, col1) pixel box around world points `means` [M, 3] in front of `camera`, padded."""
    p = means.astype(np.float64) @ camera.R.T + camera.t
    p = p[p[:, 2] > camera.near]
    if len(p) == 0:
        return 0, 0, 0, 0
    u = camera.fx * p[:, 0] / p[:, 2] + camera.cx
    v = camera.fy * p[:, 1] / p[:, 2] + camera.cy
    pad = MOUTH_BOX_PAD * max(camera.width, camera.height)
    row0, row1 = int(np.clip(np.floor(v.min() - pad), 0, camera.height)), int(np.clip(np.ceil(v.max() + pad), 0,
                                                                                     camera.height))
    col0, col1 = int(np.clip(np.floor(u.min() - pad), 0, camera.width)), int(np.clip(np.ceil(u.max() + pad), 0,
                                                                                    camera.width))
    return row0, row1, col0, col1


@dataclass
class ReferenceClip:
    """The fp32 bundle's frames of the clip with each frame's head and mouth masks, and its translator output."""

    frames: np.ndarray  # [T, H, W, 3] uint8
    head: np.ndarray  # [T, H, W] bool
    mouth: np.ndarray  # [T, H, W] bool
    expression: np.ndarray  # [T, n_expr]
    jaw: np.ndarray  # [T, 3]


def reference_clip(head, audio: np.ndarray, frames: np.ndarray, expression: np.ndarray,
                   jaw: np.ndarray) -> ReferenceClip:
    """The fp32 bundle's `frames`, expression and jaw of `audio`, with head and mouth masks made by the fp32
    `head` (alpha and deformation recomputed from the same drives)."""
    movers = mouth_gaussians(head)
    heads, mouths = [], []
    for drive in head.drives(audio, head.driver.config.sample_rate):
        alpha = head.render(drive, output="rgba")[..., 3] >= 1
        row0, row1, col0, col1 = mouth_box(head.frame_renderer.deform(drive)["means"][movers], head.camera)
        box = np.zeros_like(alpha)
        box[row0:row1, col0:col1] = True
        heads.append(alpha)
        mouths.append(alpha & box)
    return ReferenceClip(frames, np.stack(heads), np.stack(mouths), expression, jaw)


def _gaussian_blur(image: np.ndarray) -> np.ndarray:
    """Separable Gaussian filter of [H, W, C] float64 with reflected edges (SSIM's local means).

    Hand-written: SSIM libraries reduce over the whole image, and the sweep needs the per-pixel map to average
    over a region; this is the 11-tap filter those libraries use, nothing more.
    """
    taps = np.arange(-SSIM_RADIUS, SSIM_RADIUS + 1)
    kernel = np.exp(-0.5 * (taps / SSIM_SIGMA) ** 2)
    kernel /= kernel.sum()
    out = np.pad(image, ((SSIM_RADIUS, SSIM_RADIUS), (0, 0), (0, 0)), mode="reflect")
    out = sum(w * out[i:i + image.shape[0]] for i, w in enumerate(kernel))
    out = np.pad(out, ((0, 0), (SSIM_RADIUS, SSIM_RADIUS), (0, 0)), mode="reflect")
    return sum(w * out[:, i:i + image.shape[1]] for i, w in enumerate(kernel))


def ssim_map(reference: np.ndarray, test: np.ndarray) -> np.ndarray:
    """Per-pixel SSIM [H, W] of two uint8 [H, W, 3] frames (mean over the colour channels)."""
    x, y = reference.astype(np.float64) / 255.0, test.astype(np.float64) / 255.0  # float32 cancels in E[x^2] - E[x]^2
    mx, my = _gaussian_blur(x), _gaussian_blur(y)
    sxx = _gaussian_blur(x * x) - mx * mx
    syy = _gaussian_blur(y * y) - my * my
    sxy = _gaussian_blur(x * y) - mx * my
    ssim = ((2 * mx * my + SSIM_C1) * (2 * sxy + SSIM_C2)) / ((mx * mx + my * my + SSIM_C1) * (sxx + syy + SSIM_C2))
    return ssim.mean(axis=-1)


def region_scores(reference: np.ndarray, test: np.ndarray, regions: list[np.ndarray]) -> list[tuple[float, float]]:
    """(PSNR dB, mean SSIM) of two uint8 frames over each boolean region (inf and 1 for an empty region); the SSIM
    map is computed once, on the crop holding every region plus the window's reach."""
    covered = np.logical_or.reduce(regions)
    if not covered.any():
        return [(float("inf"), 1.0)] * len(regions)
    rows, cols = np.flatnonzero(covered.any(axis=1)), np.flatnonzero(covered.any(axis=0))
    crop = (slice(max(rows[0] - SSIM_RADIUS, 0), rows[-1] + SSIM_RADIUS + 1),
            slice(max(cols[0] - SSIM_RADIUS, 0), cols[-1] + SSIM_RADIUS + 1))
    ssim = ssim_map(reference[crop], test[crop])
    scores = []
    for region in regions:
        if not region.any():
            scores.append((float("inf"), 1.0))
            continue
        scores.append((psnr_db(reference[region], test[region]), float(ssim[region[crop]].mean())))
    return scores


def clip_quality(reference: ReferenceClip, frames: np.ndarray, expression: np.ndarray, jaw: np.ndarray) -> dict:
    """Head/mouth PSNR (min over frames) and SSIM (mean), and the translator's FLAME error, against `reference`."""
    if frames.shape != reference.frames.shape:
        raise ValueError(f"frames {frames.shape} do not match the reference's {reference.frames.shape}")
    head, mouth = [], []
    for index in range(len(frames)):
        head_scores, mouth_scores = region_scores(reference.frames[index], frames[index],
                                                  [reference.head[index], reference.mouth[index]])
        head.append(head_scores)
        mouth.append(mouth_scores)
    flame = np.concatenate([expression - reference.expression, jaw - reference.jaw], axis=1)
    return {
        "head_psnr_db": min(p for p, _ in head), "head_psnr_mean_db": float(np.mean([p for p, _ in head])),
        "head_ssim": float(np.mean([s for _, s in head])),
        "mouth_psnr_db": min(p for p, _ in mouth), "mouth_ssim": float(np.mean([s for _, s in mouth])),
        "flame_max_abs": float(np.abs(flame).max(initial=0.0)),
        "flame_rms": float(np.sqrt(np.mean(flame * flame))) if flame.size else 0.0,
    }
