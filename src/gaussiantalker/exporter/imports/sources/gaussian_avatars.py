"""GaussianAvatars avatars (Qian et al., CVPR 2024) -> a FLAME speaker (docs/import.md, "GaussianAvatars avatars").

A trained avatar is a directory GaussianAvatars writes: `point_cloud/iteration_N/point_cloud.ply` (3DGS Gaussians
plus `binding_0`, each Gaussian's FLAME triangle, with position, scale and rotation in that triangle's frame) and
`flame_param.npz` beside it (the identity shape, the static offset and the tracked per-frame FLAME parameters).
With the user's own FLAME 2023 model (GaussianAvatars' teeth added, sources/gaussian_avatars_flame.py) it becomes
an ordinary speaker: binding "scaled_triangle" (docs/numerics.md), no latent-pose blendshapes, no
translator (an audio-to-FLAME ONNX model may be attached), and the tracked motion as its motion track.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from gaussiantalker.sdk.camera import Camera
from gaussiantalker.sdk.config import DEFAULT_FPS, SpeakerConfig
from gaussiantalker.sdk.drive import MAX_DRIVE_MAGNITUDE
from gaussiantalker.sdk.errors import CameraError, DriveError, ImportFormatError
from gaussiantalker.sdk.flame_motion import MOTION_KEYS, FlameMotion, parse_flame_motion, read_npz
from gaussiantalker.sdk.numerics import sh_coeff_count
from gaussiantalker.sdk.rig import SCALED_TRIANGLE_BINDING

from ...model.flame import FlameArrays
from ...model.speaker import Speaker
from ..formats.gaussian_ply import read_gaussian_ply
from ..portrait import CAMERA_CHOICES, head_box, portrait_camera
from .gaussian_avatars_flame import GA_N_EXPR, GA_N_SHAPE, fold_static_offset, load_gaussian_avatars_flame

PLY_NAME = "point_cloud.ply"
PARAMS_NAME = "flame_param.npz"
ITERATION_DIR = re.compile(r"iteration_(\d+)\Z")
# The source camera (`--camera source`): GaussianAvatars' viewer's vertical field of view, framing the first tracked
# frame's mesh (FLAME's frame: y up, the face toward +z) so that its height fills HEAD_FILL of the image.
CAMERA_FOV_DEG = 20.0
HEAD_FILL = 0.8
DEFAULT_RESOLUTION = 512
# An avatar without a trained translator has no latent-pose blendshapes: the smallest MLP, all zero, whose output
# the deformation graph leaves out (exporter/export/deform_graph.py).
NO_LATENT = {"latent_dim": 1, "latent_hidden": 1}


@dataclass
class GaussianAvatarsOptions:
    """Import choices: which training iteration (None: the last), the tracked motion's frame rate (the npz does
    not record one; it is resampled to the speaker's 25 fps), the frame size and the background colour."""

    iteration: int | None = None
    fps: float = DEFAULT_FPS
    resolution: int = DEFAULT_RESOLUTION
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)
    camera: str = "portrait"  # or "source": GaussianAvatars' viewer's framing


def find_avatar(path: str | os.PathLike, iteration: int | None = None) -> Path:
    """The `point_cloud/iteration_N` folder of a GaussianAvatars output (or that folder, or its PLY, given
    directly): the last iteration unless `iteration` is given; ImportFormatError saying what is missing."""
    path = Path(path)
    if path.is_file() and path.name == PLY_NAME:
        path = path.parent
    if not path.is_dir():
        raise ImportFormatError(f"{path}: not a GaussianAvatars output directory (no such directory)")
    if (path / PLY_NAME).is_file() and iteration is None:
        return path
    root = path / "point_cloud" if (path / "point_cloud").is_dir() else path
    found = {int(m.group(1)): d for d in root.iterdir() if d.is_dir() and (m := ITERATION_DIR.match(d.name))}
    if not found:
        raise ImportFormatError(f"{path}: no point_cloud/iteration_N/{PLY_NAME} (a GaussianAvatars output holds the "
                                f"trained Gaussians there)")
    if iteration is not None and iteration not in found:
        raise ImportFormatError(f"{path}: no iteration {iteration}; it has {', '.join(map(str, sorted(found)))}")
    chosen = found[max(found) if iteration is None else iteration]
    if not (chosen / PLY_NAME).is_file():
        raise ImportFormatError(f"{chosen}: {PLY_NAME} is missing")
    return chosen


