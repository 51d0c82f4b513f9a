"""ARKit motion files: per-frame blendshape weights as LAM writes them (docs/import.md, "Motion files").

Two kinds are read, both JSON with "names" (the blendshape of each weight column) and "frames" (one
{"weights": [...], "time": seconds} per frame): LAM_WebRender's sample motion (30 fps, with a "head_pose" list)
and LAM's audio-to-expression output `bsData.json` (with "metadata": {"fps": ...}). The per-frame "rotation" and
"head_pose" entries are not used, as LAM's web renderer does not use them. A frame may also be a {name: weight}
object. Columns are reordered to ARKIT_BLENDSHAPES; names a file lacks are 0.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .drive import MAX_DRIVE_MAGNITUDE
from .errors import DriveError
from .rig import ARKIT_BLENDSHAPES

# A motion file whose frames give no rate (no metadata fps, fewer than two times) plays at LAM's 30 fps.
DEFAULT_MOTION_FPS = 30.0


@dataclass(frozen=True)
class MotionTrack:
    """ARKit weights [T, 52] (ARKIT_BLENDSHAPES order) at `fps` frames per second."""

    weights: np.ndarray
    fps: float

    def __post_init__(self) -> None:
        weights = np.asarray(self.weights, np.float64)
        if weights.ndim != 2 or weights.shape[1] != len(ARKIT_BLENDSHAPES) or weights.shape[0] < 1:
            raise DriveError(f"a motion track is [T >= 1, {len(ARKIT_BLENDSHAPES)}] ARKit weights, got "
                             f"{list(weights.shape)}")
        bad = np.argwhere(~np.isfinite(weights) | (np.abs(weights) > MAX_DRIVE_MAGNITUDE))
        if bad.size:
            row, column = bad[0]
            raise DriveError(f"motion frame {row}: {ARKIT_BLENDSHAPES[column]} = {weights[row, column]} is not a "
                             f"finite weight within {MAX_DRIVE_MAGNITUDE:g}")
        if not (np.isfinite(self.fps) and self.fps > 0):
            raise DriveError(f"motion fps must be positive, got {self.fps}")
        object.__setattr__(self, "weights", weights.astype(np.float32))

    def __len__(self) -> int:
        return int(self.weights.shape[0])

    def at_fps(self, fps: float) -> MotionTrack:
        """The same motion resampled (linearly in time) to `fps`, covering the same duration."""
        if abs(fps - self.fps) < 1e-9:
            return self
        return MotionTrack(resample_at_fps(self.weights, self.fps, fps), fps)


def resample_at_fps(rows: np.ndarray, fps: float, new_fps: float) -> np.ndarray:
    """Per-frame rows [T, D] at `fps` resampled linearly in time to `new_fps`, covering the same duration
    (round(T * new_fps / fps) rows, at least one; the last row holds past the end). float64."""
    count = max(1, int(round(rows.shape[0] * new_fps / fps)))
    source = np.arange(rows.shape[0]) / fps
    target = np.minimum(np.arange(count) / new_fps, source[-1])
    return np.stack([np.interp(target, source, rows[:, k]) for k in range(rows.shape[1])], axis=1)


def _frame_weights(frame, names: list[str], index: int, where: str) -> list[float]:
    """One frame's weights in `names` order from a {"weights": [...]} or a {name: weight} object."""
    if isinstance(frame, dict) and "weights" in frame:
        weights = frame["weights"]
    elif isinstance(frame, dict):
        return [frame.get(name, 0.0) for name in names]
    else:
        weights = frame
    if not isinstance(weights, list) or len(weights) != len(names):
        raise DriveError(f"{where}: frame {index} has {len(weights) if isinstance(weights, list) else 'no'} weights "
                         f"but the file names {len(names)} blendshapes")
    return weights


def _frame_rate(data: dict, frames: list) -> float:
    """metadata.fps, else the median step of the frames' times, else DEFAULT_MOTION_FPS."""
    fps = (data.get("metadata") or {}).get("fps") if isinstance(data.get("metadata"), dict) else None
    if isinstance(fps, int | float) and fps > 0:
        return float(fps)
    times = [f.get("time") for f in frames if isinstance(f, dict)]
    if len(times) >= 2 and all(isinstance(t, int | float) for t in times):
        step = float(np.median(np.diff(np.asarray(times, np.float64))))
        if step > 0:
            return 1.0 / step
    return DEFAULT_MOTION_FPS


def parse_motion(data: object, where: str = "motion") -> MotionTrack:
    """A motion file's parsed JSON -> MotionTrack; DriveError naming the field that is wrong."""
    if not isinstance(data, dict) or not isinstance(data.get("frames"), list):
        raise DriveError(f"{where}: an ARKit motion file is a JSON object with a 'frames' list")
    frames = data["frames"]
    if not frames:
        raise DriveError(f"{where}: 'frames' is empty")
    names = data.get("names") or (data.get("metadata") or {}).get("blendshape_names")
    if names is None and isinstance(frames[0], dict) and "weights" not in frames[0]:
        names = sorted({key for frame in frames for key in frame})
    if names is None:
        names = list(ARKIT_BLENDSHAPES)  # bare weight lists: the ARKit order
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        raise DriveError(f"{where}: 'names' must be a list of blendshape names")
    unknown = [n for n in names if n not in ARKIT_BLENDSHAPES]
    if unknown:
        raise DriveError(f"{where}: unknown blendshape name {unknown[0]!r} in 'names' (ARKit names only, "
                         "gaussiantalker.sdk.rig.ARKIT_BLENDSHAPES)")
    rows = [_frame_weights(frame, names, i, where) for i, frame in enumerate(frames)]
    try:
        table = np.asarray(rows, np.float64)
    except (TypeError, ValueError) as exc:
        raise DriveError(f"{where}: frame weights must be numbers: {exc}") from None
    weights = np.zeros((len(rows), len(ARKIT_BLENDSHAPES)))
    weights[:, [ARKIT_BLENDSHAPES.index(n) for n in names]] = table
    return MotionTrack(weights, _frame_rate(data, frames))


def load_motion(path: str | os.PathLike) -> MotionTrack:
    """Read an ARKit motion JSON file (LAM's kinds); DriveError naming the file and what is wrong."""
    path = Path(path)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise DriveError(f"cannot read motion file {path}: {exc.strerror or exc}") from None
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise DriveError(f"motion file {path} is not JSON: {exc}") from None
    return parse_motion(data, str(path))


__all__ = ["DEFAULT_MOTION_FPS", "MotionTrack", "load_motion", "parse_motion", "resample_at_fps"]
