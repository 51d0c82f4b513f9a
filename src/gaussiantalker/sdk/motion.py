"""ARKit motion files: per-frame blendshape weights as LAM writes them (docs/import.md, "Motion files").

Two kinds are read, both JSON with "names" (the blendshape of each weight column) and "frames" (one
{"weights": [...], "time": seconds} per frame): LAM_WebRender's sample motion (30 fps, with a "head_pose" list)
and LAM's audio-to-expression output `bsData.json` (with "metadata": {"fps": ...}). The per-frame "rotation" and
"head_pose" entries are not used, as LAM's web renderer does not use them. A frame may also be a {name: weight}
object. Columns are reordered to ARKIT_BLENDSHAPES; names a file lacks are 0. A motion file is the user's
(docs/untrusted-input.md, "Motion files"): its size, nesting, numbers and frame rate are bounded before use.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .drive import MAX_DRIVE_MAGNITUDE
from .errors import DriveError
from .json_bounds import MAX_JSON_DEPTH, nests_deeper_than, no_constant
from .rig import ARKIT_BLENDSHAPES

# A motion file whose frames give no rate (no metadata fps, fewer than two times) plays at LAM's 30 fps.
DEFAULT_MOTION_FPS = 30.0
# The most frames a motion may have once resampled to a speaker's rate (4.9 hours at 30 fps): a rate read from a
# file (a tiny fps, or times a day apart) must not make a table of billions of rows.
MAX_MOTION_FRAMES = 1 << 19
# The largest motion file read: JSON of MAX_MOTION_FRAMES frames of 52 weights fits.
MAX_MOTION_FILE_BYTES = 512 << 20


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
    (round(T * new_fps / fps) rows, at least one; the last row holds past the end). float64. DriveError when that
    is over MAX_MOTION_FRAMES rows."""
    wanted = rows.shape[0] * float(new_fps) / float(fps)
    if not wanted <= MAX_MOTION_FRAMES:
        raise DriveError(f"a motion of {rows.shape[0]} frames at {fps:g} fps would be {wanted:.4g} frames at "
                         f"{new_fps:g} fps, over the {MAX_MOTION_FRAMES} frame limit")
    count = max(1, int(round(wanted)))
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


def _number(value) -> float | None:
    """A JSON number as a finite float, None for anything else (bools, strings, numbers past float's range)."""
    if not isinstance(value, int | float) or isinstance(value, bool):
        return None
    try:
        number = float(value)
    except OverflowError:
        return None
    return number if np.isfinite(number) else None


def _frame_rate(data: dict, frames: list) -> float:
    """metadata.fps, else the median step of the frames' times, else DEFAULT_MOTION_FPS."""
    fps = _number(data["metadata"].get("fps")) if isinstance(data.get("metadata"), dict) else None
    if fps is not None and fps > 0:
        return fps
    times = [_number(f.get("time")) for f in frames if isinstance(f, dict)]
    if len(times) >= 2 and all(t is not None for t in times):
        step = float(np.median(np.diff(np.asarray(times, np.float64))))
        if step > 0 and np.isfinite(1.0 / step):
            return 1.0 / step
    return DEFAULT_MOTION_FPS


def parse_motion(data: object, where: str = "motion") -> MotionTrack:
    """A motion file's parsed JSON -> MotionTrack; DriveError naming the field that is wrong."""
    if not isinstance(data, dict) or not isinstance(data.get("frames"), list):
        raise DriveError(f"{where}: an ARKit motion file is a JSON object with a 'frames' list")
    frames = data["frames"]
    if not frames:
        raise DriveError(f"{where}: 'frames' is empty")
    metadata = data.get("metadata") if isinstance(data.get("metadata"), dict) else {}
    names = data.get("names") or metadata.get("blendshape_names")
    if names is None and all(isinstance(frame, dict) and "weights" not in frame for frame in frames):
        names = sorted({key for frame in frames for key in frame})
    if names is None:
        names = list(ARKIT_BLENDSHAPES)  # bare weight lists: the ARKit order
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        raise DriveError(f"{where}: 'names' must be a list of blendshape names")
    unknown = [n for n in names if n not in ARKIT_BLENDSHAPES]
    if unknown:
        raise DriveError(f"{where}: unknown blendshape name {unknown[0][:40]!r} in 'names' (ARKit names only, "
                         "gaussiantalker.sdk.rig.ARKIT_BLENDSHAPES)")
    if len(set(names)) != len(names):
        raise DriveError(f"{where}: 'names' lists a blendshape twice")
    rows = [_frame_weights(frame, names, i, where) for i, frame in enumerate(frames)]
    if any(isinstance(value, bool) for row in rows if isinstance(row, list) for value in row):
        raise DriveError(f"{where}: frame weights must be numbers, one per name")  # JSON's true is not 1.0
    try:
        table = np.asarray(rows, np.float64)
    except (TypeError, ValueError, OverflowError) as exc:
        raise DriveError(f"{where}: frame weights must be numbers: {' '.join(str(exc).split())[:120]}") from None
    if table.shape != (len(rows), len(names)):
        raise DriveError(f"{where}: frame weights must be numbers, one per name")
    weights = np.zeros((len(rows), len(ARKIT_BLENDSHAPES)))
    weights[:, [ARKIT_BLENDSHAPES.index(n) for n in names]] = table
    try:
        return MotionTrack(weights, _frame_rate(data, frames))
    except DriveError as exc:
        raise DriveError(f"{where}: {exc}") from None


def load_motion(path: str | os.PathLike) -> MotionTrack:
    """Read an ARKit motion JSON file (LAM's kinds); DriveError naming the file and what is wrong."""
    path = Path(path)
    try:
        size = path.stat().st_size
        if size > MAX_MOTION_FILE_BYTES:
            raise DriveError(f"motion file {path} is {size} bytes, over the {MAX_MOTION_FILE_BYTES} byte limit")
        data = json.loads(path.read_text(encoding="utf-8"), parse_constant=no_constant)
        if nests_deeper_than(data, MAX_JSON_DEPTH):
            raise RecursionError
    except OSError as exc:
        raise DriveError(f"cannot read motion file {path}: {exc.strerror or exc}") from None
    except (UnicodeDecodeError, ValueError, RecursionError) as exc:
        detail = "it nests too deep" if isinstance(exc, RecursionError) else " ".join(str(exc).split())[:200]
        raise DriveError(f"motion file {path} is not JSON: {detail}") from None
    return parse_motion(data, str(path))


__all__ = ["DEFAULT_MOTION_FPS", "MAX_MOTION_FRAMES", "MotionTrack", "load_motion", "parse_motion", "resample_at_fps"]
