"""LAM avatars (aigc3d/LAM's export for its web renderer) -> an ARKit speaker (docs/import.md, "LAM avatars").

What the web renderer draws, and so what this importer reproduces: Gaussian i at skin.glb's mesh vertex i, moved
by the weighted morph targets, plus offset.ply's xyz i, carried rigidly by the head bone only (the neck and
body bones move the mesh, never the Gaussians); its covariance stays the rest one; f_dc is RGB (clamped to 0..1,
as the renderer stores colours in 8 bits), opacity a logit, scale a log. The renderer scales some incoming ARKit
weights before use (LAM_WEIGHT_SCALE): folded into the morph targets, so the same weights give the same face.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from gaussiantalker.sdk.camera import Camera
from gaussiantalker.sdk.errors import CameraError, DriveError, ImportFormatError
from gaussiantalker.sdk.motion import parse_motion
from gaussiantalker.sdk.numerics import SH_C0
from gaussiantalker.sdk.progress import progress_bar
from gaussiantalker.sdk.rig import ARKIT_BLENDSHAPES, ArkitRig

from ...model.arkit_speaker import ArkitSpeaker
from ...model.blendshape_rig import BlendshapeRig
from ...model.vertex_binding import VertexBoundGaussians
from ..formats.avatar_zip import read_avatar_zip
from ..formats.gaussian_ply import read_gaussian_ply
from ..formats.gltf import (
    MAX_DEPTH,
    Gltf,
    animation_names,
    as_dict,
    as_list,
    clip_duration,
    load_glb,
    node_names,
    parents,
    parse_json,
    read_accessor,
    sampled_world,
    world_matrix,
)
from ..portrait import CAMERA_CHOICES, head_box, portrait_camera

REQUIRED_MEMBERS = ("skin.glb", "offset.ply")
OPTIONAL_MEMBERS = ("animation.glb", "vertex_order.json", "bsData.json")
HEAD_BONE = "head"
LAM_FPS = 30
# The web renderer multiplies these incoming weights before use (its motion config; every offset is 0).
LAM_WEIGHT_SCALE = {"jawOpen": 1.2, "mouthClose": 0.2, "mouthDimpleLeft": 1.3, "mouthDimpleRight": 1.3,
                    "mouthFrownLeft": 1.3, "mouthFrownRight": 1.3, "mouthFunnel": 1.3, "mouthLeft": 1.3,
                    "mouthLowerDownLeft": 0.7, "mouthLowerDownRight": 0.7, "mouthPressLeft": 1.3,
                    "mouthPressRight": 1.3, "mouthRight": 1.3, "mouthRollLower": 1.3, "mouthRollUpper": 1.3,
                    "mouthShrugLower": 1.3, "mouthShrugUpper": 0.1, "mouthStretchLeft": 1.3, "mouthStretchRight": 1.3,
                    "mouthUpperUpLeft": 1.3, "mouthUpperUpRight": 1.3}
# The renderer's fixed camera (position, pitch about x, vertical field of view) and the head it frames: the centre
# and height of LAM's sample avatar's Gaussian bounds (1st to 99th percentile), docs/import.md "Camera".
LAM_CAMERA_EYE = (0.0, 1.8, 1.0)
LAM_CAMERA_PITCH_DEG = -10.0
LAM_CAMERA_FOV_DEG = 50.0
LAM_REFERENCE_CENTER = (-0.0013, 1.6523, 0.0151)
LAM_REFERENCE_HEIGHT = 0.2936
# The portrait camera frames the Gaussians on vertices the head bone moves (not the neck and chest) when at least this
# share of them are (LAM's: 95%); else all of them.
MIN_HEAD_SHARE = 0.1
# Opacity logit of a Gaussian whose 8-bit opacity is 0 in the renderer: sigmoid 2e-9, far below the contract's
# 1/255 alpha floor, so it is never drawn either.
OPACITY_ZERO_LOGIT = -20.0
# The bind pose must be the rest pose: head bone world x inverse bind = identity to this tolerance.
BIND_TOLERANCE = 1e-4
# Bounds on what a (possibly hostile) avatar may ask of the importer (docs/untrusted-input.md, "LAM avatars"): the
# head mesh's vertices (its morph targets take 52 x 24 bytes per vertex), coordinates in metres (mesh, morphs,
# offsets), and the head-pose clip's length (sampled at 30 fps, frame by frame).
MAX_VERTICES = 1 << 20
MAX_COORDINATE = 1e4
MAX_CLIP_SECONDS = 600.0


@dataclass
class LamOptions:
    """Import choices: which animation clip is the head-pose track, whether to fold the renderer's weight scales,
    how covariances follow the head, the head bone's name, the default camera (portrait framing or the renderer's
    own)."""

    clip: str | None = None  # None: the first clip named *idle*, else the first clip
    renderer_weight_scale: bool = True
    renderer_colours: bool = True  # colours and opacities in the renderer's 8 bits
    covariance: str = "static"
    head_bone: str = HEAD_BONE
    camera: str = "portrait"


def rotation_vector(matrix: np.ndarray) -> np.ndarray:
    """Axis-angle [3] of a rotation matrix [3, 3] (orthonormalised first), accurate at every angle: the axis from
    the antisymmetric part below 90 degrees, from the symmetric part (sign from the antisymmetric) above."""
    u, _, vt = np.linalg.svd(matrix)
    rotation = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    cos = np.clip((np.trace(rotation) - 1.0) / 2.0, -1.0, 1.0)
    angle = float(np.arccos(cos))
    twice_sin_axis = np.array([rotation[2, 1] - rotation[1, 2], rotation[0, 2] - rotation[2, 0],
                               rotation[1, 0] - rotation[0, 1]])  # 2 sin(angle) axis
    if angle < 1e-6:
        return twice_sin_axis / 2.0
    if cos > 0.0:
        return twice_sin_axis * angle / (2.0 * np.sin(angle))
    outer = (rotation + rotation.T) / 2.0 - cos * np.eye(3)  # (1 - cos) axis axisᵀ
    column = int(np.argmax(np.diag(outer)))
    axis = outer[:, column] / np.linalg.norm(outer[:, column])
    return axis * angle * (1.0 if axis @ twice_sin_axis >= 0 else -1.0)


def renderer_colours(f_dc: np.ndarray, opacity_logit: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(RGB [N, 3], opacity logit [N]) as LAM's renderer stores them: 8 bits each, floor(value * 255) / 255 of
    the clamped f_dc and of sigmoid(opacity); an opacity stored as 0 gets the logit OPACITY_ZERO_LOGIT (never
    drawn, as there)."""
    rgb = np.floor(np.clip(f_dc.astype(np.float64), 0.0, 1.0) * 255.0) / 255.0
    alpha = np.floor(255.0 / (1.0 + np.exp(-opacity_logit.astype(np.float64)))) / 255.0
    with np.errstate(divide="ignore"):
        logit = np.where(alpha > 0, np.log(alpha) - np.log1p(-np.minimum(alpha, 1 - 1e-7)), OPACITY_ZERO_LOGIT)
    return rgb.astype(np.float32), logit.astype(np.float32)


