"""GaussianAvatars avatars for the tests, written the way its training saves them (no avatar is committed, no
network): a synthetic FLAME-layout head model, the avatar folder (point_cloud/iteration_N/point_cloud.ply with
flame_param.npz beside it), and an independent numpy reference of what GaussianAvatars computes from them: FLAME
with its teeth (`ga_flame_with_teeth`, `ga_flame_vertices`) and the triangle binding (`ga_world_gaussians`).
Nothing here calls the SDK, so the importer is checked against the format, not against itself.

Run as a script it writes a synthetic avatar of any size for benchmarks (`gt-bench avatar`; docs/bench/
gaussian-avatars/avatar.md was measured on the one below: FLAME's sizes, 100k Gaussians at SH degree 3):

    python tests/gaussian_avatars.py OUT --gaussians 100000 --frames 100 --seed 0

writes OUT/flame.npz (the FLAME-layout model, for `--flame`) and OUT/avatar/point_cloud/iteration_30000/
{point_cloud.ply, flame_param.npz}.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np
from flame_pickles import UINT32_MAX, flame_pickle_dict, py2_dumps
from plyfile import PlyData, PlyElement

FLAME_VERTICES, FLAME_FACES = 5023, 9976
N_SHAPE, N_EXPR = 300, 100
TEETH_VERTICES, TEETH_FACES = 120, 168
GA_VERTICES, GA_FACES = FLAME_VERTICES + TEETH_VERTICES, FLAME_FACES + TEETH_FACES
FLAME_KEYS = ("v_template", "f", "shapedirs", "posedirs", "J_regressor", "weights", "kintree_table")
PARENTS = (-1, 0, 1, 1, 1)  # global, neck, jaw, left eye, right eye
# FLAME's lip_outside_ring_upper / _lower vertex masks, in the order GaussianAvatars reads them.
UPPER_LIP = (1713, 1715, 1716, 1735, 1696, 1694, 1657, 3543, 2774, 2811, 2813, 2850, 2833, 2832, 2830)
LOWER_LIP = (1576, 1577, 1773, 1774, 1795, 1802, 1865, 3503, 2948, 2905, 2898, 2881, 2880, 2713, 2712)
SH_C0 = 0.28209479177387814
DEFAULT_ITERATION = 30000

# The synthetic head: a tube of rings around the y axis on an ellipsoid (metres, y up, face toward +z).
RINGS, SEGMENTS = 173, 29  # 5017 vertices used, 6 left unreferenced; 2 * 172 * 29 = 9976 triangles
RADII = np.array([0.075, 0.11, 0.09])  # x, y, z semi-axes: about 0.21 m tall
THETA = np.linspace(0.35, np.pi - 0.2, RINGS)  # polar angle from the bottom (open neck) to near the crown
# Segment angles about y (0 = straight ahead): 15 segments on the front +-35 degrees (the mouth), 14 round the back.
PHI = np.deg2rad(np.concatenate([np.linspace(35.0, -35.0, 15), -35.0 - (290.0 / 15) * np.arange(1, 15)]))
UPPER_LIP_RING, LOWER_LIP_RING = 56, 50  # the rings the lip vertices sit on (about 9 mm apart, y ~ -4.5 cm)
EYES = np.array([[0.032, 0.03, 0.0], [-0.032, 0.03, 0.0]])  # left (+x), right; z set on the surface below


# ------------------------------------------------------------------------------------------- FLAME model


def _smoothstep(x: np.ndarray, lo: float, hi: float) -> np.ndarray:
    t = np.clip((x - lo) / (hi - lo), 0.0, 1.0)
    return t * t * (3 - 2 * t)


def _tube() -> tuple[np.ndarray, np.ndarray]:
    """Natural (ring-major) positions [5023, 3] and faces [9976, 3] of the tube, outward winding."""
    t, p = np.meshgrid(THETA, PHI, indexing="ij")
    points = np.stack([np.sin(t) * np.sin(p), -np.cos(t), np.sin(t) * np.cos(p)], -1).reshape(-1, 3) * RADII
    inside = np.linspace(-0.02, 0.02, FLAME_VERTICES - RINGS * SEGMENTS)[:, None] * np.ones(3)  # unreferenced
    r, j = np.meshgrid(np.arange(RINGS - 1), np.arange(SEGMENTS), indexing="ij")
    a, b = r * SEGMENTS + j, r * SEGMENTS + (j + 1) % SEGMENTS
    c, d = a + SEGMENTS, b + SEGMENTS
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([b, d, c], -1).reshape(-1, 3)])
    tri = points[faces]
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    if (normals * tri.mean(1)).sum() < 0:
        faces = faces[:, ::-1]
    return np.concatenate([points, inside]), np.ascontiguousarray(faces)


def _lip_order() -> np.ndarray:
    """order[m] = the natural vertex that model vertex m is: FLAME's lip indices land on the lip rings' front."""
    order = np.arange(FLAME_VERTICES)
    targets = [(m, ring * SEGMENTS + k) for ring, lips in ((UPPER_LIP_RING, UPPER_LIP), (LOWER_LIP_RING, LOWER_LIP))
               for k, m in enumerate(lips)]
    for m, natural in targets:  # swaps; an earlier placement is never undone (its natural vertex is taken)
        j = int(np.nonzero(order == natural)[0][0])
        order[m], order[j] = order[j], order[m]
    return order


def _smooth_fields(points: np.ndarray, rng: np.random.Generator, n_columns: int, amplitude: np.ndarray
                   ) -> np.ndarray:
    """[V, 3, n_columns] smooth random displacement fields (low-frequency functions of position)."""
    n_features = 16
    freq = rng.normal(0.0, 12.0, (3, n_features))  # rad/m: wavelengths of a few decimetres
    phase = rng.uniform(0, 2 * np.pi, n_features)
    features = np.concatenate([np.ones((len(points), 1)), points / RADII, np.sin(points @ freq + phase)], 1)
    coeffs = rng.normal(0.0, 1.0, (features.shape[1], 3 * n_columns)) / np.sqrt(features.shape[1])
    fields = (features @ coeffs).reshape(len(points), 3, n_columns)
    return fields * np.asarray(amplitude, np.float64)


def _joint_regressor(points: np.ndarray, on_surface: np.ndarray) -> np.ndarray:
    """[5, V]: each joint a weighted mean of surface vertices (rows sum to 1)."""
    unit = points / RADII
    ring = np.full(len(points), -1)
    ring[on_surface] = np.arange(on_surface.sum()) // SEGMENTS
    back = np.clip(-unit[:, 2], 0, None)
    rows = [
        ((ring >= 0) & (ring < 5)) * (0.1 + back**2),  # global: the neck's base, towards the back
        ((ring >= 16) & (ring < 22)) * (0.1 + back**2),  # neck: a little higher
        ((ring >= 58) & (ring < 66)) * (0.1 + back**2),  # jaw: the hinge inside the head, above the mouth
    ]
    for eye in _eye_points(points, on_surface):  # eyes: small patches on the upper front
        rows.append(on_surface * np.exp(-((points - eye) ** 2).sum(1) / (2 * 0.006**2)))
    regressor = np.stack(rows)
    return regressor / regressor.sum(1, keepdims=True)


def _eye_points(points: np.ndarray, on_surface: np.ndarray) -> np.ndarray:
    """The surface points nearest EYES' (x, y) on the front."""
    front = on_surface & (points[:, 2] > 0)
    out = []
    for eye in EYES:
        distance = ((points[:, :2] - eye[:2]) ** 2).sum(1) + np.where(front, 0.0, 1.0)
        out.append(points[np.argmin(distance)])
    return np.asarray(out)


