"""FLAME head model: its arrays, a real-FLAME npz loader, the teeth extension, and torch blendshapes + LBS.

The torch side (`rodrigues`, `lbs`, `FlameLayer`) is a pure function of tensors built from common ONNX ops
(matmul, sin, sqrt, reshape, stack), so it exports with a dynamic batch and mirrors smplx/FLAME numerically:

    v_shaped = v_template + shapedirs·β + exprdirs·ε                      # [B, V, 3]
    J        = J_regressor · v_shaped                                     # [B, 5, 3]
    v_posed  = v_shaped + ((R_j − I) for the 4 non-root joints)·posedirs  # [B, V, 3]
    v        = Σ_k w_k (G_k · v_posed)                                    # forward kinematics along parents
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch
from torch import nn

from gaussiantalker.sdk.config import FLAME_JOINTS, FLAME_PARENTS
from gaussiantalker.sdk.errors import CheckpointError
from gaussiantalker.sdk.zip_reader import read_npz

N_JOINTS = len(FLAME_JOINTS)
POSE_FEATURE_DIM = 9 * (N_JOINTS - 1)  # (R_j - I) flattened for neck, jaw, left_eye, right_eye
# Rodrigues guard: angle = sqrt(|r|^2 + eps) keeps the axis, the angle and their gradients finite at r = 0.
ANGLE_EPS = 1e-16
# Row sums of the skinning weights must be 1 within this tolerance.
WEIGHT_SUM_TOL = 1e-3

# Keys of a real FLAME model saved as npz (generic_model.pkl converted with dense J_regressor).
FLAME_NPZ_KEYS = ("v_template", "f", "shapedirs", "posedirs", "J_regressor", "weights", "kintree_table")
# The largest magnitude a FLAME npz's float arrays may hold (metres, bases, weights: real values are below 10), so
# that nothing overflows float32 or the checks' sums.
NPZ_VALUE_LIMIT = 1e6
# FLAME's shapedirs hold 300 identity-shape columns followed by the expression columns.
FLAME_SHAPE_COLUMNS = 300

TEETH_REGION = "teeth"
MOUTH_INTERIOR_REGION = "mouth_interior"
BASE_REGION = "skin"

_FLOAT_KEYS = ("v_template", "shapedirs", "exprdirs", "posedirs", "J_regressor", "lbs_weights")


def _empty_index() -> np.ndarray:
    return np.zeros(0, dtype=np.int64)


@dataclass
class FlameArrays:
    """A FLAME-structured head model as numpy arrays (float32 unless noted), shared by torch and bundle."""

    v_template: np.ndarray  # [V, 3]
    shapedirs: np.ndarray  # [V, 3, n_shape]
    exprdirs: np.ndarray  # [V, 3, n_expr]
    posedirs: np.ndarray  # [36, V*3]
    J_regressor: np.ndarray  # [5, V]
    lbs_weights: np.ndarray  # [V, 5]
    faces: np.ndarray  # [F, 3] int64
    parents: tuple[int, ...] = FLAME_PARENTS
    regions: np.ndarray | None = None  # [F] int64 label per face, an index into region_names
    region_names: tuple[str, ...] = ()
    # The last T vertices are the teeth extension; teeth_anchors[t] is the lip vertex vertex V-T+t copies.
    teeth_anchors: np.ndarray = field(default_factory=_empty_index)  # [T] int64

    @property
    def n_vertices(self) -> int:
        return int(self.v_template.shape[0])

    @property
    def n_faces(self) -> int:
        return int(self.faces.shape[0])

    @property
    def n_shape(self) -> int:
        return int(self.shapedirs.shape[2])

    @property
    def n_expr(self) -> int:
        return int(self.exprdirs.shape[2])

    @property
    def n_base_vertices(self) -> int:
        """Vertices of the head proper (everything before the teeth extension)."""
        return self.n_vertices - int(self.teeth_anchors.shape[0])

    def validate(self) -> FlameArrays:
        """Check dtypes, shapes, finiteness and index ranges; raise CheckpointError naming the bad key."""
        n_v = _check_array("v_template", self.v_template, np.float32, (None, 3))[0]
        _check_array("shapedirs", self.shapedirs, np.float32, (n_v, 3, None))
        _check_array("exprdirs", self.exprdirs, np.float32, (n_v, 3, None))
        _check_array("posedirs", self.posedirs, np.float32, (POSE_FEATURE_DIM, n_v * 3))
        _check_array("J_regressor", self.J_regressor, np.float32, (N_JOINTS, n_v))
        _check_array("lbs_weights", self.lbs_weights, np.float32, (n_v, N_JOINTS))
        n_f = _check_array("faces", self.faces, np.int64, (None, 3))[0]
        if tuple(int(p) for p in self.parents) != FLAME_PARENTS:
            raise CheckpointError(f"FLAME 'parents' is {tuple(self.parents)}, expected {FLAME_PARENTS}")
        if n_f and (self.faces.min() < 0 or self.faces.max() >= n_v):
            raise CheckpointError(f"FLAME 'faces' index vertices outside [0, {n_v})")
        row_sums = self.lbs_weights.sum(axis=1)
        if np.abs(row_sums - 1.0).max(initial=0.0) > WEIGHT_SUM_TOL:
            raise CheckpointError("FLAME 'lbs_weights' rows must sum to 1")
        self._validate_regions(n_f)
        self._validate_teeth(n_v)
        return self

    def _validate_regions(self, n_f: int) -> None:
        if self.regions is None:
            return
        _check_array("regions", self.regions, np.int64, (n_f,))
        n_names = len(self.region_names)
        if n_f and (self.regions.min() < 0 or (n_names and self.regions.max() >= n_names)):
            raise CheckpointError(f"FLAME 'regions' labels must lie in [0, {n_names}) (region_names)")

    def _validate_teeth(self, n_v: int) -> None:
        n_t = _check_array("teeth_anchors", self.teeth_anchors, np.int64, (None,))[0]
        if n_t > n_v:
            raise CheckpointError(f"FLAME 'teeth_anchors' has {n_t} entries for {n_v} vertices")
        if n_t and (self.teeth_anchors.min() < 0 or self.teeth_anchors.max() >= n_v - n_t):
            raise CheckpointError("FLAME 'teeth_anchors' must index vertices of the head proper")

    def to_dict(self) -> dict:
        """Plain dict of numpy arrays, ints and strings (for a weights-only checkpoint or a bundle)."""
        data = {key: getattr(self, key) for key in (*_FLOAT_KEYS, "faces", "teeth_anchors")}
        data["parents"] = [int(p) for p in self.parents]
        data["region_names"] = list(self.region_names)
        if self.regions is not None:
            data["regions"] = self.regions
        return data

    @classmethod
    def from_dict(cls, data: Mapping) -> FlameArrays:
        """Inverse of `to_dict` (numpy arrays or CPU tensors), validated; CheckpointError on bad input."""
        missing = [key for key in (*_FLOAT_KEYS, "faces") if key not in data]
        if missing:
            raise CheckpointError(f"FLAME model is missing keys: {missing}")
        arrays = {key: np.asarray(data[key], dtype=np.float32) for key in _FLOAT_KEYS}
        regions = data.get("regions")
        return cls(
            **arrays,
            faces=np.asarray(data["faces"], dtype=np.int64),
            parents=tuple(int(p) for p in data.get("parents", FLAME_PARENTS)),
            regions=None if regions is None else np.asarray(regions, dtype=np.int64),
            region_names=tuple(str(n) for n in data.get("region_names", ())),
            teeth_anchors=np.asarray(data.get("teeth_anchors", _empty_index()), dtype=np.int64).reshape(-1),
        ).validate()


def _check_array(key: str, value: object, dtype: type, shape: tuple[int | None, ...]) -> tuple[int, ...]:
    """Raise CheckpointError unless `value` is a finite ndarray of `dtype` matching `shape` (None = any)."""
    if not isinstance(value, np.ndarray):
        raise CheckpointError(f"FLAME {key!r} must be a numpy array, got {type(value).__name__}")
    if value.dtype != dtype:
        raise CheckpointError(f"FLAME {key!r} has dtype {value.dtype}, expected {np.dtype(dtype)}")
    ok = value.ndim == len(shape) and all(w in (None, g) for g, w in zip(value.shape, shape, strict=False))
    if not ok:
        expected = "[" + ", ".join("*" if s is None else str(s) for s in shape) + "]"
        raise CheckpointError(f"FLAME {key!r} has shape {list(value.shape)}, expected {expected}")
    if value.dtype.kind == "f" and not np.isfinite(value).all():
        raise CheckpointError(f"FLAME {key!r} contains non-finite values")
    return tuple(value.shape)


# ----------------------------------------------------------------------------------------------- npz loader


def load_flame_npz(
    path: str | Path, n_shape: int, n_expr: int, *, shape_columns: int = FLAME_SHAPE_COLUMNS
) -> FlameArrays:
    """Load a real FLAME model saved as npz (standard keys), never unpickling, truncated to n_shape/n_expr. The file
    is the user's: its members' sizes are checked before they are read, and every array must be numbers
    (docs/untrusted-input.md, "FLAME npz")."""
    raw = read_npz(Path(path), CheckpointError, "a FLAME model npz", FLAME_NPZ_KEYS)
    missing = [key for key in FLAME_NPZ_KEYS if key not in raw]
    if missing:
        raise CheckpointError(f"FLAME npz {path} is missing keys: {missing}")
    for key, value in raw.items():
        whole = key in ("f", "kintree_table")
        if value.dtype.kind not in "biuf":
            raise CheckpointError(f"FLAME npz {path}: {key!r} holds {value.dtype.str} values, not numbers")
        if value.dtype.kind == "f" and value.size and not (
                np.isfinite(value).all() and float(np.abs(value).max()) <= (2.0**53 if whole else NPZ_VALUE_LIMIT)
                and (not whole or np.array_equal(value, np.round(value)))):
            raise CheckpointError(f"FLAME npz {path}: {key!r} must hold finite "
                                  f"{'whole numbers' if whole else f'numbers within {NPZ_VALUE_LIMIT:g}'}")
    dirs = raw["shapedirs"]
    if dirs.ndim != 3 or dirs.shape[1] != 3:
        raise CheckpointError(f"FLAME npz {path}: 'shapedirs' has shape {list(dirs.shape)}, expected [V, 3, K]")
    n_expr_avail = dirs.shape[2] - shape_columns
    if not (0 <= n_shape <= shape_columns and 0 <= n_expr <= n_expr_avail):
        raise CheckpointError(
            f"FLAME npz {path}: 'shapedirs' has {shape_columns} shape / {n_expr_avail} expression columns; "
            f"asked for {n_shape} / {n_expr}"
        )
    posedirs = raw["posedirs"]
    if posedirs.ndim != 3 or posedirs.shape[1:] != (3, POSE_FEATURE_DIM):
        raise CheckpointError(f"FLAME npz {path}: 'posedirs' has shape {list(posedirs.shape)}, expected [V, 3, 36]")
    if raw["kintree_table"].shape != (2, N_JOINTS):
        raise CheckpointError(f"FLAME npz {path}: 'kintree_table' has shape {list(raw['kintree_table'].shape)}, "
                              f"expected [2, {N_JOINTS}]")
    try:
        return FlameArrays(
            v_template=_f32(raw["v_template"]),
            shapedirs=_f32(dirs[:, :, :n_shape]),
            exprdirs=_f32(dirs[:, :, shape_columns : shape_columns + n_expr]),
            posedirs=_f32(posedirs.reshape(-1, POSE_FEATURE_DIM).T),  # [36, V*3], as smplx does
            J_regressor=_f32(raw["J_regressor"]),
            lbs_weights=_f32(raw["weights"]),
            faces=np.ascontiguousarray(raw["f"], dtype=np.int64),
            parents=parents_from_kintree(raw["kintree_table"]),
        ).validate()
    except CheckpointError as exc:  # the layout checks, told with the file they are about
        raise CheckpointError(f"FLAME npz {path}: {exc}") from None


def _f32(array: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(array, dtype=np.float32)


def parents_from_kintree(kintree: np.ndarray) -> tuple[int, ...]:
    """Parent index per joint from FLAME's [2, 5] kintree_table (root parent stored as uint32 max)."""
    if kintree.shape != (2, N_JOINTS) or list(kintree[1]) != list(range(N_JOINTS)):
        raise CheckpointError(f"FLAME npz 'kintree_table' {kintree.tolist()} is not a 5-joint FLAME tree")
    parents = tuple(-1 if i == 0 else int(p) for i, p in enumerate(kintree[0]))
    if parents != FLAME_PARENTS:
        raise CheckpointError(f"FLAME npz 'kintree_table' gives parents {parents}, expected {FLAME_PARENTS}")
    return parents