def lam_camera(center: np.ndarray, height: float, width_px: int = 512, height_px: int = 512) -> Camera:
    """LAM's framing for a head whose bounds have this centre and height: the renderer's camera, moved and scaled
    with the head relative to LAM's sample avatar (it is the renderer's own camera for that avatar)."""
    scale = height / LAM_REFERENCE_HEIGHT
    eye = np.asarray(center) + (np.asarray(LAM_CAMERA_EYE) - np.asarray(LAM_REFERENCE_CENTER)) * scale
    pitch = np.radians(LAM_CAMERA_PITCH_DEG)
    forward = np.array([0.0, np.sin(pitch), -np.cos(pitch)])
    return Camera.looking_at(eye, eye + forward, (0.0, 1.0, 0.0), width_px, height_px, LAM_CAMERA_FOV_DEG)


def _mesh_primitive(gltf: Gltf) -> tuple[dict, dict]:
    """The one mesh primitive with morph targets (LAM's head mesh), and its mesh."""
    member = gltf.member
    meshes = [as_dict(mesh, f"mesh {k}", member) for k, mesh in enumerate(gltf.items("meshes"))]
    found = [(mesh, as_dict(primitive, f"mesh {k} primitive", member)) for k, mesh in enumerate(meshes)
             for primitive in as_list(mesh.get("primitives"), f"mesh {k} primitives", member)]
    found = [(mesh, primitive) for mesh, primitive in found if primitive.get("targets")]
    if not found:
        raise ImportFormatError(f"{gltf.member}: no mesh has morph targets (a LAM skin.glb's head mesh holds the "
                                "ARKit blendshapes as morph targets)")
    if len(found) > 1:
        raise ImportFormatError(f"{gltf.member}: {len(found)} mesh primitives have morph targets; expected one")
    return found[0]