def _skinning(points: np.ndarray, on_surface: np.ndarray) -> np.ndarray:
    """[V, 5] smooth weights: the neck's base on the global joint, the lower front (lower lip, chin) on the jaw,
    small patches round the eyes partly on the eye joints, the rest of the head on the neck joint."""
    y, z = points[:, 1], points[:, 2]
    mouth = -RADII[1] * (np.cos(THETA[UPPER_LIP_RING]) + np.cos(THETA[LOWER_LIP_RING])) / 2
    root = 1.0 - _smoothstep(y, -0.095, -0.075)
    jaw = (1.0 - _smoothstep(y, mouth - 0.003, mouth + 0.003)) * _smoothstep(z, -0.03, 0.0)
    eyes = [0.8 * np.exp(-((points - e) ** 2).sum(1) / (2 * 0.008**2)) for e in _eye_points(points, on_surface)]
    rest = (1.0 - root) * (1.0 - jaw)
    weights = np.stack([root, rest * (1.0 - eyes[0] - eyes[1]), (1.0 - root) * jaw, rest * eyes[0], rest * eyes[1]],
                       1)
    return weights / weights.sum(1, keepdims=True)


def synthetic_flame(seed: int = 0) -> dict[str, np.ndarray]:
    """A FLAME-layout head model as FLAME's files hold it (float64, uint32 faces, FLAME's kintree_table), smooth and
    head-like enough to render; FLAME's lip-ring vertex indices sit on the mouth, so the teeth land behind it."""
    rng = np.random.default_rng(seed)
    natural, natural_faces = _tube()
    order = _lip_order()
    inverse = np.argsort(order)
    points = natural[order]
    faces = inverse[natural_faces]
    on_surface = np.zeros(FLAME_VERTICES, bool)
    on_surface[faces] = True
    # The regressor picks vertices by ring: built in natural order, then taken in model order.
    natural_surface = np.arange(FLAME_VERTICES) < RINGS * SEGMENTS
    regressor = _joint_regressor(natural, natural_surface)[:, order]
    decay = lambda n: 2e-3 / (1.0 + np.arange(n) / 10.0)  # noqa: E731  metres per unit coefficient
    shapedirs = np.concatenate([_smooth_fields(points, rng, N_SHAPE, decay(N_SHAPE)),
                                _smooth_fields(points, rng, N_EXPR, decay(N_EXPR))], 2)
    return {
        "v_template": points.astype(np.float64),
        "f": faces.astype(np.uint32),
        "shapedirs": shapedirs,
        "posedirs": _smooth_fields(points, rng, 36, np.full(36, 1e-3)),
        "J_regressor": regressor,
        "weights": _skinning(points, on_surface),
        "kintree_table": np.array([[UINT32_MAX, 0, 1, 1, 1], [0, 1, 2, 3, 4]], dtype=np.int64),
    }