# ------------------------------------------------------------------------------------------ teeth extension


def add_teeth(
    arrays: FlameArrays,
    upper_lip_idx: Sequence[int],
    lower_lip_idx: Sequence[int],
    depth: float,
    height: float,
    *,
    interior: bool = True,
) -> FlameArrays:
    """Append upper/lower teeth (and a closed dark mouth pocket) that move in sync with their anchor lip rows.

    The lip rows run along the mouth in the same order (equal length). Each new vertex copies its anchor's
    shapedirs/exprdirs/posedirs rows and LBS weights and has no J_regressor weight, so it gets no blendshapes
    or skinning of its own (paper, Implementation Details); only its template position differs.
    depth/height are in metres, in FLAME's frame (y up, face toward +z): teeth sit `depth` behind the lip line.
    """
    upper = np.asarray(upper_lip_idx, dtype=np.int64)
    lower = np.asarray(lower_lip_idx, dtype=np.int64)
    n_v = arrays.n_vertices
    if upper.ndim != 1 or upper.shape != lower.shape or upper.size < 2:
        raise ValueError("upper_lip_idx and lower_lip_idx must be equal-length rows of at least 2 vertices")
    if min(upper.min(), lower.min()) < 0 or max(upper.max(), lower.max()) >= n_v:
        raise ValueError(f"lip vertex indices must lie in [0, {n_v})")
    rows, strips, corners = _teeth_layout(upper, lower, depth, height, interior)
    return _append_anchored(arrays, rows, strips, corners)


