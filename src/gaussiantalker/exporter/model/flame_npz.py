"""A real FLAME model saved as npz (the standard keys, `gt-import flame`'s output) -> FlameArrays, never unpickled
and checked as a user's file (docs/untrusted-input.md, "FLAME npz")."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from gaussiantalker.sdk.config import FLAME_PARENTS
from gaussiantalker.sdk.errors import CheckpointError
from gaussiantalker.sdk.zip_reader import read_npz

from .flame import N_JOINTS, POSE_FEATURE_DIM, FlameArrays, as_float32

# Keys of a real FLAME model saved as npz (generic_model.pkl converted with dense J_regressor).
FLAME_NPZ_KEYS = ("v_template", "f", "shapedirs", "posedirs", "J_regressor", "weights", "kintree_table")
# The largest magnitude a FLAME npz's float arrays may hold (metres, bases, weights: real values are below 10), so
# that nothing overflows float32 or the checks' sums.
NPZ_VALUE_LIMIT = 1e6
# FLAME's shapedirs hold 300 identity-shape columns followed by the expression columns.
FLAME_SHAPE_COLUMNS = 300


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
            v_template=as_float32(raw["v_template"]),
            shapedirs=as_float32(dirs[:, :, :n_shape]),
            exprdirs=as_float32(dirs[:, :, shape_columns : shape_columns + n_expr]),
            posedirs=as_float32(posedirs.reshape(-1, POSE_FEATURE_DIM).T),  # [36, V*3], as smplx does
            J_regressor=as_float32(raw["J_regressor"]),
            lbs_weights=as_float32(raw["weights"]),
            faces=np.ascontiguousarray(raw["f"], dtype=np.int64),
            parents=parents_from_kintree(raw["kintree_table"]),
        ).validate()
    except CheckpointError as exc:  # the layout checks, told with the file they are about
        raise CheckpointError(f"FLAME npz {path}: {exc}") from None


def parents_from_kintree(kintree: np.ndarray) -> tuple[int, ...]:
    """Parent index per joint from FLAME's [2, 5] kintree_table (root parent stored as uint32 max)."""
    if kintree.shape != (2, N_JOINTS) or list(kintree[1]) != list(range(N_JOINTS)):
        raise CheckpointError(f"FLAME npz 'kintree_table' {kintree.tolist()} is not a 5-joint FLAME tree")
    parents = tuple(-1 if i == 0 else int(p) for i, p in enumerate(kintree[0]))
    if parents != FLAME_PARENTS:
        raise CheckpointError(f"FLAME npz 'kintree_table' gives parents {parents}, expected {FLAME_PARENTS}")
    return parents