def write_flame_npz(path: str | Path, model: dict[str, np.ndarray], **extra: np.ndarray) -> Path:
    """The model as a FLAME npz with the standard keys (plus `extra` entries, e.g. flame_version)."""
    path = Path(path)
    with path.open("wb") as handle:
        np.savez(handle, **{key: model[key] for key in FLAME_KEYS}, **extra)
    return path


def write_flame_pickle_model(path: str | Path, model: dict[str, np.ndarray]) -> Path:
    """The model as a FLAME pickle written the way the licensed files are (tests/flame_pickles.py)."""
    path = Path(path)
    path.write_bytes(py2_dumps(flame_pickle_dict(model)))
    return path


# -------------------------------------------------------------------------------------- GaussianAvatars' teeth

# Teeth rows of 15 vertices, appended in this order after FLAME's 5023.
TEETH_ROWS = ("UR", "LR", "UE", "LE", "URB", "UEB", "LRB", "LEB")
# Each strip joins row P to row Q, one quad per column pair (i, i+1); in a quad, p = P[i], P = P[i+1], q = Q[i],
# Q = Q[i+1]. Quads 0..6 use the first pattern, 7..13 the second; a pattern is its two triangles' corners in order.
_QUAD = {"A": ("pQq", "pPQ"), "B": ("pPq", "PQq"), "C": ("pqQ", "pQP"), "D": ("pqP", "PqQ")}
TEETH_STRIPS = (("UR", "UE", "A", "B"), ("URB", "UEB", "C", "D"), ("UEB", "UE", "D", "C"),  # upper: 84 faces
                ("LE", "LR", "B", "A"), ("LRB", "LEB", "A", "B"), ("LEB", "LE", "B", "A"))  # lower: 84 faces


def ga_teeth_faces() -> np.ndarray:
    """GaussianAvatars' 168 teeth triangles (upper, then lower), local vertex indices 0..119. -> [168, 3]"""
    out = []
    for row_p, row_q, left, right in TEETH_STRIPS:
        p0, q0 = 15 * TEETH_ROWS.index(row_p), 15 * TEETH_ROWS.index(row_q)
        for i in range(14):
            corner = {"p": p0 + i, "P": p0 + i + 1, "q": q0 + i, "Q": q0 + i + 1}
            for triangle in _QUAD[left if i < 7 else right]:
                out.append([corner[c] for c in triangle])
    return np.asarray(out, dtype=np.int64)