# A row is (anchor vertex per entry [n], template offset from the anchor [3]); a strip joins two rows with
# quads and has a region name and the direction its normals should face.
_Row = tuple[np.ndarray, np.ndarray]
_Strip = tuple[str, int, int, tuple[float, float, float]]
# A single triangle given as three (row, entry) references (entry -1: the row's last), with its region name.
_Corner = tuple[str, tuple[tuple[int, int], tuple[int, int], tuple[int, int]]]


def _teeth_layout(
    upper: np.ndarray, lower: np.ndarray, depth: float, height: float, interior: bool
) -> tuple[list[_Row], list[_Strip], list[_Corner]]:
    """Rows of new vertices behind the lip rows, the strips (teeth faces, inner pocket) joining them and the
    single triangles closing the pocket's sides."""
    back = np.array([0.0, 0.0, -1.0])
    up = np.array([0.0, 1.0, 0.0])
    lower_depth = 1.25 * depth  # lower incisors sit behind the upper ones (overbite), so they never z-fight
    rows: list[_Row] = [
        (upper, height * up + depth * back),  # 0: upper gum line, hidden behind the upper lip
        (upper, -0.25 * height * up + depth * back),  # 1: upper incisal edge, just below the lip line
        (upper, -0.25 * height * up + 2.0 * depth * back),  # 2: upper biting surface
        (lower, -height * up + lower_depth * back),  # 3: lower gum line
        (lower, 0.1 * height * up + lower_depth * back),  # 4: lower incisal edge
        (lower, 0.1 * height * up + (lower_depth + depth) * back),  # 5: lower biting surface
    ]
    strips: list[_Strip] = [
        (TEETH_REGION, 0, 1, (0.0, 0.0, 1.0)),
        (TEETH_REGION, 1, 2, (0.0, -1.0, 0.0)),
        (TEETH_REGION, 3, 4, (0.0, 0.0, 1.0)),
        (TEETH_REGION, 4, 5, (0.0, 1.0, 0.0)),
    ]
    corners: list[_Corner] = []
    if interior:  # a closed dark pocket behind the lips that stretches as the jaw opens (docs/demo-speaker.md):
        rows.append((upper, 1.5 * height * up + 3.0 * depth * back))  # 6: top of the back wall
        rows.append((lower, -1.5 * height * up + 3.0 * depth * back))  # 7: bottom of the back wall
        rows.append((upper, 0.0 * up))  # 8: the upper lip's inner edge (a copy of the lip row)
        rows.append((lower, 0.0 * up))  # 9: the lower lip's inner edge
        strips.append((MOUTH_INTERIOR_REGION, 6, 7, (0.0, 0.0, 1.0)))  # back wall
        strips.append((MOUTH_INTERIOR_REGION, 8, 6, (0.0, -1.0, 0.0)))  # roof, from the upper lip to the wall
        strips.append((MOUTH_INTERIOR_REGION, 9, 7, (0.0, 1.0, 0.0)))  # floor, from the lower lip to the wall
        # Side walls at each mouth corner, where the lip rows meet: (lip corner, wall top, wall bottom).
        corners = [(MOUTH_INTERIOR_REGION, ((8, end), (6, end), (7, end))) for end in (0, -1)]
    return rows, strips, corners