def _target_names(gltf: Gltf, mesh: dict, count: int) -> list[str]:
    """The morph targets' ARKit names (mesh.extras.targetNames), checked."""
    extras = mesh.get("extras")
    names = extras.get("targetNames") if isinstance(extras, dict) else None
    if not isinstance(names, list) or len(names) != count:
        raise ImportFormatError(f"{gltf.member}: the head mesh's extras.targetNames must name each of its {count} "
                                f"morph targets, got {str(names)[:80]}")
    unknown = [n for n in names if n not in ARKIT_BLENDSHAPES]
    if unknown:
        raise ImportFormatError(f"{gltf.member}: morph target name(s) "
                                f"{', '.join(repr(n)[:40] for n in unknown[:3])} are not "
                                "ARKit blendshape names (gaussiantalker.sdk.rig.ARKIT_BLENDSHAPES)")
    if len(set(names)) != len(names):
        raise ImportFormatError(f"{gltf.member}: morph target names repeat")
    return names


def _head_joint(gltf: Gltf, bone: str) -> tuple[int, np.ndarray]:
    """(node index, rest world matrix) of the skin's joint named `bone`, its bind pose checked to be its rest."""
    skins = gltf.items("skins")
    if not skins:
        raise ImportFormatError(f"{gltf.member}: no skin (skeleton): a LAM skin.glb carries the head with its "
                                f"{bone!r} bone")
    skin = as_dict(skins[0], "skin 0", gltf.member)
    joints = as_list(skin.get("joints"), "skin 0 joints", gltf.member)
    names = node_names(gltf)
    joint_names = [names[j] if isinstance(j, int) and not isinstance(j, bool) and 0 <= j < len(names) else None
                   for j in joints]
    if bone not in joint_names:
        raise ImportFormatError(f"{gltf.member}: the skin has no joint named {bone!r} (joints: "
                                f"{', '.join(map(str, joint_names[:6]))}, ...)")
    index = joint_names.index(bone)
    world = world_matrix(gltf, joints[index])
    if not (np.isfinite(world).all() and np.abs(world).max() <= MAX_COORDINATE
            and abs(np.linalg.det(world[:3, :3])) > 1e-12):
        raise ImportFormatError(f"{gltf.member}: the {bone!r} bone's rest transform is degenerate or not finite")
    if skin.get("inverseBindMatrices") is not None:
        inverse_bind = read_accessor(gltf, skin["inverseBindMatrices"])
        if inverse_bind.shape[1] != 16:
            raise ImportFormatError(f"{gltf.member}: the skin's inverseBindMatrices must be MAT4, got "
                                    f"{inverse_bind.shape[1]} values per joint")
        inverse_bind = inverse_bind.reshape(-1, 4, 4).astype(np.float64)
        if inverse_bind.shape[0] != len(joints):
            raise ImportFormatError(f"{gltf.member}: the skin has {len(joints)} joints but "
                                    f"{inverse_bind.shape[0]} inverse bind matrices")
        if not np.abs(world @ inverse_bind[index].T - np.eye(4)).max() <= BIND_TOLERANCE:
            raise ImportFormatError(f"{gltf.member}: the {bone!r} bone's rest transform times its inverse bind "
                                    "matrix is not the identity: the mesh is not bound in its rest pose")
    return joints[index], world


def _coordinates(values: np.ndarray) -> bool:
    """Whether every value is finite and within MAX_COORDINATE (metres)."""
    return bool(np.isfinite(values).all() and (values.size == 0 or np.abs(values).max() <= MAX_COORDINATE))


