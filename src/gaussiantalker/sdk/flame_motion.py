"""FLAME motion: per-frame FLAME parameters (expression, joint rotations, translation), as a tracker writes them.

GaussianAvatars (and the VHAP tracker it builds on) store a tracked sequence as an npz of per-frame arrays:
`expr` [T, E], `rotation`, `neck_pose`, `jaw_pose`, `translation` [T, 3] and `eyes_pose` [T, 6] (left eye, then
right), beside per-avatar entries (`shape`, `static_offset`, ...) that a motion does not use. docs/import.md,
"Motion files". A bundle stores a FLAME speaker's motion as one [T, E + 18] table, `FlameMotion.table`.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .config import POSE_DIM
from .drive import MAX_DRIVE_MAGNITUDE, FrameDrive, HeadPose
from .errors import DriveError
from .motion import resample_at_fps
from .zip_reader import read_npz as _read_npz

# The npz keys of a FLAME motion and their widths (None: the expression count); flame_pose is their concatenation
# rotation | neck | jaw | eyes, in FLAME_JOINTS order.
MOTION_KEYS = (("expr", None), ("rotation", 3), ("neck_pose", 3), ("jaw_pose", 3), ("eyes_pose", 6),
               ("translation", 3))
# Extra columns of a bundle's FLAME motion table after the expression: flame_pose [15], head translation [3].
TABLE_POSE_COLUMNS = POSE_DIM + 3


@dataclass(frozen=True)
class FlameMotion:
    """FLAME parameters per frame: expression [T, E], flame_pose [T, 15] (rotation, neck, jaw, left eye, right
    eye: axis-angle) and head_translation [T, 3], at `fps` frames per second."""

    expression: np.ndarray
    flame_pose: np.ndarray
    head_translation: np.ndarray
    fps: float

    def __post_init__(self) -> None:
        parts = {"expression": self.expression, "flame_pose": self.flame_pose,
                 "head_translation": self.head_translation}
        count = np.asarray(self.expression).shape[0] if np.ndim(self.expression) == 2 else 0
        for name, value in parts.items():
            width = {"flame_pose": POSE_DIM, "head_translation": 3}.get(name)
            object.__setattr__(self, name, _table(name, value, count, width, "FLAME motion"))
        if not (np.isfinite(self.fps) and self.fps > 0):
            raise DriveError(f"motion fps must be positive, got {self.fps}")

    def __len__(self) -> int:
        return int(self.expression.shape[0])

    @property
    def n_expr(self) -> int:
        return int(self.expression.shape[1])

    @property
    def table(self) -> np.ndarray:
        """float32 [T, E + 18]: expression | flame_pose | head_translation (a bundle's `motion_track`)."""
        return np.concatenate([self.expression, self.flame_pose, self.head_translation], axis=1)

    @classmethod
    def from_table(cls, table: np.ndarray, fps: float) -> FlameMotion:
        """Inverse of `table` (the expression count is the width less 18)."""
        table = np.asarray(table)
        if table.ndim != 2 or table.shape[1] <= TABLE_POSE_COLUMNS:
            raise DriveError(f"a FLAME motion table is [T, E + {TABLE_POSE_COLUMNS}], got {list(table.shape)}")
        n_expr = table.shape[1] - TABLE_POSE_COLUMNS
        return cls(table[:, :n_expr], table[:, n_expr:n_expr + POSE_DIM], table[:, n_expr + POSE_DIM:], fps)

    def with_expressions(self, n_expr: int) -> FlameMotion:
        """The motion for a speaker of `n_expr` coefficients: the same, or zero-padded when it has fewer; a
        DriveError when it moves coefficients the speaker does not have."""
        if n_expr == self.n_expr:
            return self
        if n_expr > self.n_expr:
            padded = np.zeros((len(self), n_expr), np.float32)
            padded[:, : self.n_expr] = self.expression
            return FlameMotion(padded, self.flame_pose, self.head_translation, self.fps)
        extra = np.abs(self.expression[:, n_expr:]).max()
        if extra > 0:
            raise DriveError(f"the motion has {self.n_expr} expression coefficients and moves coefficient "
                             f"{n_expr + int(np.argmax(np.abs(self.expression[:, n_expr:]).max(0)))}; this speaker "
                             f"has {n_expr}")
        return FlameMotion(self.expression[:, :n_expr], self.flame_pose, self.head_translation, self.fps)

    def at_fps(self, fps: float) -> FlameMotion:
        """The same motion resampled (linearly in time, every column) to `fps`, covering the same duration."""
        if abs(fps - self.fps) < 1e-9:
            return self
        return FlameMotion.from_table(resample_at_fps(self.table, self.fps, fps), fps)

    def drive(self, index: int, head_pose: HeadPose | None = None) -> FrameDrive:
        """Frame `index` as a FrameDrive (`head_pose` given: it replaces the motion's rotation and translation)."""
        pose = self.flame_pose[index]
        head = head_pose or HeadPose.make(pose[:3], self.head_translation[index])
        return FrameDrive.make(self.n_expr, self.expression[index], jaw_pose=pose[6:9], neck_pose=pose[3:6],
                               eye_pose=pose[9:15], head_pose=head)


def _table(name: str, value: object, count: int, width: int | None, where: str) -> np.ndarray:
    """A finite float32 [count, width] table (width None: any >= 1); DriveError naming `name` otherwise."""
    if isinstance(value, np.ndarray) and value.dtype.kind not in "biuf":
        raise DriveError(f"{where}: {name!r} holds {value.dtype.str} values, not numbers")
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError, OverflowError) as exc:
        raise DriveError(f"{where}: {name!r} must be numbers: {' '.join(str(exc).split())[:120]}") from None
    expected = f"[{count or 'T >= 1'}, {width if width is not None else 'E'}]"
    if array.ndim != 2 or array.shape[0] < 1 or (count and array.shape[0] != count) or \
            (width is not None and array.shape[1] != width) or array.shape[1] < 1:
        raise DriveError(f"{where}: {name!r} has shape {list(array.shape)}, expected {expected}")
    bad = np.argwhere(~np.isfinite(array) | (np.abs(array) > MAX_DRIVE_MAGNITUDE))
    if bad.size:
        row, column = bad[0]
        raise DriveError(f"{where}: {name}[{row}, {column}] = {array[row, column]} is not finite within "
                         f"{MAX_DRIVE_MAGNITUDE:g}")
    return array.astype(np.float32)


