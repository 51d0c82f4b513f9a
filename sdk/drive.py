"""Per-frame drive parameters: FLAME expression and pose plus the head pose, validated and packed for graphs.

The deformation graph takes `expression [B, n_expr]`, `flame_pose [B, 15]` (axis-angle per FLAME joint:
global = head rotation, neck, jaw, left eye, right eye) and `head_translation [B, 3]`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .config import POSE_DIM
from .errors import DriveError

# Largest magnitude accepted for any drive value: far beyond anatomy (FLAME units are sigma / radians / metres),
# small enough that no intermediate product overflows float32.
MAX_DRIVE_MAGNITUDE = 1e4


def _vector(name: str, value, size: int) -> np.ndarray:
    array = np.zeros(size, np.float32) if value is None else np.asarray(value, dtype=np.float32)
    if array.shape != (size,):
        raise DriveError(f"{name} must have shape ({size},), got {tuple(array.shape)}")
    if not np.all(np.isfinite(array)):
        raise DriveError(f"{name} has non-finite values: {array.tolist()}")
    if np.abs(array).max(initial=0.0) > MAX_DRIVE_MAGNITUDE:
        raise DriveError(f"{name} exceeds the supported magnitude {MAX_DRIVE_MAGNITUDE:g}")
    return array


@dataclass(frozen=True)
class HeadPose:
    """Rigid head pose: FLAME global rotation (axis-angle, radians) and translation (metres)."""

    rotation: np.ndarray
    translation: np.ndarray

    @classmethod
    def make(cls, rotation=None, translation=None) -> HeadPose:
        return cls(_vector("head rotation", rotation, 3), _vector("head translation", translation, 3))


@dataclass(frozen=True)
class FrameDrive:
    """Everything that drives one frame, validated: expression, jaw/neck/eye pose and head pose."""

    expression: np.ndarray  # [n_expr]
    flame_pose: np.ndarray  # [15]
    head_translation: np.ndarray  # [3]

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


def pose_track_frame(track: np.ndarray, index: int) -> HeadPose:
    """Head pose of frame `index` from a [T, 6] track (rotation, translation), played forth and back (no jump)."""
    count = track.shape[0]
    if count == 1:
        return HeadPose.make(track[0, :3], track[0, 3:])
    period = 2 * (count - 1)
    phase = index % period
    row = phase if phase < count else period - phase
    return HeadPose.make(track[row, :3], track[row, 3:])