def _append_anchored(arrays: FlameArrays, rows: list[_Row], strips: list[_Strip], corners: list[_Corner] = ()
                     ) -> FlameArrays:
    """Append the rows as anchored vertex copies and the strips and corner triangles as faces with their region
    labels."""
    names = list(arrays.region_names) or [BASE_REGION]
    regions = arrays.regions if arrays.regions is not None else np.zeros(arrays.n_faces, dtype=np.int64)
    anchor_idx = np.concatenate([anchor for anchor, _ in rows])  # [T]
    positions = np.concatenate([arrays.v_template[anchor] + offset for anchor, offset in rows])  # [T, 3]
    starts = arrays.n_vertices + np.cumsum([0] + [anchor.size for anchor, _ in rows])
    all_pos = np.concatenate([arrays.v_template, positions])
    new_faces, new_regions = [], []
    for region, row_a, row_b, facing in strips:
        if region not in names:
            names.append(region)
        ids_a = np.arange(starts[row_a], starts[row_a + 1])
        ids_b = np.arange(starts[row_b], starts[row_b + 1])
        faces = _orient(_strip_faces(ids_a, ids_b), all_pos, np.asarray(facing))
        new_faces.append(faces)
        new_regions.append(np.full(len(faces), names.index(region), dtype=np.int64))
    for region, refs in corners:
        if region not in names:
            names.append(region)
        new_faces.append(np.array([[starts[row] + entry % rows[row][0].size for row, entry in refs]], np.int64))
        new_regions.append(np.array([names.index(region)], np.int64))
    return _with_vertices(arrays, anchor_idx, positions, new_faces, new_regions, names, regions)