def read_rig(data: bytes, options: LamOptions, member: str = "skin.glb"):
    """(gltf, rest [V, 3], morphs [52, V, 3] in ARKIT_BLENDSHAPES order, pivot [3], head node, target names, which
    vertices the head bone moves [V] bool or None, the mesh's triangles [F, 3] or None)."""
    if options.camera not in CAMERA_CHOICES:
        raise ValueError(f"camera must be one of {', '.join(CAMERA_CHOICES)}, got {options.camera!r}")
    gltf = load_glb(data, member)
    mesh, primitive = _mesh_primitive(gltf)
    position = as_dict(primitive.get("attributes") or {}, "primitive attributes", member).get("POSITION")
    if position is None:
        raise ImportFormatError(f"{member}: the head mesh has no POSITION attribute")
    rest = read_accessor(gltf, position).astype(np.float64)
    if rest.ndim != 2 or rest.shape[1] != 3 or not _coordinates(rest):
        raise ImportFormatError(f"{member}: the head mesh's POSITION must be VEC3 values, finite within "
                                f"{MAX_COORDINATE:g} m")
    if not 1 <= rest.shape[0] <= MAX_VERTICES:
        raise ImportFormatError(f"{member}: the head mesh has {rest.shape[0]} vertices; the importer reads 1 to "
                                f"{MAX_VERTICES}")
    targets = as_list(primitive["targets"], "primitive targets", member)
    names = _target_names(gltf, mesh, len(targets))
    morphs = np.zeros((len(ARKIT_BLENDSHAPES), *rest.shape))
    for name, target in zip(names, targets, strict=True):
        if not isinstance(target, dict) or target.get("POSITION") is None:
            raise ImportFormatError(f"{member}: morph target {name} has no POSITION")
        delta = read_accessor(gltf, target["POSITION"]).astype(np.float64)
        if delta.shape != rest.shape or not _coordinates(delta):
            raise ImportFormatError(f"{member}: morph target {name} must hold {rest.shape[0]} VEC3 rows, finite "
                                    f"within {MAX_COORDINATE:g} m, got {delta.shape[0]} rows")
        scale = LAM_WEIGHT_SCALE.get(name, 1.0) if options.renderer_weight_scale else 1.0
        morphs[ARKIT_BLENDSHAPES.index(name)] = delta * scale
    head, world = _head_joint(gltf, options.head_bone)
    return (gltf, rest, morphs, world[:3, 3].copy(), head, names, head_vertices(gltf, primitive, head, rest.shape[0]),
            mesh_triangles(gltf, primitive, rest.shape[0]))


def mesh_triangles(gltf: Gltf, primitive: dict, count: int) -> np.ndarray | None:
    """The head mesh's triangles [F, 3] (its `indices`), or None when it has none or draws another kind of primitive.
    LAM's renderer draws no triangles; the exporter reads the mesh's edges from them (docs/import.md)."""
    if primitive.get("indices") is None or primitive.get("mode", 4) != 4:
        return None
    indices = read_accessor(gltf, primitive["indices"])
    if indices.dtype.kind not in "iu" or indices.size % 3 or indices.ndim != 2 or indices.shape[1] != 1 \
            or (indices.size and not 0 <= int(indices.min()) <= int(indices.max()) < count):
        raise ImportFormatError(f"{gltf.member}: the head mesh's indices must be SCALAR integers, three a triangle, "
                                f"each below its {count} vertices")
    return indices.reshape(-1, 3).astype(np.int64)


def _below(gltf: Gltf, head: int, joints: list) -> list[bool]:
    """For each joint (a node index), whether it is `head` or lies below it in the node tree. One walk up the tree
    per node at most (results shared along each path; a path longer than MAX_DEPTH, or a cycle, is not below), so
    a hostile skin of many joints costs linear time."""
    up, known = parents(gltf), {head: True}
    n_nodes = len(gltf.items("nodes"))

    def below(node) -> bool:
        if isinstance(node, bool) or not isinstance(node, int) or not 0 <= node < n_nodes:
            return False
        path, current = [], node
        while current is not None and current not in known and len(path) <= MAX_DEPTH:
            path.append(current)
            current = up.get(current)
        result = known.get(current, False)
        known.update((visited, result) for visited in path)
        return result

    return [below(node) for node in joints]


def head_vertices(gltf: Gltf, primitive: dict, head: int, count: int) -> np.ndarray | None:
    """Which of the head mesh's `count` vertices the skin moves mostly (over half their weight) with the head bone
    and the bones below it (the head, not the neck and chest), or None when the mesh has no skin weights;
    ImportFormatError for weights that are not [count, k] rows or name a joint the skin lacks."""
    attributes = primitive.get("attributes") or {}
    if attributes.get("JOINTS_0") is None or attributes.get("WEIGHTS_0") is None:
        return None
    joints = read_accessor(gltf, attributes["JOINTS_0"])
    weights = read_accessor(gltf, attributes["WEIGHTS_0"])
    skin_joints = as_list(as_dict(gltf.items("skins")[0], "skin 0", gltf.member).get("joints"), "skin 0 joints",
                          gltf.member)
    if joints.shape != weights.shape or joints.shape[0] != count or joints.ndim != 2 or joints.shape[1] == 0 \
            or joints.dtype.kind not in "iu" or not np.isfinite(weights).all():
        raise ImportFormatError(f"{gltf.member}: the head mesh's JOINTS_0 and WEIGHTS_0 must be integer and finite "
                                f"rows, one per vertex ({count}), of the same width")
    if joints.size and not 0 <= int(joints.min()) <= int(joints.max()) < len(skin_joints):
        raise ImportFormatError(f"{gltf.member}: JOINTS_0 names joints {int(joints.min())} to {int(joints.max())}; "
                                f"the skin has {len(skin_joints)}")
    below_head = np.array(_below(gltf, head, skin_joints), dtype=bool)
    weights = weights.astype(np.float64)
    return (weights * below_head[joints]).sum(axis=1) > weights.sum(axis=1) / 2.0