def read_bound_gaussians(path: Path, n_faces: int):
    """The PLY's Gaussians and each one's triangle (`binding_0`, stored as float): ImportFormatError naming the
    field when it is missing, not a whole number, or outside the mesh's [0, n_faces)."""
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise ImportFormatError(f"{path}: cannot read the PLY: {exc.strerror or exc}") from None
    cloud = read_gaussian_ply(data, str(path))
    if "binding_0" not in cloud.extra:
        raise ImportFormatError(f"{path}: the PLY's vertex element lacks field binding_0 (each Gaussian's FLAME "
                                "triangle); a plain 3DGS PLY is not a GaussianAvatars avatar")
    if cloud.extra["binding_0"].dtype.kind not in "biuf":
        raise ImportFormatError(f"{path}: the PLY's binding_0 must be numbers (each Gaussian's triangle)")
    raw = np.asarray(cloud.extra["binding_0"], np.float64)
    bad = np.flatnonzero(~np.isfinite(raw) | (raw != np.round(raw)) | (raw < 0) | (raw >= n_faces))
    if bad.size:
        raise ImportFormatError(f"{path}: binding_0 of Gaussian {bad[0]} is {raw[bad[0]]}, not a triangle of the "
                                f"mesh [0, {n_faces}) ({bad.size} Gaussians are bound outside it)")
    rest = cloud.f_rest.shape[1]
    if rest + 1 not in [sh_coeff_count(d) for d in range(4)]:
        raise ImportFormatError(f"{path}: {3 * rest} f_rest fields is not SH degree 0-3 (0, 9, 24 or 45)")
    return cloud, raw.astype(np.int64)


def read_flame_params(path: Path, n_vertices: int, fps: float) -> tuple[np.ndarray, np.ndarray, FlameMotion]:
    """(shape [300], static offset [V, 3], tracked motion) from flame_param.npz, never unpickling; ImportFormatError
    naming the key that is missing or mis-shaped."""
    if not path.is_file():
        raise ImportFormatError(f"{path.parent}: {PARAMS_NAME} is missing (GaussianAvatars saves it beside "
                                f"{PLY_NAME})")
    arrays = read_npz(path, ImportFormatError, "an npz of FLAME parameters",
                      ("shape", "static_offset", *(key for key, _ in MOTION_KEYS)))
    for key in ("shape", "static_offset"):
        if key in arrays and arrays[key].dtype.kind not in "biuf":
            raise ImportFormatError(f"{path}: '{key}' holds {arrays[key].dtype.str} values, not numbers")
    shape = np.asarray(arrays.get("shape", np.zeros(0)), np.float64).reshape(-1)
    if "shape" not in arrays or shape.shape != (GA_N_SHAPE,) or not np.isfinite(shape).all():
        got = list(np.shape(arrays["shape"])) if "shape" in arrays else "missing"
        raise ImportFormatError(f"{path}: 'shape' must be {GA_N_SHAPE} finite FLAME shape coefficients, got {got}")
    if not _bounded(shape):
        raise ImportFormatError(f"{path}: 'shape' holds {np.abs(shape).max():g}; FLAME shape coefficients lie "
                                f"within {MAX_DRIVE_MAGNITUDE:g}")
    offset = np.asarray(arrays.get("static_offset", np.zeros((1, n_vertices, 3))), np.float64)
    if offset.ndim not in (2, 3) or offset.shape[-1] != 3 or offset.size != 3 * n_vertices or not _bounded(offset):
        raise ImportFormatError(f"{path}: 'static_offset' has shape {list(offset.shape)}, expected [1, {n_vertices}, "
                                f"3] (FLAME's 5023 vertices and GaussianAvatars' 120 teeth vertices), finite within "
                                f"{MAX_DRIVE_MAGNITUDE:g} m")
    try:
        motion = parse_flame_motion(arrays, fps, str(path))
    except DriveError as exc:
        raise ImportFormatError(str(exc)) from None
    if motion.n_expr != GA_N_EXPR:
        raise ImportFormatError(f"{path}: 'expr' has {motion.n_expr} coefficients per frame; GaussianAvatars tracks "
                                f"{GA_N_EXPR}")
    return shape.astype(np.float32), offset.reshape(n_vertices, 3), motion


def _bounded(values: np.ndarray) -> bool:
    """Whether every value is finite and within MAX_DRIVE_MAGNITUDE, the bound on every FLAME parameter."""
    return bool(np.isfinite(values).all() and (values.size == 0 or np.abs(values).max() <= MAX_DRIVE_MAGNITUDE))


def first_frame_vertices(speaker: Speaker) -> np.ndarray:
    """The mesh [V, 3] of the first tracked frame."""
    with torch.no_grad():
        drive = speaker.motion_drive(0)
        inputs = drive.graph_inputs()
        return speaker.vertices(*(torch.from_numpy(inputs[k]) for k in speaker.drive_inputs))[0].numpy()


def head_vertices(arrays: FlameArrays) -> np.ndarray:
    """Which vertices FLAME's skinning moves mostly (over half their weight) with the neck joint and the joints
    below it (jaw, eyes): the head, not the base of the neck, which follows the root."""
    weights = arrays.lbs_weights.astype(np.float64)
    return weights[:, 1:].sum(axis=1) > weights[:, 0]


