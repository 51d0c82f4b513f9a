"""Per-frame drive parameters, validated and packed for the deformation graph, one kind per rig (sdk/rig.py).

A FLAME speaker's graph takes `expression [B, n_expr]`, `flame_pose [B, 15]` (axis-angle per FLAME joint:
global = head rotation, neck, jaw, left eye, right eye) and `head_translation [B, 3]` (`FrameDrive`); an ARKit
speaker's takes `blendshapes [B, 52]`, `head_rotation [B, 3]` and `head_translation [B, 3]` (`BlendshapeDrive`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .config import POSE_DIM
from .errors import DriveError
from .rig import ARKIT_BLENDSHAPES, ARKIT_RIG, FLAME_RIG

# Largest magnitude accepted for any drive value: far beyond anatomy (FLAME units are sigma / radians / metres),
# small enough that no intermediate product overflows float32.
MAX_DRIVE_MAGNITUDE = 1e4


def _within_magnitude(values: np.ndarray) -> bool:
    """Whether every value is finite and within MAX_DRIVE_MAGNITUDE, in one reduction (NaN propagates through the
    maximum and compares False; an empty array passes)."""
    return bool(np.maximum.reduce(np.abs(values), initial=0.0) <= MAX_DRIVE_MAGNITUDE)


def _vector(name: str, value, size: int | None) -> np.ndarray:
    """Validated float32 copy of one drive field (`size` None: any length); DriveError naming field and limit."""
    if value is None:
        if size is None:
            raise DriveError(f"{name} is missing")
        return np.zeros(size, np.float32)
    if isinstance(value, np.ndarray) and value.dtype == np.float32 and value.ndim == 1 and \
            (size is None or value.shape[0] == size) and _within_magnitude(value):
        return value.copy()  # the usual case (a driver's own rows), in one pass
    try:  # float64 first: a finite value too large for float32 must read as "too large", not as "inf"
        array = np.asarray(value)
        if np.iscomplexobj(array):
            raise TypeError("complex values")
        array = array.astype(np.float64)
    except (TypeError, ValueError) as exc:
        raise DriveError(f"{name} must be an array of real numbers, got {type(value).__name__}: {exc}") from exc
    if array.ndim != 1 or (size is not None and array.shape != (size,)):
        raise DriveError(f"{name} must have shape ({'N' if size is None else size},), got {tuple(array.shape)}")
    if (np.abs(array) <= MAX_DRIVE_MAGNITUDE).all():  # one pass for the usual case (NaN compares False)
        return array.astype(np.float32)
    bad = np.flatnonzero(~np.isfinite(array))
    if bad.size:
        raise DriveError(f"{name} has non-finite values: {name}[{bad[0]}] = {array[bad[0]]} "
                         f"({bad.size} of {array.size} entries)")
    over = np.flatnonzero(np.abs(array) > MAX_DRIVE_MAGNITUDE)
    if over.size:
        raise DriveError(f"{name} exceeds the supported magnitude {MAX_DRIVE_MAGNITUDE:g}: "
                         f"{name}[{over[0]}] = {array[over[0]]:.6g}")
    return array.astype(np.float32)


def _is_checked_row(values, size: int) -> bool:
    """Whether `values` is a float32 [size] array of finite values within MAX_DRIVE_MAGNITUDE: the whole check of
    a driver's own row."""
    return isinstance(values, np.ndarray) and values.dtype == np.float32 and values.shape == (size,) and \
        _within_magnitude(values)


def _unchecked(cls, **fields):
    """A frozen drive dataclass from fields the caller has checked as a whole (a row, a track) instead of one
    check per field: a live server makes a drive per session and frame (docs/live.md, "Load on replicas")."""
    made = object.__new__(cls)
    for name, value in fields.items():
        object.__setattr__(made, name, value)
    return made


@dataclass(frozen=True)
class HeadPose:
    """Rigid head pose: FLAME global rotation (axis-angle, radians) and translation (metres)."""

    rotation: np.ndarray
    translation: np.ndarray

    def __post_init__(self) -> None:
        """Validate even when built directly (not through `make`), so no NaN reaches a graph."""
        object.__setattr__(self, "rotation", _vector("head rotation", self.rotation, 3))
        object.__setattr__(self, "translation", _vector("head translation", self.translation, 3))

    @classmethod
    def make(cls, rotation=None, translation=None) -> HeadPose:
        """Validated head pose; omitted parts are zero (identity rotation, no translation)."""
        return cls(rotation, translation)


