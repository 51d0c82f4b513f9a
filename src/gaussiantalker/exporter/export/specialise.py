"""Scene-specialised export: leave out of a speaker what its scene never uses (docs/scene.md).

`specialise` resolves a scene against a speaker and decides every removal by measurement:
* the drive entries the scene (or, for an audio scene, the translator) never moves: their expression and
  pose-corrective rows leave the FLAME basis (exact: those inputs are always 0);
* the latent pose code γ = W_γ(ψ) of the poses the scene reaches: it spans a low-dimensional affine subspace when
  few joint axes move, so the speaker blendshapes are stored projected onto it (exact up to a measured residual);
* Gaussians whose blend weight is below ALPHA_MIN at every pixel of a dense sweep of the scene (scene_sweep.py);
* SH bands: each Gaussian's higher bands refitted by the lower ones over the view directions the scene gives it
  (ridge-conditioned, `_sh_refit`), when no Gaussian's colour moves by more than SH_REFIT_BOUND (a pixel is a
  convex blend of Gaussian colours, so no pixel moves by more), or down to the export settings' SH degree;
* the vertices no kept Gaussian's triangle needs (DeformationGraph(vertex_subset=True)), and, for a flame-driven
  scene, the translator graph (bundle_export.py).
Each removal is reported with its reason, the bytes it saves (stored as float32) and the per-frame work it saves.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field, replace

import numpy as np
import torch

from gaussiantalker.sdk.camera import Camera
from gaussiantalker.sdk.config import FLAME_JOINTS
from gaussiantalker.sdk.numerics import ALPHA_MIN, sh_coeff_count
from gaussiantalker.sdk.scene import Scene, SceneError

from ..model.flame import POSE_FEATURE_DIM
from ..model.speaker import Speaker
from ..model.splat_math import sh_basis
from .prune import prune_speaker
from .scene_sweep import measure_sweep, sweep_drives

# Largest change of any Gaussian's colour (0..1 units, per channel, over the sweep's view directions) an SH refit
# may make: one 8-bit level, so no pixel moves by more than that either (before rounding).
SH_REFIT_BOUND = 1.0 / 255
# The latent subspace keeps the fewest directions whose residual, on poses sampled between the fitting ones, is
# at most this fraction of γ's own spread over the scene (float32 rounding of γ is ~1e-7 of it).
LATENT_RESIDUAL_REL = 1e-5
LATENT_SAMPLES = 4096
# SH refit conditioning (`_sh_refit`): ridge weights tried in order (per sweep frame, relative to the unit-scale
# SH basis), and how far a refitted coefficient may exceed the speaker's largest in bands 1-3.
RIDGE_WEIGHTS = (0.0, 1e-6, 1e-5, 1e-4, 1e-3, 1e-2, 1e-1, 1.0)
REFIT_RANGE = 2.0
FLOAT_BYTES = 4


@dataclass
class Removal:
    """One specialisation: what it removed, why, the float32 bytes it saves and the per-frame work it saves."""

    name: str
    removed: str
    reason: str
    bytes_saved: int = 0
    work_saved: str = ""


@dataclass
class Specialisation:
    """A speaker compiled for a scene: the reduced torch speaker (pruned, SH refitted: the verification reference
    inside the scene) and the deformation graph's scene options."""

    scene: Scene  # as compiled: explicit camera and ranges, the expression/joint axes that really move
    camera: Camera
    speaker: Speaker
    drive_allowed: np.ndarray  # [E + POSE_FEATURE_DIM] bool: rows of the FLAME basis the scene can drive
    latent_mean: torch.Tensor | None = None  # [D]
    latent_basis: torch.Tensor | None = None  # [D, r] orthonormal
    sh_degree: int = 3
    removals: list[Removal] = field(default_factory=list)
    sweep_frames: int = 0

    @property
    def has_translator(self) -> bool:
        return self.scene.driver == "audio"


def translator_outputs(speaker: Speaker) -> tuple[np.ndarray, np.ndarray]:
    """(expression [E], jaw [3]) bool: the translator outputs that can be non-zero (an output whose row of the
    final linear layer, weight and bias, is exactly zero is always 0)."""
    head = speaker.translator.motion_decoder.head
    live = ((head.weight.detach().abs().amax(1) > 0) | (head.bias.detach().abs() > 0)).numpy()
    n_expr = speaker.config.n_expr
    return live[:n_expr], live[n_expr:]