def head_pose_track(skin: Gltf, head: int, data: bytes, options: LamOptions, fps: int,
                    member: str = "animation.glb") -> tuple[np.ndarray, str]:
    """[T, 6] head rotation (axis-angle about the head bone's pivot) and translation of one clip sampled at `fps`,
    and the clip's name."""
    gltf = load_glb(data, member)
    names = animation_names(gltf)
    if not names:
        raise ImportFormatError(f"{member}: the file has no animation clips")
    if options.clip is not None:
        if options.clip not in names:
            raise ImportFormatError(f"{member}: no clip named {options.clip!r} (clips: {', '.join(names)})")
        clip = names.index(options.clip)
    else:
        clip = next((k for k, name in enumerate(names) if "idle" in name.lower()), 0)
    duration = clip_duration(gltf, clip)
    if not duration <= MAX_CLIP_SECONDS:
        raise ImportFormatError(f"{member}: clip {names[clip]!r} lasts {duration:g} s; the importer samples clips of "
                                f"up to {MAX_CLIP_SECONDS:g} s")
    times = np.arange(int(np.floor(duration * fps + 1e-6)) + 1) / fps
    rest = world_matrix(skin, head)
    pivot = rest[:3, 3]
    track = np.zeros((times.shape[0], 6))
    sampled = sampled_world(skin, head, gltf, clip, times)
    if not (np.isfinite(sampled).all() and np.abs(sampled).max() <= MAX_COORDINATE
            and np.all(np.abs(np.linalg.det(sampled[:, :3, :3])) > 1e-12)):
        raise ImportFormatError(f"{member}: clip {names[clip]!r} moves the head bone through a degenerate or "
                                "non-finite transform")
    for frame, current in enumerate(sampled):
        motion = current @ np.linalg.inv(rest)  # the bone's world motion since rest: x -> R x + m
        rotation = motion[:3, :3]
        track[frame, :3] = rotation_vector(rotation)
        track[frame, 3:] = motion[:3, 3] + rotation @ pivot - pivot
    return track.astype(np.float32), names[clip]


def _vertex_order(data: bytes | None, count: int) -> None:
    """vertex_order.json, if present, must list `count` vertex indices (the renderer does not use it)."""
    if data is None:
        return
    order = parse_json(data, "vertex_order.json")
    if not isinstance(order, list) or len(order) != count:
        raise ImportFormatError(f"vertex_order.json lists {len(order) if isinstance(order, list) else 'no'} "
                                f"entries; the avatar has {count} vertices and Gaussians")
    if not all(type(index) is int and 0 <= index < count for index in order):
        raise ImportFormatError(f"vertex_order.json must hold vertex indices in [0, {count})")


def import_lam(path: str | os.PathLike, options: LamOptions | None = None, progress: bool = True) -> ArkitSpeaker:
    """Read a LAM avatar zip into an ArkitSpeaker; ImportFormatError naming the member and field on bad input."""
    options = options or LamOptions()
    steps = progress_bar(total=4, desc="gt-import lam", unit="step", disable=not progress)
    with steps:
        steps.set_postfix_str("reading zip")
        members = read_avatar_zip(path, REQUIRED_MEMBERS, OPTIONAL_MEMBERS)
        steps.update()
        try:
            return _import_members(path, members, options, steps)
        except ImportFormatError as exc:  # a member's error, told with the zip it came from
            raise ImportFormatError(f"avatar {path}: {exc}") from None