def parse_flame_motion(arrays: Mapping[str, np.ndarray], fps: float, where: str = "motion") -> FlameMotion:
    """FLAME motion from GaussianAvatars' per-frame keys (MOTION_KEYS); DriveError naming a missing or mis-shaped
    key. A key with one row less than `expr` is not accepted: every key has a row per frame."""
    missing = [key for key, _ in MOTION_KEYS if key not in arrays]
    if missing:
        raise DriveError(f"{where}: a FLAME motion needs {', '.join(k for k, _ in MOTION_KEYS)}; missing "
                         f"{', '.join(missing)}")
    expr = _table("expr", arrays["expr"], 0, None, where)
    parts = {key: _table(key, arrays[key], expr.shape[0], width, where) for key, width in MOTION_KEYS[1:]}
    pose = np.concatenate([parts["rotation"], parts["neck_pose"], parts["jaw_pose"], parts["eyes_pose"]], axis=1)
    return FlameMotion(expr, pose, parts["translation"], fps)


def read_npz(path: Path, error: type[Exception], what: str, keys: tuple[str, ...] | None = None
             ) -> dict[str, np.ndarray]:
    """The arrays of an npz file (only `keys`, when given), never unpickling, every member's size checked before
    it is read (sdk/zip_reader.py); `error` naming the file and `what` it should be otherwise."""
    return _read_npz(path, error, what, keys)


def load_flame_motion(path: str | os.PathLike, fps: float) -> FlameMotion:
    """Read a FLAME motion npz (GaussianAvatars' `flame_param.npz` or one with the same keys), never unpickling;
    `fps` is its frame rate (the file does not record one). Only the motion's keys are read (a tracked sequence's
    npz also holds per-vertex offsets per frame, which a motion does not use)."""
    arrays = read_npz(Path(path), DriveError, "an npz of per-frame FLAME parameters", tuple(k for k, _ in MOTION_KEYS))
    return parse_flame_motion(arrays, fps, str(path))


__all__ = ["FlameMotion", "MOTION_KEYS", "TABLE_POSE_COLUMNS", "load_flame_motion", "parse_flame_motion", "read_npz"]