def _pose_feature_rows(ranges: np.ndarray) -> np.ndarray:
    """[POSE_FEATURE_DIM] bool: entries of (R_j - I) (joints neck..right eye, row-major 3x3) that can be non-zero.
    A joint held at 0 has R = I; one turning about a single axis k changes only the entries off row and column k."""
    rows = np.zeros((len(FLAME_JOINTS) - 1, 3, 3), bool)
    for joint in range(1, len(FLAME_JOINTS)):
        moving = np.flatnonzero(np.any(ranges[joint] != 0.0, axis=1))
        if len(moving) == 1:
            k = moving[0]
            rows[joint - 1] = True
            rows[joint - 1, k, :] = rows[joint - 1, :, k] = False
        elif len(moving) > 1:
            rows[joint - 1] = True
    return rows.reshape(POSE_FEATURE_DIM)


def _effective_scene(speaker: Speaker, scene: Scene) -> tuple[Scene, Camera, list[Removal]]:
    """The scene as it will be compiled: pose range from the track if asked, explicit camera, and for an audio
    scene only the expression coefficients and jaw axes the translator can move."""
    removals = []
    if scene.pose_from_track:
        if speaker.pose_track is None:
            raise SceneError("scene head.from_track is true but the speaker has no pose track")
        scene = scene.with_pose_range(speaker.pose_track.numpy())
    camera = scene.resolve_camera(speaker.camera)
    scene = scene.with_camera(camera)
    n_expr = speaker.config.n_expr
    allowed = scene.expression_allowed(n_expr)
    joints = dict(scene.joints)
    if scene.driver == "audio":
        expression_live, jaw_live = translator_outputs(speaker)
        missing = np.flatnonzero(expression_live & ~allowed)
        if missing.size:
            raise SceneError(f"scene drive.expression leaves out coefficient {missing[0]}, which the translator "
                             f"drives: an audio scene must allow every coefficient the translator outputs "
                             f"({', '.join(map(str, np.flatnonzero(expression_live)))})")
        silent = np.flatnonzero(allowed & ~expression_live)
        silent_axes = [axis for axis in range(3) if not jaw_live[axis] and joints["jaw"][axis] != (0.0, 0.0)]
        allowed &= expression_live
        joints["jaw"] = tuple((0.0, 0.0) if not jaw_live[axis] else joints["jaw"][axis] for axis in range(3))
        if silent.size or silent_axes:
            parts = ([f"expression coefficients {_ranges_text(silent)}"] if silent.size else []) + (
                [f"jaw axes {', '.join('xyz'[a] for a in silent_axes)}"] if silent_axes else [])
            removals.append(Removal("translator-silent drives", " and ".join(parts),
                                    "the translator's output rows for them are exactly zero, so an audio scene "
                                    "never moves them"))
    expression = None if bool(allowed.all()) else tuple(int(i) for i in np.flatnonzero(allowed))
    return replace(scene, expression=expression, joints=joints), camera, removals


def _ranges_text(ids: np.ndarray) -> str:
    """0, 2-5, 9 for sorted ids."""
    parts, start = [], None
    for i, value in enumerate(ids):
        if start is None:
            start = value
        if i + 1 == len(ids) or ids[i + 1] != value + 1:
            parts.append(str(start) if start == value else f"{start}-{value}")
            start = None
    return ", ".join(parts)


def _latent_subspace(speaker: Speaker, ranges: np.ndarray) -> tuple[torch.Tensor, torch.Tensor, float] | None:
    """(mean [D], basis [D, r], residual) of γ over the scene's joint ranges, or None when no r < D holds it."""
    box = ranges[1:].reshape(-1, 2)  # [12, 2] ψ = neck, jaw, eyes
    moving = np.flatnonzero(box[:, 0] != box[:, 1])
    dim = speaker.config.latent_dim
    if moving.size == 0:
        return None

    def samples(seed: int) -> torch.Tensor:
        rng = np.random.default_rng(seed)
        unit = rng.random((LATENT_SAMPLES, moving.size))
        if moving.size == 1:  # one axis: an even grid, the ends included
            unit = np.linspace(0.0, 1.0, LATENT_SAMPLES)[:, None]
        psi = np.tile(box[:, 0], (LATENT_SAMPLES, 1))
        psi[:, moving] = box[moving, 0] + unit * (box[moving, 1] - box[moving, 0])
        with torch.no_grad():
            return speaker.latent_pose(torch.from_numpy(psi).float()).double()

    fit, check = samples(0), samples(1)
    mean = fit.mean(0)
    _, _, vh = torch.linalg.svd(fit - mean, full_matrices=False)
    spread = float((check - mean).abs().max())
    for rank in range(1, dim):
        basis = vh[:rank].T  # [D, r]
        centred = check - mean
        residual = float((centred - centred @ basis @ basis.T).abs().max())
        if residual <= LATENT_RESIDUAL_REL * max(spread, 1e-30):
            return mean.float(), basis.float(), residual
    return None


