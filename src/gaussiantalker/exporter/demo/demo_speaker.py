"""A deterministic demo speaker: the procedural FLAME-structured head, ~20k Gaussians coloured by face region,
a gentle head-pose track, and a translator trained briefly so the face follows the audio (docs/demo-speaker.md).

Not a trained photoreal avatar: it is a complete, real speaker of the same structure, so every code path of
export, verification and playback runs without the licensed FLAME file or any downloaded weights.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from gaussiantalker.sdk.camera import Camera
from gaussiantalker.sdk.config import SpeakerConfig
from gaussiantalker.sdk.numerics import SH_C0

from ..model.flame import FlameArrays
from ..model.speaker import Speaker
from .procedural_head import EXPRESSION_FIELDS, REGION_COLORS, make_demo_head
from .steps import INPAINT_STEPS, training_steps
from .train_translator import TrainSettings, train_demo_translator

DEMO_BACKGROUND = (0.93, 0.93, 0.95)
POSE_TRACK_FRAMES = 150
# tangential sigma = this * sqrt(area per Gaussian): neighbouring splats overlap enough that the surface is opaque
# like a trained head's (nothing behind it shows through at any yaw in +-90 degrees; measured in
# docs/demo-speaker.md, "Surface"); overdraw, and so llvmpipe's fill work, grows with its square.
TANGENT_COVERAGE = 1.0
OPACITY_LOGIT = 8.0  # sigmoid(8) = 0.9997, above the contract's 0.99 clamp: every surface splat is as opaque as allowed
CAMERA_DISTANCE = 0.85  # metres from the head's centre
NORMAL_FLATNESS = 0.2  # sigma along the triangle normal relative to the tangential sigma


def _face_geometry(head: FlameArrays) -> tuple[np.ndarray, np.ndarray]:
    """Template triangle areas [F] and mean edge lengths S [F] (the triangle frame's scale)."""
    v = head.v_template[head.faces]  # [F, 3, 3]
    e01, e02, e12 = v[:, 1] - v[:, 0], v[:, 2] - v[:, 0], v[:, 2] - v[:, 1]
    area = 0.5 * np.linalg.norm(np.cross(e01, e02), axis=1)
    mean_edge = (np.linalg.norm(e01, axis=1) + np.linalg.norm(e02, axis=1) + np.linalg.norm(e12, axis=1)) / 3
    return area, mean_edge


def _allocate(area: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    """Parent triangle per Gaussian (sorted): one per face first (no holes), the rest proportional to area."""
    faces = np.arange(area.shape[0])
    if count <= faces.size:  # systematic sampling of the cumulative area: evenly spread, so the surface stays closed
        steps = (np.arange(count) + rng.uniform()) * (area.sum() / count)
        return np.minimum(np.searchsorted(np.cumsum(area), steps), faces.size - 1)
    extra = rng.choice(faces, size=count - faces.size, p=area / area.sum())
    return np.sort(np.concatenate([faces, extra]))


def demo_camera(head: FlameArrays, size: int = 512) -> Camera:
    """Frontal portrait camera: the whole head and neck with a margin (0.85 m away, 24 degree vertical FOV)."""
    lo, hi = head.v_template.min(axis=0), head.v_template.max(axis=0)
    centre = (lo + hi) / 2
    return Camera.looking_at(eye=centre + [0.0, 0.0, CAMERA_DISTANCE], target=centre, up=[0, 1, 0],
                             width=size, height=size, fov_y_deg=24.0)


def demo_pose_track(frames: int = POSE_TRACK_FRAMES) -> np.ndarray:
    """[T, 6] head rotation (axis-angle) and translation: slow nods and turns, as a seated speaker moves."""
    t = np.arange(frames) / 25.0
    track = np.zeros((frames, 6), np.float32)
    track[:, 0] = 0.05 * np.sin(2 * np.pi * 0.23 * t)  # nod (pitch)
    track[:, 1] = 0.12 * np.sin(2 * np.pi * 0.11 * t + 0.5)  # turn (yaw)
    track[:, 2] = 0.03 * np.sin(2 * np.pi * 0.17 * t + 1.0)  # tilt (roll)
    track[:, 3] = 0.004 * np.sin(2 * np.pi * 0.09 * t)  # sway (x, metres)
    return track


def _stratified_barycentric(parent: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Barycentrics [N, 3] spreading a triangle's Gaussians evenly (jittered Fibonacci lattice), not in clumps."""
    order = np.argsort(parent, kind="stable")
    counts = np.bincount(parent)
    rank = np.empty_like(parent)
    rank[order] = np.arange(parent.size) - np.repeat(np.cumsum(counts) - counts, counts)[np.arange(parent.size)]
    k = counts[parent]
    golden = (np.sqrt(5.0) - 1.0) / 2.0
    u = np.where(k == 1, 1.0 / 3.0, (rank + 0.5) / k)
    v = np.where(k == 1, 1.0 / 3.0, np.mod(rank * golden + rng.uniform(0, 1, parent.size), 1.0))
    u, v = np.clip(u + rng.normal(0, 0.03, u.shape), 0.0, 1.0), np.clip(v, 0.0, 1.0)
    # Fold the unit square onto the triangle (u + v <= 1) and jitter slightly inside it.
    flip = u + v > 1.0
    u, v = np.where(flip, 1.0 - u, u), np.where(flip, 1.0 - v, v)
    return np.stack([1.0 - u - v, u, v], axis=1).astype(np.float32)


@torch.no_grad()
def _init_gaussians(speaker: Speaker, head: FlameArrays, parent: np.ndarray, rng: np.random.Generator) -> None:
    g = speaker.gaussians
    n, d = g.count, speaker.config.latent_dim
    area, mean_edge = _face_geometry(head)
    per_face = np.bincount(parent, minlength=area.shape[0])[parent]
    # Area each Gaussian covers: its share of its triangle, or, with fewer Gaussians than triangles (some triangles
    # get none), its share of the whole surface, so that the splats still close it.
    share = area[parent] / per_face if n >= area.shape[0] else np.full(n, area.sum() / n)
    tangent = TANGENT_COVERAGE * np.sqrt(share)
    scale_local = np.stack([tangent, NORMAL_FLATNESS * tangent, tangent], axis=1) / mean_edge[parent, None]

    colours = np.asarray(REGION_COLORS, np.float32)[head.regions[parent]]
    colours = np.clip(colours * rng.uniform(0.92, 1.06, (n, 1)), 0.0, 1.0)
    sh = np.zeros(tuple(g.sh.shape), np.float32)
    sh[:, 0] = (colours - 0.5) / SH_C0
    sh[:, 1:] = rng.normal(0.0, 0.015, sh[:, 1:].shape)

    g.barycentric.copy_(torch.from_numpy(_stratified_barycentric(parent, rng)))
    g.local_position.copy_(torch.from_numpy(rng.normal(0.0, 2e-4, (n, 3)).astype(np.float32)))
    g.local_rotation.copy_(torch.from_numpy(np.concatenate(
        [np.ones((n, 1)), rng.normal(0.0, 0.1, (n, 3))], axis=1).astype(np.float32)))
    g.log_scale.copy_(torch.from_numpy(np.log(scale_local).astype(np.float32)))
    g.opacity_logit.copy_(torch.from_numpy(rng.normal(OPACITY_LOGIT, 0.3, n).astype(np.float32)))
    g.sh.copy_(torch.from_numpy(sh))
    g.w_pos.copy_(torch.from_numpy(rng.normal(0.0, 1e-4, (n, 3, d)).astype(np.float32)))
    g.w_rot.copy_(torch.from_numpy(rng.normal(0.0, 0.02, (n, 4, d)).astype(np.float32)))
    g.w_color.copy_(torch.from_numpy(rng.normal(0.0, 0.02, (n, 3, d)).astype(np.float32)))


def make_demo_speaker(n_gaussians: int = 20_000, seed: int = 0, train_seconds: float | None = None,
                      progress: bool = True, config: SpeakerConfig | None = None,
                      reference_clip: bool = False, inpaint_seconds: float | None = None, *,
                      train_steps: int | None = None, inpaint_steps: int | None = None) -> tuple[Speaker, dict]:
    """Build the demo speaker; returns it with the translator's training metrics. `train_steps`: the translator's
    training steps at most (default TrainSettings.max_steps; 0: untrained). `reference_clip`: also its procedural
    reference video and masks (exporter/demo/clip.py), and an inpainting generator F trained on it for
    `inpaint_steps` (default INPAINT_STEPS; 0: none, so the runtime uses the OpenCV fallback); needs OpenGL. The
    same arguments give the same speaker on any machine: `train_seconds` and `inpaint_seconds`, the former time
    budgets, are read as step counts (exporter/demo/steps.py)."""
    if n_gaussians < 1:
        raise ValueError(f"a speaker needs at least one Gaussian, got {n_gaussians}")
    max_steps = TrainSettings().max_steps
    train_steps = training_steps(train_steps, train_seconds, max_steps, names=("train_steps", "train_seconds"),
                                 cap=max_steps)
    inpaint_steps = training_steps(inpaint_steps, inpaint_seconds, INPAINT_STEPS,
                                   names=("inpaint_steps", "inpaint_seconds"))
    config = config or SpeakerConfig()
    if not config.expression_names:  # the named fields, then the random local bumps (exporter/demo/procedural_head.py)
        names = EXPRESSION_FIELDS + tuple(f"bump_{k}" for k in range(len(EXPRESSION_FIELDS), config.n_expr))
        config = dataclasses.replace(config, expression_names=names[: config.n_expr])
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    head = make_demo_head(n_shape=config.n_shape, n_expr=config.n_expr, seed=seed)
    area, _ = _face_geometry(head)
    parent = _allocate(area, n_gaussians, rng)
    shape = rng.normal(0.0, 0.5, config.n_shape).astype(np.float32)
    speaker = Speaker(config, head, torch.from_numpy(shape), torch.from_numpy(parent), demo_camera(head),
                      DEMO_BACKGROUND, torch.from_numpy(demo_pose_track()))
    _init_gaussians(speaker, head, parent, rng)
    metrics = {"gaussians": n_gaussians, "vertices": head.n_vertices, "faces": head.n_faces}
    if train_steps > 0:
        metrics.update(train_demo_translator(speaker.translator, config.n_expr, seed=seed, progress=progress,
                                             settings=TrainSettings(max_steps=train_steps)))
    if reference_clip:
        metrics.update(_add_reference(speaker.eval(), inpaint_steps, seed, progress))
    return speaker.eval(), metrics


def _add_reference(speaker: Speaker, inpaint_steps: int, seed: int, progress: bool) -> dict:
    """Attach the procedural reference clip and (if `inpaint_steps` > 0) a trained F; returns their metrics."""
    from .clip import ClipComposer, make_demo_clip
    from .train_inpainter import train_demo_inpainter

    composer = ClipComposer(speaker)
    speaker.reference = make_demo_clip(speaker, composer)
    metrics = {"reference_frames": speaker.reference.layout.count, "reference_mb": speaker.reference.nbytes / 1e6}
    if inpaint_steps > 0:
        speaker.inpaint, inpainter_metrics = train_demo_inpainter(composer, steps=inpaint_steps, seed=seed,
                                                                  progress=progress)
        metrics.update(inpainter_metrics)
    composer.splatter.release()
    return metrics
