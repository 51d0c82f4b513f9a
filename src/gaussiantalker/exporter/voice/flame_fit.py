"""The voice driver for FLAME speakers: the ARKit mouth it predicts, as FLAME 2023 jaw pose and expression
coefficients fitted on the user's own FLAME model (docs/voice.md, "FLAME").

No FLAME basis can be shipped (FLAME's licence), and FLAME's expression coefficients are principal components with
no published meaning per coefficient, so a fixed "coefficient k opens the lips" table would be a guess. Instead:
* the jaw is FLAME's own joint: jaw_pose = (JAW_RADIANS x (jawOpen - closure share of mouthClose), 0, 0), an
  x-axis rotation, well defined in every FLAME;
* each ARKit mouth shape is written as a displacement of FLAME's two outer lip rings (the vertex rings
  GaussianAvatars builds its teeth from) in units of the mouth's width: corners out and up for a smile, lips forward
  and in for a pucker, and so on (LIP_SHAPES);
* the expression coefficients of a shape are the regularised least-squares fit of that displacement by the user's
  expression basis, with the vertices far from the mouth held still (FAR_WEIGHT): the most probable FLAME
  expression (the coefficients are unit-variance components) that moves the lips that way.

The committed model file (models/flame_voice.onnx) carries the jaw alone (an all-zero expression map, and
mouthClose closing the jaw), since it ships without a FLAME; `bind_to_flame` gives it the expression map fitted on
a FLAME model, as the importer would when it attaches the driver to a GaussianAvatars avatar.
"""

from __future__ import annotations

import numpy as np
import onnx

from gaussiantalker.sdk.rig import ARKIT_BLENDSHAPES, ARKIT_COUNT

from ..imports.sources.gaussian_avatars_flame import LOWER_LIP_RING, UPPER_LIP_RING
from ..model.flame import FlameArrays
from .onnx_graph import with_expression_map, with_jaw_map

JAW_RADIANS = 0.5  # jaw rotation per unit of jawOpen: speech's jawOpen up to ~0.4 opens FLAME's jaw ~0.2 rad
JAW_JOINT = 2
FLAME_VERTICES = 5023  # a model with GaussianAvatars' teeth has them after these
FAR_RADIUS = 1.6  # vertices farther than this many mouth widths from the mouth centre should not move
FAR_WEIGHT = 0.3  # weight of keeping them still, per vertex, against the lip rings' fit
RIDGE = 1e-4  # weight of the coefficients' size (relative to the fit's scale)
# FLAME's expression coefficients are unit-variance components: a fitted shape needing more than this many
# standard deviations is scaled down to it, so a driven face stays among the faces FLAME was built from.
MAX_COEFFICIENT = 3.0
# mouthClose on an open jaw: the lower lip rises by this share of the jaw's opening at the lips, the upper lip
# falls by the rest.
CLOSE_LOWER_SHARE = 0.7


def _ring_coordinates(template: np.ndarray) -> dict:
    """The mouth frame of a template: centre, axes (x from the right corner to the left, y up, z forward), width,
    and per ring vertex its signed position s in -1..1 along x and its closeness to the midline c = 1 - s^2."""
    upper, lower = template[list(UPPER_LIP_RING)], template[list(LOWER_LIP_RING)]
    corner_a, corner_b = 0.5 * (upper[0] + lower[0]), 0.5 * (upper[-1] + lower[-1])
    if corner_a[0] > corner_b[0]:
        corner_a, corner_b = corner_b, corner_a
    x = corner_b - corner_a  # towards the subject's left (+x in FLAME's frame)
    width = float(np.linalg.norm(x))
    x /= width
    z = np.array([0.0, 0.0, 1.0]) - x[2] * x
    z /= np.linalg.norm(z)
    y = np.cross(z, x)
    centre = 0.5 * (upper.mean(axis=0) + lower.mean(axis=0))
    s_upper = np.clip((upper - centre) @ x / (0.5 * width), -1.0, 1.0)
    s_lower = np.clip((lower - centre) @ x / (0.5 * width), -1.0, 1.0)
    return {"centre": centre, "axes": np.stack([x, y, z]), "width": width, "s": (s_upper, s_lower)}