def _sh_refit(sh: torch.Tensor, directions: torch.Tensor, degree: int) -> tuple[torch.Tensor, float]:
    """sh [N, K, 3] refitted to bands up to `degree` over each Gaussian's view directions [F, N, 3]: (new sh
    [N, K, 3], the largest colour change over those directions).

    Per Gaussian, the colour the dropped bands add is fitted by the kept bands in least squares. Over the narrow
    cone of directions a scene gives a Gaussian, the kept bands are nearly collinear, and a plain fit cancels huge
    coefficients against each other: exact in float64, but a quantised codec or fp16 destroys it. So the fit is
    ridge-regularised (bands 1+; the constant band is free), with the smallest weight from RIDGE_WEIGHTS that keeps
    every refitted coefficient within REFIT_RANGE times the largest the speaker has in those bands. At any weight the
    fit is never worse than dropping the bands, in least squares over the directions (x = 0 is a candidate)."""
    full = sh.shape[1]
    kept = sh_coeff_count(degree)
    basis = sh_basis(directions.double(), int(round(full ** 0.5)) - 1).permute(1, 0, 2)  # [N, F, K]
    target = basis[..., kept:] @ sh[:, kept:].double()  # [N, F, 3] what the dropped bands add
    low = basis[..., :kept]  # [N, F, kept]
    gram, rhs = low.transpose(1, 2) @ low, low.transpose(1, 2) @ target  # [N, kept, kept], [N, kept, 3]
    limit = REFIT_RANGE * float(sh[:, 1:].abs().max())
    for weight in RIDGE_WEIGHTS:
        ridge = torch.eye(kept, dtype=torch.float64) * weight * low.shape[1]
        ridge[0, 0] = 0.0
        solution = torch.linalg.solve(gram + ridge, rhs)  # [N, kept, 3]
        refit = sh.double().clone()
        refit[:, :kept] += solution
        if kept == 1 or float(refit[:, 1:kept].abs().max()) <= limit:
            break
    refit[:, kept:] = 0.0
    change = float((low @ solution - target).abs().max())
    return refit.float(), change