def _import_members(path: str | os.PathLike, members: dict[str, bytes], options: LamOptions, steps
                    ) -> ArkitSpeaker:
    """import_lam's work on the zip's members (ImportFormatError naming the member and field)."""
    steps.set_postfix_str("skin.glb")
    skin, rest, morphs, pivot, head, target_names, on_head, faces = read_rig(members["skin.glb"], options)
    steps.update()
    steps.set_postfix_str("offset.ply")
    cloud = read_gaussian_ply(members["offset.ply"], "offset.ply")
    if cloud.count != rest.shape[0]:
        raise ImportFormatError(f"offset.ply holds {cloud.count} Gaussians but skin.glb's head mesh has "
                                f"{rest.shape[0]} vertices (LAM binds Gaussian i to vertex i)")
    if not _coordinates(cloud.xyz):
        raise ImportFormatError(f"offset.ply: the Gaussians' offsets must be finite within {MAX_COORDINATE:g} m")
    _vertex_order(members.get("vertex_order.json"), rest.shape[0])
    steps.update()
    steps.set_postfix_str("motion")
    pose_track, clip = (None, None)
    if "animation.glb" in members:
        pose_track, clip = head_pose_track(skin, head, members["animation.glb"], options, LAM_FPS)
    motion = None
    if "bsData.json" in members:
        try:
            motion = parse_motion(parse_json(members["bsData.json"], "bsData.json"), "bsData.json")
            motion = motion.at_fps(LAM_FPS).weights
        except DriveError as exc:
            raise ImportFormatError(str(exc)) from None
    steps.update()
    return _speaker(cloud, (rest, morphs, pivot, faces), options, pose_track, motion, on_head, {
        "format": "lam", "file": Path(path).name, "morph_targets": target_names, "pose_clip": clip,
        "camera": options.camera,
        "renderer_weight_scale": LAM_WEIGHT_SCALE if options.renderer_weight_scale else None,
        "dropped": ["f_rest (the renderer draws SH degree 0)"] if cloud.f_rest.shape[1] else []})


def _speaker(cloud, rig_parts: tuple, options: LamOptions, pose_track, motion, on_head: np.ndarray | None,
             source: dict) -> ArkitSpeaker:
    """The ArkitSpeaker of read avatar parts (`rig_parts`: rest, morphs, pivot, faces or None), its camera a portrait
    of the head (`on_head`: the Gaussians the head bone moves, None: all) or LAM's renderer's framing."""
    config = ArkitRig(covariance=options.covariance, fps=LAM_FPS)
    rest, morphs, pivot, faces = rig_parts
    rig = BlendshapeRig(torch.from_numpy(rest), torch.from_numpy(morphs), torch.from_numpy(pivot),
                        None if faces is None else torch.from_numpy(faces))
    gaussians = VertexBoundGaussians(torch.arange(cloud.count), sh_degree=0, covariance=options.covariance)
    rgb, opacity_logit = renderer_colours(cloud.f_dc, cloud.opacity) if options.renderer_colours else \
        (np.clip(cloud.f_dc, 0.0, 1.0), cloud.opacity)
    with torch.no_grad():
        gaussians.offset.copy_(torch.from_numpy(cloud.xyz))
        gaussians.rotation.copy_(torch.from_numpy(cloud.rotation))
        gaussians.log_scale.copy_(torch.from_numpy(cloud.log_scale))
        gaussians.opacity_logit.copy_(torch.from_numpy(opacity_logit))
        gaussians.sh.copy_(torch.from_numpy((rgb - 0.5) / SH_C0)[:, None, :])
    centres = rest + cloud.xyz
    framed = on_head is not None and on_head.mean() >= MIN_HEAD_SHARE
    head_low, head_high = head_box(centres[on_head] if framed else centres)
    source = {**source, "head_box": [head_low.tolist(), head_high.tolist()]}
    try:
        if options.camera == "source":  # placed on all the Gaussians' box, as LAM's renderer frames its avatars
            low, high = head_box(centres)
            camera = lam_camera((low + high) / 2.0, float(high[1] - low[1]))
        else:
            camera = portrait_camera(head_low, head_high, 512, 512)
    except CameraError as exc:
        raise ImportFormatError(f"skin.glb, offset.ply: no default camera frames the Gaussians ({exc})") from None
    return ArkitSpeaker(config, rig, gaussians, camera, (1.0, 1.0, 1.0), None if pose_track is None else
                        torch.from_numpy(pose_track), None if motion is None else torch.from_numpy(motion),
                        source).eval()


__all__ = ["LAM_WEIGHT_SCALE", "LamOptions", "import_lam", "lam_camera", "rotation_vector"]