def first_frame_head_box(speaker: Speaker) -> tuple[np.ndarray, np.ndarray]:
    """The head's box (docs/import.md, "Portrait framing") of the first tracked frame's head vertices (all of them
    when the skinning puts none on the head)."""
    vertices = first_frame_vertices(speaker)
    on_head = head_vertices(speaker.flame_arrays)
    return head_box(vertices[on_head] if on_head.any() else vertices)


def avatar_camera(speaker: Speaker, resolution: int) -> Camera:
    """GaussianAvatars' viewer's framing (`--camera source`): a front camera (from +z, y up) on the first tracked
    frame's mesh, its height HEAD_FILL of the image."""
    vertices = first_frame_vertices(speaker)
    low, high = vertices.min(0), vertices.max(0)
    centre = (low + high) / 2.0
    half_height = max(float(high[1] - low[1]), 1e-6) / 2.0 / HEAD_FILL
    distance = half_height / np.tan(np.radians(CAMERA_FOV_DEG) / 2.0) + float(high[2] - centre[2])
    eye = centre + np.array([0.0, 0.0, distance])
    return Camera.looking_at(eye, centre, (0.0, 1.0, 0.0), resolution, resolution, CAMERA_FOV_DEG)


def import_gaussian_avatars(path: str | os.PathLike, flame: str | os.PathLike | FlameArrays,
                            options: GaussianAvatarsOptions | None = None) -> Speaker:
    """Read a GaussianAvatars avatar with the user's FLAME model (`flame`: its .pkl or npz, or arrays already
    loaded with the teeth) into a Speaker; ImportFormatError / CheckpointError naming what is wrong."""
    options = options or GaussianAvatarsOptions()
    if options.camera not in CAMERA_CHOICES:
        raise ValueError(f"camera must be one of {', '.join(CAMERA_CHOICES)}, got {options.camera!r}")
    folder = find_avatar(path, options.iteration)
    arrays = flame if isinstance(flame, FlameArrays) else load_gaussian_avatars_flame(flame)
    shape, offset, motion = read_flame_params(folder / PARAMS_NAME, arrays.n_vertices, options.fps)
    cloud, binding = read_bound_gaussians(folder / PLY_NAME, arrays.n_faces)
    arrays = fold_static_offset(arrays, offset)
    sh_degree = [sh_coeff_count(d) for d in range(4)].index(cloud.f_rest.shape[1] + 1)
    config = SpeakerConfig(n_shape=GA_N_SHAPE, n_expr=GA_N_EXPR, sh_degree=sh_degree, binding=SCALED_TRIANGLE_BINDING,
                           **NO_LATENT)
    motion = motion.at_fps(config.fps)
    pose_track = np.concatenate([motion.flame_pose[:, :3], motion.head_translation], axis=1)
    placeholder = Camera.looking_at((0, 0, 1), (0, 0, 0), (0, 1, 0), options.resolution, options.resolution,
                                    CAMERA_FOV_DEG)
    speaker = Speaker(config, arrays, torch.from_numpy(shape), torch.from_numpy(binding), placeholder,
                      options.background, torch.from_numpy(pose_track), translator=False,
                      motion_track=torch.from_numpy(motion.table))
    _set_gaussians(speaker, cloud)
    low, high = first_frame_head_box(speaker)
    try:
        speaker.camera = avatar_camera(speaker, options.resolution) if options.camera == "source" else \
            portrait_camera(low, high, options.resolution, options.resolution)
    except CameraError as exc:
        raise ImportFormatError(f"{folder}: no default camera frames the first tracked frame's head ({exc})") from None
    speaker.source = {"format": "gaussian-avatars", "iteration": folder.name, "motion_fps": float(options.fps),
                      "motion_frames": len(motion), "camera": options.camera,
                      "head_box": [low.tolist(), high.tolist()]}
    return speaker.eval()


@torch.no_grad()
def _set_gaussians(speaker: Speaker, cloud) -> None:
    """The PLY's triangle-local attributes into the speaker's Gaussians: centroid binding (barycentric 1/3), raw
    quaternions (normalised where used), SH as stored, every speaker blendshape and the latent MLP zero."""
    g = speaker.gaussians
    g.barycentric.fill_(1.0 / 3.0)
    g.local_position.copy_(torch.from_numpy(cloud.xyz))
    g.local_rotation.copy_(torch.from_numpy(cloud.rotation))
    g.log_scale.copy_(torch.from_numpy(cloud.log_scale))
    g.opacity_logit.copy_(torch.from_numpy(cloud.opacity))
    g.sh.copy_(torch.from_numpy(np.concatenate([cloud.f_dc[:, None], cloud.f_rest], axis=1)))
    for weight in (g.w_pos, g.w_rot, g.w_color, *speaker.latent_pose.parameters()):
        weight.zero_()


__all__ = ["GaussianAvatarsOptions", "avatar_camera", "find_avatar", "first_frame_head_box", "head_vertices",
           "import_gaussian_avatars", "read_bound_gaussians", "read_flame_params"]