def _strip_faces(row_a: np.ndarray, row_b: np.ndarray) -> np.ndarray:
    """Two triangles per quad between two equal-length vertex rows. -> [2(n-1), 3] int64"""
    a0, a1, b0, b1 = row_a[:-1], row_a[1:], row_b[:-1], row_b[1:]
    return np.concatenate([np.stack([a0, a1, b1], 1), np.stack([a0, b1, b0], 1)]).astype(np.int64)


def _orient(faces: np.ndarray, positions: np.ndarray, facing: np.ndarray) -> np.ndarray:
    """Flip a strip's winding so its mean normal points along `facing`."""
    p = positions[faces]  # [F, 3, 3]
    normals = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    return faces[:, ::-1].copy() if normals.sum(0) @ facing < 0 else faces


def _with_vertices(
    arrays: FlameArrays,
    anchor_idx: np.ndarray,
    positions: np.ndarray,
    new_faces: list[np.ndarray],
    new_regions: list[np.ndarray],
    names: list[str],
    regions: np.ndarray,
) -> FlameArrays:
    """New FlameArrays with vertices appended that copy every per-vertex basis row of their anchors."""
    pose_cols = (3 * anchor_idx[:, None] + np.arange(3)).reshape(-1)  # posedirs columns of the anchors
    j_reg = np.concatenate([arrays.J_regressor, np.zeros((N_JOINTS, anchor_idx.size), np.float32)], 1)
    return replace(
        arrays,
        v_template=_f32(np.concatenate([arrays.v_template, positions])),
        shapedirs=_f32(np.concatenate([arrays.shapedirs, arrays.shapedirs[anchor_idx]])),
        exprdirs=_f32(np.concatenate([arrays.exprdirs, arrays.exprdirs[anchor_idx]])),
        posedirs=_f32(np.concatenate([arrays.posedirs, arrays.posedirs[:, pose_cols]], 1)),
        J_regressor=_f32(j_reg),
        lbs_weights=_f32(np.concatenate([arrays.lbs_weights, arrays.lbs_weights[anchor_idx]])),
        faces=np.concatenate([arrays.faces, *new_faces]).astype(np.int64),
        regions=np.concatenate([regions, *new_regions]).astype(np.int64),
        region_names=tuple(names),
        teeth_anchors=np.concatenate([arrays.teeth_anchors, anchor_idx]).astype(np.int64),
    ).validate()