def specialise(speaker: Speaker, scene: Scene, progress: bool = False, sh_degree_cap: int | None = None
               ) -> Specialisation:
    """Measure what `scene` lets `speaker` leave out (see the module docstring); the speaker is not modified.
    `sh_degree_cap`: the SH degree the export settings keep (the refit then goes at least that far down)."""
    speaker = speaker.eval()
    scene, camera, removals = _effective_scene(speaker, scene)
    n_expr, count = speaker.config.n_expr, speaker.gaussians.count
    ranges = scene.joint_ranges_rad()
    expression_allowed = scene.expression_allowed(n_expr)
    drive_allowed = np.concatenate([expression_allowed, _pose_feature_rows(ranges)])
    n_vertices = speaker.flame_arrays.n_vertices
    columns = 3 * n_vertices + 3 * len(FLAME_JOINTS)
    flame_basis = torch.cat([speaker.flame.exprdirs.reshape(-1, n_expr).T, speaker.flame.posedirs], 0)
    driven = flame_basis.abs().amax(1) > 0  # rows that are zero anyway are dropped by every export
    dropped = int((driven & ~torch.from_numpy(drive_allowed)).sum())
    if dropped:
        fixed = [name for name in FLAME_JOINTS[1:] if name not in scene.joints]
        removals.append(Removal(
            "fixed drives", f"{dropped} of {int(driven.sum())} FLAME basis rows (expression and pose correctives)",
            "the scene keeps those expression coefficients at 0 and "
            + (f"{', '.join(fixed)} still, " if fixed else "") + "jaw/joint axes outside its ranges at 0",
            dropped * columns * FLOAT_BYTES, f"{dropped * columns / 1e6:.2f} M multiply-adds"))

    specialised = copy.deepcopy(speaker).eval()
    latent = _latent_subspace(speaker, ranges)
    latent_dim = speaker.config.latent_dim
    if latent is not None:
        mean, basis, residual = latent
        rank = basis.shape[1]
        saved = (latent_dim - rank) * 10 * count
        removals.append(Removal(
            "latent subspace", f"latent pose code {latent_dim} -> {rank} dimensions (speaker blendshapes "
            f"[{latent_dim}, 10 N] -> [{rank}, 10 N])",
            f"over the scene's joint ranges γ stays in a {rank}-dimensional affine subspace (residual "
            f"{residual:.1e}, measured between the fitting poses)", saved * FLOAT_BYTES,
            f"{saved / 1e6:.2f} M multiply-adds (before pruning)"))
    else:
        mean = basis = None

    drives = sweep_drives(speaker, ranges, np.asarray(scene.translation_m), expression_allowed,
                          scene.expression_sigma)
    max_weight, directions = measure_sweep(speaker, drives, camera, progress=progress)
    keep = max_weight >= ALPHA_MIN
    kept = int(keep.sum())
    if kept == 0:
        raise SceneError(f"no Gaussian reaches a pixel anywhere in the scene ({len(drives)} frames swept): check "
                         "the scene's camera (it must look at the head) and its ranges")
    if 0 < kept < count:
        specialised = prune_speaker(specialised, kept, max_weight)
        directions = directions[:, keep]
        rank = latent_dim if basis is None else basis.shape[1]
        # Per Gaussian: blendshape columns (10 per latent dimension), bias (10), SH bands 1-3 (45), log-scale and
        # barycentric (3 + 3), reference size, opacity and parent triangle (1 each).
        per_gaussian = 10 * rank + 10 + 45 + 3 + 3 + 3
        removals.append(Removal(
            "pruned Gaussians", f"{count - kept} of {count} Gaussians",
            f"their blend weight stays below 1/255 at every pixel of {len(drives)} frames sweeping the scene",
            (count - kept) * per_gaussian * FLOAT_BYTES, f"{100 * (count - kept) / count:.1f}% of the per-Gaussian "
            "deformation, sort and draw"))

    degree = full = speaker.gaussians.sh_degree
    cap = full if sh_degree_cap is None else min(int(sh_degree_cap), full)
    for lower in range(cap + 1):
        if lower == full:
            break
        refit, change = _sh_refit(specialised.gaussians.sh.detach(), directions, lower)
        bounded = change <= SH_REFIT_BOUND
        if not (bounded or lower == cap):
            continue
        with torch.no_grad():
            specialised.gaussians.sh.copy_(refit)
        dropped_k = sh_coeff_count(full) - sh_coeff_count(lower)
        why = (f"over the view directions of the sweep no Gaussian's colour moves by more than {change * 255:.2f}/255 "
               f"(bound {SH_REFIT_BOUND * 255:.0f}/255)" if bounded else
               f"the export settings keep SH degree {cap}: refitted over the scene's view directions instead of "
               f"truncated (never worse in least squares; largest colour change {change * 255:.1f}/255)")
        removals.append(Removal(
            "SH degree", f"SH band{'s' if lower + 1 < full else ''} {lower + 1}{f'-{full}' if lower + 1 < full else ''}"
            f" ({dropped_k} coefficients x 3 per Gaussian), refitted into bands 0-{lower}", why,
            dropped_k * 3 * kept * FLOAT_BYTES, f"{dropped_k * 3 * kept / 1e6:.2f} M multiply-adds"))
        degree = lower
        break

    faces = torch.as_tensor(speaker.flame_arrays.faces).long()
    used = torch.unique(faces[specialised.gaussians.parent])
    unused = n_vertices - int(used.numel())
    if unused:
        rows = int((driven & torch.from_numpy(drive_allowed)).sum())
        # Per vertex: 3 basis columns and 3 rest coordinates per kept row, 5 skinning weights; per frame the
        # basis product, the 5 joint transforms (4 x 3 each) and the blend.
        removals.append(Removal(
            "vertex subset", f"{unused} of {n_vertices} vertices", "no kept Gaussian's triangle uses them",
            unused * (3 * rows + 3 + len(FLAME_JOINTS)) * FLOAT_BYTES,
            f"{unused * (3 * rows + 15 * len(FLAME_JOINTS)) / 1e6:.2f} M multiply-adds"))
    if scene.driver == "flame":
        params = sum(p.numel() for p in speaker.translator.parameters())
        removals.append(Removal("translator graph", f"the translator ({params / 1e6:.2f} M parameters)",
                                "a flame-driven scene gets FLAME parameters from the app, never audio",
                                params * FLOAT_BYTES, "the audio -> FLAME pass"))
    return Specialisation(scene, camera, specialised, drive_allowed, mean, basis, degree, removals, len(drives))


def format_removals(removals: list[Removal]) -> str:
    """The exporter's report: one block per specialisation."""
    if not removals:
        return "scene specialisation: nothing to leave out"
    lines = ["scene specialisation:"]
    for r in removals:
        saved = f"{r.bytes_saved / 1e6:.2f} MB (fp32)" if r.bytes_saved else "-"
        lines.append(f"  {r.name}: removed {r.removed}; saves {saved}" + (f", {r.work_saved} per frame"
                                                                         if r.work_saved else ""))
        lines.append(f"      why: {r.reason}")
    return "\n".join(lines)


__all__ = ["Removal", "SH_REFIT_BOUND", "Specialisation", "format_removals", "specialise", "translator_outputs"]