@dataclass(frozen=True)
class FrameDrive:
    """Everything that drives one frame, validated: expression, jaw/neck/eye pose and head pose."""

    expression: np.ndarray  # [n_expr]
    flame_pose: np.ndarray  # [15]
    head_translation: np.ndarray  # [3]
    rig = FLAME_RIG

    def __post_init__(self) -> None:
        """Validate even when built directly (not through `make`), so no NaN reaches a graph."""
        object.__setattr__(self, "expression", _vector("expression", self.expression, None))
        object.__setattr__(self, "flame_pose", _vector("flame pose", self.flame_pose, POSE_DIM))
        object.__setattr__(self, "head_translation", _vector("head translation", self.head_translation, 3))

    @classmethod
    def make(cls, n_expr: int, expression=None, jaw_pose=None, neck_pose=None, eye_pose=None,
             head_pose: HeadPose | None = None) -> FrameDrive:
        """Validate and pack; omitted parts are zero (neutral face, identity head pose)."""
        head_pose = head_pose or HeadPose.make()
        flame_pose = np.concatenate([
            head_pose.rotation, _vector("neck pose", neck_pose, 3), _vector("jaw pose", jaw_pose, 3),
            _vector("eye pose", eye_pose, 6)])
        assert flame_pose.shape == (POSE_DIM,)
        return cls(_vector("expression", expression, n_expr), flame_pose, head_pose.translation)

    def graph_inputs(self) -> dict[str, np.ndarray]:
        """Inputs of the deformation graph for a batch of one frame."""
        return {"expression": self.expression[None], "flame_pose": self.flame_pose[None],
                "head_translation": self.head_translation[None]}


def blendshape_vector(weights, names: tuple[str, ...] = ARKIT_BLENDSHAPES) -> np.ndarray:
    """float32 [len(names)] from a {name: weight} mapping (names left out are 0) or an array in `names` order;
    DriveError naming an unknown name, a wrong length or a bad value."""
    if isinstance(weights, dict):
        unknown = [key for key in weights if key not in names]
        if unknown:
            raise DriveError(f"unknown blendshape name {unknown[0]!r}" + (f" (and {len(unknown) - 1} more)"
                             if len(unknown) > 1 else "") + f"; the ARKit names are {', '.join(names[:4])}, ... "
                             "(gaussiantalker.sdk.rig.ARKIT_BLENDSHAPES)")
        vector = np.zeros(len(names), np.float64)
        for key, value in weights.items():
            vector[names.index(key)] = _vector(f"blendshape {key!r}", [value], 1)[0]  # one number each
        return vector.astype(np.float32)
    return _vector("blendshapes", weights, len(names))


@dataclass(frozen=True)
class BlendshapeDrive:
    """Everything that drives one frame of an ARKit speaker, validated: blendshape weights and head pose."""

    blendshapes: np.ndarray  # [52] in ARKIT_BLENDSHAPES order
    head_rotation: np.ndarray  # [3] axis-angle about the head bone's pivot (radians)
    head_translation: np.ndarray  # [3] metres
    rig = ARKIT_RIG

    def __post_init__(self) -> None:
        """Validate even when built directly (not through `make`), so no NaN reaches a graph."""
        object.__setattr__(self, "blendshapes", _vector("blendshapes", self.blendshapes, None))
        object.__setattr__(self, "head_rotation", _vector("head rotation", self.head_rotation, 3))
        object.__setattr__(self, "head_translation", _vector("head translation", self.head_translation, 3))

    @classmethod
    def make(cls, weights=None, head_pose: HeadPose | None = None,
             names: tuple[str, ...] = ARKIT_BLENDSHAPES) -> BlendshapeDrive:
        """Validate and pack: `weights` a {name: weight} dict or an array in `names` order (None: neutral)."""
        head_pose = head_pose or HeadPose.make()
        vector = np.zeros(len(names), np.float32) if weights is None else blendshape_vector(weights, names)
        return cls(vector, head_pose.rotation, head_pose.translation)

    def graph_inputs(self) -> dict[str, np.ndarray]:
        """Inputs of the ARKit deformation graph for a batch of one frame."""
        return {"blendshapes": self.blendshapes[None], "head_rotation": self.head_rotation[None],
                "head_translation": self.head_translation[None]}


def blendshape_drive_of(weights: np.ndarray, head_pose: HeadPose) -> BlendshapeDrive:
    """The drive of a driver's own row (float32 [52] in ARKIT_BLENDSHAPES order) and a HeadPose: the row checked
    in one pass; anything else goes through BlendshapeDrive.make and its errors."""
    if _is_checked_row(weights, len(ARKIT_BLENDSHAPES)):
        return _unchecked(BlendshapeDrive, blendshapes=weights.copy(), head_rotation=head_pose.rotation,
                          head_translation=head_pose.translation)
    return BlendshapeDrive.make(weights, head_pose)