def _side(s: np.ndarray, sign: float) -> np.ndarray:
    """Weight of the ring's `sign` side (+1 the subject's left): 0 at the other corner, 1 at this one."""
    return np.clip(0.5 + 0.5 * sign * s, 0.0, 1.0) ** 2


def lip_shapes(s_upper: np.ndarray, s_lower: np.ndarray) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """ARKit mouth shape -> (upper ring, lower ring) displacements [15, 3] in the mouth frame (x to the subject's
    left, y up, z forward), in mouth widths, at weight 1. From ARKit's descriptions of each shape."""
    shapes: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    cu, cl = 1.0 - s_upper ** 2, 1.0 - s_lower ** 2

    def ring(dx, dy, dz) -> np.ndarray:  # per-vertex or constant components -> [15, 3]
        columns = np.broadcast_arrays(np.zeros(len(s_upper)), dx, dy, dz)[1:]
        return np.stack(columns, axis=1).astype(np.float64)

    zero_u, zero_l = np.zeros((len(s_upper), 3)), np.zeros((len(s_lower), 3))
    shapes["mouthFunnel"] = (ring(-0.12 * s_upper, 0.04 * cu, 0.03 + 0.1 * cu),
                             ring(-0.12 * s_lower, -0.04 * cl, 0.03 + 0.1 * cl))
    shapes["mouthPucker"] = (ring(-0.2 * s_upper, -0.02 * cu, 0.06 + 0.08 * cu),
                             ring(-0.2 * s_lower, 0.02 * cl, 0.06 + 0.08 * cl))
    shapes["mouthRollLower"] = (zero_u, ring(0.0, 0.04 * cl, -0.05 * cl))
    shapes["mouthRollUpper"] = (ring(0.0, -0.03 * cu, -0.04 * cu), zero_l)
    shapes["mouthShrugLower"] = (zero_u, ring(0.0, 0.05 * cl, 0.02 * cl))
    shapes["mouthShrugUpper"] = (ring(0.0, 0.03 * cu, 0.01 * cu), zero_l)
    for sign, side in ((1.0, "Left"), (-1.0, "Right")):
        wu, wl = _side(s_upper, sign), _side(s_lower, sign)
        shapes[f"mouthSmile{side}"] = (ring(sign * 0.1 * wu, 0.08 * wu, -0.03 * wu),
                                       ring(sign * 0.1 * wl, 0.06 * wl, -0.03 * wl))
        shapes[f"mouthStretch{side}"] = (ring(sign * 0.1 * wu, -0.03 * wu, -0.01 * wu),
                                         ring(sign * 0.1 * wl, -0.05 * wl, -0.01 * wl))
        shapes[f"mouthDimple{side}"] = (ring(sign * 0.05 * wu, 0.0, -0.03 * wu),
                                        ring(sign * 0.05 * wl, 0.0, -0.03 * wl))
        shapes[f"mouthFrown{side}"] = (ring(0.0, -0.06 * wu, 0.0), ring(0.0, -0.06 * wl, 0.0))
        shapes[f"mouthPress{side}"] = (ring(0.0, -0.02 * cu * (0.5 + 0.5 * sign * s_upper), -0.01 * cu),
                                       ring(0.0, 0.02 * cl * (0.5 + 0.5 * sign * s_lower), -0.01 * cl))
        shapes[f"mouthUpperUp{side}"] = (ring(0.0, 0.07 * cu * (0.5 + 0.5 * sign * s_upper), 0.0), zero_l)
        shapes[f"mouthLowerDown{side}"] = (zero_u, ring(0.0, -0.07 * cl * (0.5 + 0.5 * sign * s_lower), 0.0))
    shapes["mouthLeft"] = (ring(0.08, 0.0, 0.0), ring(0.08, 0.0, 0.0))
    shapes["mouthRight"] = (ring(-0.08, 0.0, 0.0), ring(-0.08, 0.0, 0.0))
    return shapes


