"""FLAME head model as numpy arrays: `FlameArrays` (template, bases, skinning, faces, regions, the teeth
extension's anchors), its validation and its plain-dict form, shared by the torch layer (flame_lbs.py), the
checkpoint and the bundle. Reading a real FLAME npz: flame_npz.py; adding teeth: flame_teeth.py."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from gaussiantalker.sdk.config import FLAME_JOINTS, FLAME_PARENTS
from gaussiantalker.sdk.errors import CheckpointError

N_JOINTS = len(FLAME_JOINTS)
POSE_FEATURE_DIM = 9 * (N_JOINTS - 1)  # (R_j - I) flattened for neck, jaw, left_eye, right_eye
# Row sums of the skinning weights must be 1 within this tolerance.
WEIGHT_SUM_TOL = 1e-3
# The float32 arrays of a FlameArrays, by field name (each a buffer of the torch layer).
FLAME_FLOAT_KEYS = ("v_template", "shapedirs", "exprdirs", "posedirs", "J_regressor", "lbs_weights")


def _empty_index() -> np.ndarray:
    return np.zeros(0, dtype=np.int64)


def as_float32(array: np.ndarray) -> np.ndarray:
    """`array` as a contiguous float32 array (FlameArrays' float layout)."""
    return np.ascontiguousarray(array, dtype=np.float32)


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
        data = {key: getattr(self, key) for key in (*FLAME_FLOAT_KEYS, "faces", "teeth_anchors")}
        data["parents"] = [int(p) for p in self.parents]
        data["region_names"] = list(self.region_names)
        if self.regions is not None:
            data["regions"] = self.regions
        return data

    @classmethod
    def from_dict(cls, data: Mapping) -> FlameArrays:
        """Inverse of `to_dict` (numpy arrays or CPU tensors), validated; CheckpointError on bad input."""
        missing = [key for key in (*FLAME_FLOAT_KEYS, "faces") if key not in data]
        if missing:
            raise CheckpointError(f"FLAME model is missing keys: {missing}")
        arrays = {key: np.asarray(data[key], dtype=np.float32) for key in FLAME_FLOAT_KEYS}
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