# -------------------------------------------------------------------------------------------- torch layer


def rodrigues(rotvec: torch.Tensor) -> torch.Tensor:
    """Axis-angle [N, 3] -> rotation matrices [N, 3, 3]; finite (with finite gradients) at 0 and any angle."""
    angle = torch.sqrt((rotvec * rotvec).sum(dim=1, keepdim=True) + ANGLE_EPS)  # [N, 1]
    axis = rotvec / angle  # [N, 3]; ~0 (not NaN) at zero rotation, where sin(angle) ~ angle restores scale
    x, y, z = axis[:, 0], axis[:, 1], axis[:, 2]
    zero = torch.zeros_like(x)
    k = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], dim=1).reshape(-1, 3, 3)  # [N, 3, 3] [axis]x
    sin = torch.sin(angle).unsqueeze(2)  # [N, 1, 1]
    half = torch.sin(0.5 * angle).unsqueeze(2)
    eye = torch.eye(3, dtype=rotvec.dtype, device=rotvec.device)
    return eye + sin * k + (2.0 * half * half) * torch.matmul(k, k)  # 1 - cos = 2 sin^2(a/2), no cancellation


def blend_shapes(coeffs: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """Linear blendshape offsets: coeffs [B, L] · dirs [V, 3, L] -> [B, V, 3]."""
    n_v = dirs.shape[0]
    flat = dirs.reshape(n_v * 3, dirs.shape[2])  # [V*3, L]
    return torch.matmul(coeffs, flat.transpose(0, 1)).reshape(coeffs.shape[0], n_v, 3)


def forward_kinematics(
    rot: torch.Tensor, joints: torch.Tensor, parents: Sequence[int]
) -> tuple[torch.Tensor, torch.Tensor]:
    """World rotations [B, J, 3, 3] and posed joints [B, J, 3] from local rotations and rest joints."""
    world_rot = [rot[:, 0]]
    world_pos = [joints[:, 0]]
    for i in range(1, len(parents)):
        p = parents[i]
        offset = (joints[:, i] - joints[:, p]).unsqueeze(2)  # [B, 3, 1]
        world_rot.append(torch.matmul(world_rot[p], rot[:, i]))
        world_pos.append(torch.matmul(world_rot[p], offset).squeeze(2) + world_pos[p])
    return torch.stack(world_rot, dim=1), torch.stack(world_pos, dim=1)


def lbs(
    v_template: torch.Tensor,
    shapedirs: torch.Tensor,
    exprdirs: torch.Tensor,
    posedirs: torch.Tensor,
    J_regressor: torch.Tensor,
    parents: Sequence[int],
    lbs_weights: torch.Tensor,
    shape: torch.Tensor,
    expression: torch.Tensor,
    pose: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """FLAME blendshapes + linear blend skinning -> (vertices [B, V, 3], posed joints [B, 5, 3]).

    shape [B, n_shape], expression [B, n_expr], pose [B, 15] axis-angle per joint in FLAME_JOINTS order.
    `parents` is the static kinematic tree (python ints), so the graph has no data-dependent control flow.
    """
    _check_parents(parents)
    batch = pose.shape[0]
    n_v = v_template.shape[0]
    n_j = len(parents)
    v_shaped = v_template.unsqueeze(0) + blend_shapes(shape, shapedirs) + blend_shapes(expression, exprdirs)
    joints = torch.matmul(J_regressor, v_shaped)  # [J, V] @ [B, V, 3] -> [B, J, 3]
    rot = rodrigues(pose.reshape(-1, 3)).reshape(batch, n_j, 3, 3)  # [B, J, 3, 3]
    eye = torch.eye(3, dtype=pose.dtype, device=pose.device)
    pose_feature = (rot[:, 1:] - eye).reshape(batch, 9 * (n_j - 1))  # [B, 36]
    v_posed = v_shaped + torch.matmul(pose_feature, posedirs).reshape(batch, n_v, 3)  # [B, V, 3]
    world_rot, world_pos = forward_kinematics(rot, joints, parents)
    # Joint k moves a rest point v to world_rot_k (v - J_k) + world_pos_k.
    skin_t = world_pos - torch.matmul(world_rot, joints.unsqueeze(3)).squeeze(3)  # [B, J, 3]
    blend_rot = torch.matmul(lbs_weights, world_rot.reshape(batch, n_j, 9)).reshape(batch, n_v, 3, 3)
    blend_t = torch.matmul(lbs_weights, skin_t)  # [V, J] @ [B, J, 3] -> [B, V, 3]
    vertices = torch.matmul(blend_rot, v_posed.unsqueeze(3)).squeeze(3) + blend_t
    return vertices, world_pos


def _check_parents(parents: Sequence[int]) -> None:
    """The tree must be topologically ordered with the root first (static check, not traced)."""
    if len(parents) < 1 or parents[0] != -1 or any(not 0 <= p < i for i, p in enumerate(parents) if i):
        raise ValueError(f"parents {tuple(parents)} is not a root-first kinematic tree")


class FlameLayer(nn.Module):
    """FLAME as a torch module: every basis a buffer; forward(shape, expression, pose, translation)."""

    def __init__(self, arrays: FlameArrays) -> None:
        super().__init__()
        arrays.validate()
        for key in _FLOAT_KEYS:
            self.register_buffer(key, torch.from_numpy(np.array(getattr(arrays, key), dtype=np.float32)))
        self.register_buffer("faces", torch.from_numpy(np.array(arrays.faces, dtype=np.int64)))
        self.parents = tuple(int(p) for p in arrays.parents)
        self.n_shape = arrays.n_shape
        self.n_expr = arrays.n_expr

    def posed(
        self, shape: torch.Tensor, expression: torch.Tensor, pose: torch.Tensor, translation: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Vertices [B, V, 3] and posed joints [B, 5, 3], both shifted by translation [B, 3]."""
        vertices, joints = lbs(
            self.v_template,
            self.shapedirs,
            self.exprdirs,
            self.posedirs,
            self.J_regressor,
            self.parents,
            self.lbs_weights,
            shape,
            expression,
            pose,
        )
        offset = translation.unsqueeze(1)  # [B, 1, 3]
        return vertices + offset, joints + offset

    def forward(
        self, shape: torch.Tensor, expression: torch.Tensor, pose: torch.Tensor, translation: torch.Tensor
    ) -> torch.Tensor:
        """Posed mesh vertices [B, V, 3] (translation added after LBS)."""
        return self.posed(shape, expression, pose, translation)[0]