def _jaw_displacement(template: np.ndarray, joint: np.ndarray, angle: float) -> np.ndarray:
    """Displacement of `template` points rotated by `angle` about the x axis through `joint`."""
    c, s = np.cos(angle), np.sin(angle)
    rotation = np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])
    return (template - joint) @ rotation.T + joint - template


def fit_expression_map(flame: FlameArrays) -> np.ndarray:
    """[52, n_expr] ARKit weight -> FLAME expression coefficients, fitted on `flame` (module docstring): rows of the
    shapes in LIP_SHAPES and mouthClose; other rows (jaw, eyes, brows, cheeks, tongue) zero."""
    template = np.asarray(flame.v_template[:FLAME_VERTICES], np.float64)
    basis = np.asarray(flame.exprdirs[:FLAME_VERTICES], np.float64)  # [V, 3, E]
    frame = _ring_coordinates(template)
    axes, width = frame["axes"], frame["width"]
    rings = list(UPPER_LIP_RING) + list(LOWER_LIP_RING)
    far = np.flatnonzero(np.linalg.norm(template - frame["centre"], axis=1) > FAR_RADIUS * width)
    ring_basis = basis[rings].reshape(-1, basis.shape[2])  # [90, E]
    far_basis = basis[far].reshape(-1, basis.shape[2])
    normal = ring_basis.T @ ring_basis / len(rings) + FAR_WEIGHT * far_basis.T @ far_basis / max(len(far), 1)
    normal += RIDGE * np.trace(normal) / normal.shape[0] * np.eye(normal.shape[0])
    shapes = lip_shapes(*frame["s"])
    joint = np.asarray(flame.J_regressor, np.float64)[JAW_JOINT, :FLAME_VERTICES] @ template
    opening = _jaw_displacement(template[rings], joint, JAW_RADIANS)  # jawOpen 1 at the lips, model units
    out = np.zeros((ARKIT_COUNT, basis.shape[2]))
    for name in ARKIT_BLENDSHAPES:
        if name in shapes:
            upper, lower = shapes[name]
            target = np.concatenate([upper, lower]) @ axes * width  # mouth frame -> model frame, metres
        elif name == "mouthClose":  # the lips shut against jawOpen 1: lower lip up, upper lip down
            n = len(UPPER_LIP_RING)
            target = np.concatenate([(1.0 - CLOSE_LOWER_SHARE) * opening[n:], -CLOSE_LOWER_SHARE * opening[n:]])
        else:
            continue
        row = np.linalg.solve(normal, ring_basis.T @ target.reshape(-1) / len(rings))
        out[ARKIT_BLENDSHAPES.index(name)] = row * min(1.0, MAX_COEFFICIENT / max(np.abs(row).max(), 1e-12))
    return out.astype(np.float32)


def jaw_map(closes_jaw: bool) -> np.ndarray:
    """[52, 3] ARKit weights -> jaw pose: JAW_RADIANS per unit of jawOpen about x; with `closes_jaw` (no
    expression map to shut the lips) mouthClose closes the jaw by as much."""
    out = np.zeros((ARKIT_COUNT, 3), np.float32)
    out[ARKIT_BLENDSHAPES.index("jawOpen"), 0] = JAW_RADIANS
    if closes_jaw:
        out[ARKIT_BLENDSHAPES.index("mouthClose"), 0] = -JAW_RADIANS
    return out


def default_maps(n_expr: int = 100) -> tuple[np.ndarray, np.ndarray]:
    """The committed FLAME model's maps: no expression (no FLAME to fit on), the jaw closing for mouthClose."""
    return np.zeros((ARKIT_COUNT, n_expr), np.float32), jaw_map(closes_jaw=True)


def bind_to_flame(model: onnx.ModelProto, flame: FlameArrays) -> onnx.ModelProto:
    """A FLAME voice graph with its expression map fitted on `flame` (and the jaw no longer doing mouthClose)."""
    fitted = with_expression_map(model, fit_expression_map(flame))
    return with_jaw_map(fitted, jaw_map(closes_jaw=False))


__all__ = ["JAW_RADIANS", "bind_to_flame", "default_maps", "fit_expression_map", "jaw_map", "lip_shapes"]