def ga_teeth_vertices(v_template: np.ndarray) -> np.ndarray:
    """The 120 teeth vertices GaussianAvatars builds from the raw template's lip rings (float64). -> [120, 3]"""
    upper, lower = np.asarray(v_template, np.float64)[list(UPPER_LIP)], np.asarray(v_template, np.float64)[
        list(LOWER_LIP)]
    d = np.mean(np.sqrt(((upper - lower) ** 2).sum(1)))
    m = (upper + lower) / 2
    m[:, 1] = m[:, 1].mean()
    m[:, 2] -= 1.5 * d
    ue = m + [0, 0.1 * d, 0]
    ur = ue + [0, 2 * d, 0]
    le = m - [0, 0.1 * d, 0] - [0, 0, 0.4 * d]
    lr = le - [0, 2 * d, 0]
    rows = {"UR": ur, "LR": lr, "UE": ue, "LE": le}
    rows.update({name + "B": rows[name] - [0, 0, d] for name in ("UR", "UE", "LR", "LE")})
    return np.concatenate([rows[name] for name in TEETH_ROWS])


def ga_flame_with_teeth(model: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """FLAME's arrays (FLAME_KEYS layout) with GaussianAvatars' teeth: 5143 vertices, 10144 faces (float64)."""
    n_t = TEETH_VERTICES
    shapedirs = np.asarray(model["shapedirs"], np.float64)
    teeth_dirs = np.zeros((n_t, 3, shapedirs.shape[2]))
    lip_mean = (shapedirs[list(UPPER_LIP), :, :N_SHAPE] + shapedirs[list(LOWER_LIP), :, :N_SHAPE]) / 2  # [15, 3, 300]
    teeth_dirs[:, :, :N_SHAPE] = np.tile(lip_mean, (len(TEETH_ROWS), 1, 1))  # every row: the lip pairs' mean
    weights = np.zeros((n_t, 5))
    row = np.repeat(TEETH_ROWS, 15)
    weights[np.isin(row, ("UR", "UE", "URB", "UEB")), 1] = 1.0  # upper teeth: neck
    weights[np.isin(row, ("LR", "LE", "LRB", "LEB")), 2] = 1.0  # lower teeth: jaw
    return {
        "v_template": np.concatenate([np.asarray(model["v_template"], np.float64),
                                      ga_teeth_vertices(model["v_template"])]),
        "f": np.concatenate([np.asarray(model["f"], np.int64), ga_teeth_faces() + FLAME_VERTICES]),
        "shapedirs": np.concatenate([shapedirs, teeth_dirs]),
        "posedirs": np.concatenate([np.asarray(model["posedirs"], np.float64), np.zeros((n_t, 3, 36))]),
        "J_regressor": np.concatenate([np.asarray(model["J_regressor"], np.float64), np.zeros((5, n_t))], 1),
        "weights": np.concatenate([np.asarray(model["weights"], np.float64), weights]),
        "kintree_table": model["kintree_table"],
    }


# -------------------------------------------------------------------------------------------- FLAME forward


def rodrigues(rotvec: np.ndarray) -> np.ndarray:
    """Axis-angle [..., 3] -> rotation matrices [..., 3, 3] (float64)."""
    rotvec = np.asarray(rotvec, np.float64)
    angle = np.linalg.norm(rotvec, axis=-1)[..., None, None]
    k = np.zeros((*rotvec.shape[:-1], 3, 3))
    x, y, z = rotvec[..., 0], rotvec[..., 1], rotvec[..., 2]
    k[..., 0, 1], k[..., 0, 2], k[..., 1, 0], k[..., 1, 2], k[..., 2, 0], k[..., 2, 1] = -z, y, z, -x, -y, x
    safe = np.where(angle > 0, angle, 1.0)
    k = k / safe
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * (k @ k)


def ga_pose(params: dict[str, np.ndarray], frame: int) -> np.ndarray:
    """[5, 3] axis-angle per joint in FLAME's order: rotation, neck, jaw, left eye, right eye."""
    eyes = np.asarray(params["eyes_pose"][frame], np.float64)
    return np.stack([np.asarray(params[key][frame], np.float64) for key in ("rotation", "neck_pose", "jaw_pose")]
                    + [eyes[:3], eyes[3:]])


def ga_flame_vertices(model_with_teeth: dict[str, np.ndarray], params: dict[str, np.ndarray], frame: int
                      ) -> np.ndarray:
    """GaussianAvatars' FLAME forward for one frame of flame_param (float64): blendshapes (shape + expression),
    static_offset added before the joint regressor, pose correctives, LBS along the kinematic tree, translation.
    (GaussianAvatars does not add dynamic_offset.) -> [V, 3]"""
    dirs = np.asarray(model_with_teeth["shapedirs"], np.float64)
    shape = np.asarray(params["shape"], np.float64).reshape(-1)
    expr = np.asarray(params["expr"][frame], np.float64)
    v_shaped = (np.asarray(model_with_teeth["v_template"], np.float64)
                + dirs[:, :, :len(shape)] @ shape + dirs[:, :, N_SHAPE:N_SHAPE + len(expr)] @ expr)
    if "static_offset" in params:
        v_shaped = v_shaped + np.asarray(params["static_offset"], np.float64).reshape(v_shaped.shape)
    joints = np.asarray(model_with_teeth["J_regressor"], np.float64) @ v_shaped  # [5, 3]
    rot = rodrigues(ga_pose(params, frame))  # [5, 3, 3]
    pose_feature = (rot[1:] - np.eye(3)).reshape(-1)  # [36]
    v_posed = v_shaped + np.asarray(model_with_teeth["posedirs"], np.float64) @ pose_feature
    world_rot, world_pos = [rot[0]], [joints[0]]
    for i in range(1, len(PARENTS)):
        parent = PARENTS[i]
        world_rot.append(world_rot[parent] @ rot[i])
        world_pos.append(world_rot[parent] @ (joints[i] - joints[parent]) + world_pos[parent])
    world_rot, world_pos = np.stack(world_rot), np.stack(world_pos)
    shift = world_pos - np.einsum("jab,jb->ja", world_rot, joints)  # joint k: v -> R_k v + shift_k
    weights = np.asarray(model_with_teeth["weights"], np.float64)
    moved = np.einsum("jab,vb->vja", world_rot, v_posed) + shift[None]  # [V, 5, 3]
    return np.einsum("vj,vja->va", weights, moved) + np.asarray(params["translation"][frame], np.float64)


# ------------------------------------------------------------------------------------------ triangle binding


def _normalize(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def matrix_quat_wxyz(rot: np.ndarray) -> np.ndarray:
    """Rotation matrices [N, 3, 3] -> unit quaternions [N, 4] (w, x, y, z), w >= 0 (q and -q are one rotation)."""
    m = np.asarray(rot, np.float64)
    trace = m[:, 0, 0] + m[:, 1, 1] + m[:, 2, 2]
    candidates = np.stack([  # 4 q_k q, each exact where its |q_k| is largest (Shepperd)
        np.stack([1 + trace, m[:, 2, 1] - m[:, 1, 2], m[:, 0, 2] - m[:, 2, 0], m[:, 1, 0] - m[:, 0, 1]], 1),
        np.stack([m[:, 2, 1] - m[:, 1, 2], 1 + 2 * m[:, 0, 0] - trace, m[:, 0, 1] + m[:, 1, 0],
                  m[:, 0, 2] + m[:, 2, 0]], 1),
        np.stack([m[:, 0, 2] - m[:, 2, 0], m[:, 0, 1] + m[:, 1, 0], 1 + 2 * m[:, 1, 1] - trace,
                  m[:, 1, 2] + m[:, 2, 1]], 1),
        np.stack([m[:, 1, 0] - m[:, 0, 1], m[:, 0, 2] + m[:, 2, 0], m[:, 1, 2] + m[:, 2, 1],
                  1 + 2 * m[:, 2, 2] - trace], 1),
    ], 1)  # [N, 4 candidates, 4]
    diagonal = np.stack([1 + trace, 1 + 2 * m[:, 0, 0] - trace, 1 + 2 * m[:, 1, 1] - trace,
                         1 + 2 * m[:, 2, 2] - trace], 1)
    q = _normalize(candidates[np.arange(len(m)), np.argmax(diagonal, 1)])
    return q * np.where(q[:, :1] < 0, -1.0, 1.0)


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product a (x) b of (w, x, y, z) quaternions [N, 4]."""
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack([aw * bw - ax * bx - ay * by - az * bz,
                     aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw], -1)


def ga_triangle_frames(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """GaussianAvatars' per-triangle frame: rotation [F, 3, 3] (columns a0, a1, a2), scale k [F], centre [F, 3]."""
    tri = np.asarray(vertices, np.float64)[np.asarray(faces, np.int64)]
    v0, v1, v2 = tri[:, 0], tri[:, 1], tri[:, 2]
    a0 = _normalize(v1 - v0)
    a1 = _normalize(np.cross(a0, v2 - v0))
    a2 = -_normalize(np.cross(a1, a0))
    k = (np.linalg.norm(v1 - v0, axis=1) + np.abs((a2 * (v2 - v0)).sum(1))) / 2
    return np.stack([a0, a1, a2], -1), k, tri.mean(1)


def ga_world_gaussians(vertices: np.ndarray, faces: np.ndarray, ply: dict[str, np.ndarray]
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where GaussianAvatars puts each Gaussian on a posed mesh: (xyz [N, 3], scale [N, 3], quat_wxyz [N, 4]).
    `ply` maps the PLY's field names (x, y, z, scale_*, rot_*, binding_0) to their values."""
    rot, k, centre = ga_triangle_frames(vertices, faces)
    binding = np.asarray(ply["binding_0"]).astype(np.int64)
    local = np.stack([np.asarray(ply[c], np.float64) for c in "xyz"], 1)
    log_scale = np.stack([np.asarray(ply[f"scale_{i}"], np.float64) for i in range(3)], 1)
    quat = _normalize(np.stack([np.asarray(ply[f"rot_{i}"], np.float64) for i in range(4)], 1))
    xyz = k[binding, None] * np.einsum("nab,nb->na", rot[binding], local) + centre[binding]
    scale = np.exp(log_scale) * k[binding, None]
    return xyz, scale, quat_multiply(matrix_quat_wxyz(rot[binding]), quat)


# ------------------------------------------------------------------------------------------ the avatar folder


def ply_field_names(sh_degree: int) -> list[str]:
    """GaussianAvatars' point_cloud.ply fields, in order."""
    rest = 3 * ((sh_degree + 1) ** 2 - 1)
    return (["x", "y", "z", "nx", "ny", "nz"] + [f"f_dc_{i}" for i in range(3)] + [f"f_rest_{i}" for i in range(rest)]
            + ["opacity"] + [f"scale_{i}" for i in range(3)] + [f"rot_{i}" for i in range(4)] + ["binding_0"])


def _gaussians(n: int, sh_degree: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Random Gaussians bound to random faces (about 1 in 8 on the teeth), every PLY field float32."""
    n_sh = (sh_degree + 1) ** 2
    teeth = rng.random(n) < 0.125
    binding = np.where(teeth, rng.integers(FLAME_FACES, GA_FACES, n), rng.integers(0, FLAME_FACES, n))
    skin = np.array([0.80, 0.60, 0.50]) + rng.normal(0.0, 0.08, (n, 3))
    rgb = np.where(teeth[:, None], np.array([0.95, 0.94, 0.88]) + rng.normal(0.0, 0.02, (n, 3)), skin)
    f_dc = (np.clip(rgb, 0.02, 0.98) - 0.5) / SH_C0
    f_rest = rng.normal(0.0, 0.05, (n, 3, n_sh - 1)).reshape(n, -1)  # channel-major: index c * (K - 1) + (k - 1)
    rot = _normalize(rng.normal(size=(n, 4))) * rng.uniform(0.5, 2.0, (n, 1))  # not normalised, as trained
    columns = [rng.normal(0.0, 0.3, (n, 3)), np.zeros((n, 3)), f_dc, f_rest, rng.uniform(-2.0, 4.0, (n, 1)),
               np.log(rng.uniform(0.2, 0.8, (n, 3))), rot, binding[:, None].astype(np.float64)]
    values = np.concatenate(columns, 1).astype(np.float32)
    return {name: values[:, i] for i, name in enumerate(ply_field_names(sh_degree))}


def _flame_params(model_with_teeth: dict[str, np.ndarray], frames: int, rng: np.random.Generator
                  ) -> dict[str, np.ndarray]:
    """flame_param.npz's arrays: a smooth clip, the jaw opening over it, a small smooth static_offset."""
    t = np.linspace(0.0, 1.0, frames)[:, None]
    wave = lambda amplitude, dims: amplitude * np.sin(2 * np.pi * t + rng.uniform(0, 2 * np.pi, dims))  # noqa: E731
    points = model_with_teeth["v_template"]
    freq, phase = rng.normal(0.0, 15.0, (3, 3)), rng.uniform(0, 2 * np.pi, 3)
    static = 1.5e-3 * np.sin(points @ freq + phase)  # [V, 3], a few mm at most
    params = {
        "shape": rng.normal(0.0, 0.5, N_SHAPE),
        "expr": wave(rng.uniform(0.1, 0.8, N_EXPR), N_EXPR),
        "rotation": wave(np.array([0.06, 0.12, 0.03]), 3),
        "neck_pose": wave(np.array([0.04, 0.05, 0.02]), 3),
        "jaw_pose": np.concatenate([0.3 * t, wave(np.array([0.01, 0.01]), 2)], 1),  # opens about x
        "eyes_pose": np.tile(wave(np.array([0.05, 0.08, 0.0]), 3), 2),
        "translation": wave(np.array([0.005, 0.004, 0.01]), 3),
        "static_offset": static[None],
        "dynamic_offset": np.zeros((frames, len(points), 3)),
    }
    return {key: value.astype(np.float32) for key, value in params.items()}


def write_gaussian_avatar(
    directory: str | Path,
    flame_model: dict[str, np.ndarray],
    *,
    n_gaussians: int = 2000,
    frames: int = 8,
    sh_degree: int = 3,
    seed: int = 0,
    iteration: int | None = None,
    drop_fields: Iterable[str] = (),
    edit_ply: Callable[[dict[str, np.ndarray]], dict[str, np.ndarray] | None] | None = None,
    edit_params: Callable[[dict[str, np.ndarray]], dict[str, np.ndarray] | None] | None = None,
) -> dict:
    """A GaussianAvatars output folder: point_cloud/iteration_N/{point_cloud.ply, flame_param.npz}.

    drop_fields leaves PLY fields or flame_param keys out; edit_ply / edit_params may change (in place, or by
    returning a new dict) the field -> values / key -> array dicts before they are written, for broken avatars.
    Returns {"ply": fields as written, "params": flame_param as written, "ply_path", "param_path", "iteration"}.
    """
    rng = np.random.default_rng(seed)
    iteration = DEFAULT_ITERATION if iteration is None else iteration
    folder = Path(directory) / "point_cloud" / f"iteration_{iteration}"
    folder.mkdir(parents=True, exist_ok=True)
    ply = _gaussians(n_gaussians, sh_degree, rng)
    params = _flame_params(ga_flame_with_teeth(flame_model), frames, rng)
    drop = set(drop_fields)
    ply = {k: v for k, v in ply.items() if k not in drop}
    params = {k: v for k, v in params.items() if k not in drop}
    if edit_ply is not None:
        ply = edit_ply(ply) or ply
    if edit_params is not None:
        params = edit_params(params) or params
    ply_path, param_path = folder / "point_cloud.ply", folder / "flame_param.npz"
    records = np.empty(len(next(iter(ply.values()))) if ply else 0,
                       dtype=[(name, np.asarray(v).dtype.str) for name, v in ply.items()])
    for name, values in ply.items():
        records[name] = values
    PlyData([PlyElement.describe(records, "vertex")], text=False, byte_order="<").write(str(ply_path))
    with param_path.open("wb") as handle:
        np.savez(handle, **params)
    return {"ply": ply, "params": params, "ply_path": ply_path, "param_path": param_path, "iteration": iteration}


def main(argv: list[str] | None = None) -> None:
    """The script of the module docstring: a synthetic FLAME model and a GaussianAvatars avatar on it under OUT."""
    parser = argparse.ArgumentParser(description="Write a synthetic GaussianAvatars avatar and its FLAME-layout model.")
    parser.add_argument("out", type=Path, help="folder for flame.npz and avatar/")
    parser.add_argument("--gaussians", type=int, default=2000, help="Gaussians in the avatar")
    parser.add_argument("--frames", type=int, default=8, help="frames of its tracked motion")
    parser.add_argument("--sh-degree", type=int, default=3, choices=range(4), help="SH degree of its colours")
    parser.add_argument("--seed", type=int, default=0, help="seed of the model and the avatar")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    model = synthetic_flame(args.seed)
    flame = write_flame_npz(args.out / "flame.npz", model)
    written = write_gaussian_avatar(args.out / "avatar", model, n_gaussians=args.gaussians, frames=args.frames,
                                    sh_degree=args.sh_degree, seed=args.seed)
    print(f"wrote {flame} and {written['ply_path']} ({args.gaussians:,} Gaussians, {args.frames} frames)")


if __name__ == "__main__":
    main()