def rows_within_magnitude(rows: np.ndarray) -> bool:
    """`_within_magnitude` of every row of a float32 [R, D] array, in one reduction."""
    return rows.dtype == np.float32 and rows.ndim == 2 and bool(
        np.maximum.reduce(np.abs(rows), axis=None, initial=0.0) <= MAX_DRIVE_MAGNITUDE)


def frame_drive_rows(n_expr: int, params: np.ndarray, poses: np.ndarray) -> np.ndarray | None:
    """Many `frame_drive_of` drives at once, as their fields' values in order (expression, flame_pose,
    head_translation) [R, n_expr + 18], from rows [R, n_expr + 3] and poses [R, 6] (rotation, translation); None
    unless every row passes the check (each then goes through frame_drive_of, which names the error)."""
    if params.shape[1:] != (n_expr + 3,) or not rows_within_magnitude(params):
        return None
    values = np.zeros((params.shape[0], n_expr + POSE_DIM + 3), np.float32)
    values[:, :n_expr] = params[:, :n_expr]
    values[:, n_expr:n_expr + 3] = poses[:, :3]  # flame_pose: global, neck, jaw, eyes
    values[:, n_expr + 6:n_expr + 9] = params[:, n_expr:]
    values[:, n_expr + POSE_DIM:] = poses[:, 3:]
    return values


def blendshape_drive_rows(weights: np.ndarray, poses: np.ndarray) -> np.ndarray | None:
    """Many `blendshape_drive_of` drives at once, as their fields' values in order (blendshapes, head_rotation,
    head_translation) [R, 58], from weights [R, 52] and poses [R, 6]; None unless every row passes the check."""
    if weights.shape[1:] != (len(ARKIT_BLENDSHAPES),) or not rows_within_magnitude(weights):
        return None
    return np.concatenate([weights, poses.astype(np.float32)], axis=1)


def frame_drive_of(n_expr: int, params: np.ndarray, head_pose: HeadPose) -> FrameDrive:
    """The drive of a FLAME translator's row (float32 [n_expr + 3]: expression, then jaw pose) and a HeadPose:
    the row checked in one pass; anything else goes through FrameDrive.make and its errors."""
    if _is_checked_row(params, n_expr + 3):
        flame_pose = np.zeros(POSE_DIM, np.float32)  # global, neck, jaw, eyes (FrameDrive.make's order)
        flame_pose[:3] = head_pose.rotation
        flame_pose[6:9] = params[n_expr:]
        return _unchecked(FrameDrive, expression=params[:n_expr].copy(), flame_pose=flame_pose,
                          head_translation=head_pose.translation)
    return FrameDrive.make(n_expr, params[:n_expr], params[n_expr:], head_pose=head_pose)


def track_row(count: int, index: int) -> int:
    """Row shown at video frame `index` of a track (or reference clip) of `count` rows, played forth and back
    (0, 1, ..., count - 1, count - 2, ..., 1, 0, ...: no jump)."""
    if count == 1:
        return 0
    period = 2 * (count - 1)
    phase = index % period
    return phase if phase < count else period - phase


def track_rows(count: int, indices: np.ndarray) -> np.ndarray:
    """`track_row` of many frame indices at once."""
    if count == 1:
        return np.zeros(indices.shape, np.int64)
    period = 2 * (count - 1)
    phase = np.asarray(indices, np.int64) % period
    return np.where(phase < count, phase, period - phase)


def pose_track_frame(track: np.ndarray, index: int) -> HeadPose:
    """Head pose of frame `index` from a [T, 6] track (rotation, translation), played forth and back (no jump)."""
    row = track[track_row(track.shape[0], index)]
    return HeadPose.make(row[:3], row[3:])


class PoseTrack:
    """A [T, 6] head-pose track (rotation, translation) checked once; `frame(index)` as pose_track_frame gives it,
    without a check a frame."""

    def __init__(self, track) -> None:
        rows = np.asarray(track)
        if rows.ndim != 2 or rows.shape[1] != 6 or rows.shape[0] == 0:
            raise DriveError(f"a pose track must have shape [T, 6] with T >= 1, got {tuple(rows.shape)}")
        self.rows = _vector("pose track", rows.reshape(-1), None).reshape(-1, 6)

    def frame(self, index: int) -> HeadPose:
        row = self.rows[track_row(self.rows.shape[0], index)]
        return _unchecked(HeadPose, rotation=row[:3].copy(), translation=row[3:].copy())

    def rows_at(self, indices: np.ndarray) -> np.ndarray:
        """The [R, 6] rows (rotation, translation) that `frame` gives for each of `indices`."""
        return self.rows[track_rows(self.rows.shape[0], indices)]
