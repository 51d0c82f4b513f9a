"""A speaker's motion from whatever the app gives (a file, a track object, an array, or nothing: the bundle's own),
checked against the speaker's rig and resampled to its fps. docs/import.md, "Motion files"; a file is read within
the bounds of docs/untrusted-input.md, "Motion files", and every error about it names it."""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from gaussiantalker.sdk.errors import DriveError
from gaussiantalker.sdk.flame_motion import TABLE_POSE_COLUMNS, FlameMotion, load_flame_motion
from gaussiantalker.sdk.motion import MotionTrack, load_motion

# An ARKit motion: a motion file (LAM's JSON kinds), a MotionTrack, [T, 52] weights at the speaker's fps; a FLAME
# motion: an npz of GaussianAvatars' per-frame keys, a FlameMotion, a [T, n_expr + 18] table at the speaker's fps;
# None: the motion the bundle ships.
MotionSource = str | os.PathLike | MotionTrack | FlameMotion | np.ndarray | None


@contextmanager
def _naming(path: str | os.PathLike) -> Iterator[None]:
    """DriveErrors raised within name the motion file they are about."""
    try:
        yield
    except DriveError as exc:
        if str(path) in str(exc):
            raise
        raise DriveError(f"motion file {path}: {exc}") from None


def arkit_motion(source: MotionSource, shipped: MotionTrack | None, fps: int, where: str) -> MotionTrack:
    """An ARKit speaker's motion at `fps` (`shipped`: the bundle's motion track, used for None)."""
    if source is None:
        if shipped is None:
            raise DriveError(f"{where}: the avatar ships no motion track; give a motion file or [T, 52] ARKit weights")
        track = shipped
    elif isinstance(source, FlameMotion):
        raise DriveError("a FLAME motion drives FLAME speakers; this ARKit speaker takes ARKit weights")
    elif isinstance(source, MotionTrack):
        track = source
    elif isinstance(source, (str, os.PathLike)):
        with _naming(source):
            return load_motion(source).at_fps(fps)
    else:
        track = MotionTrack(np.asarray(source, dtype=np.float64), fps)
    return track.at_fps(fps)


def flame_motion(source: MotionSource, shipped: FlameMotion | None, fps: int, n_expr: int, where: str
                 ) -> FlameMotion:
    """A FLAME speaker's motion at `fps` with `n_expr` expression coefficients (`shipped`: the bundle's own)."""
    if source is None:
        if shipped is None:
            raise DriveError(f"{where}: the speaker ships no motion track; give a FLAME motion npz (GaussianAvatars' "
                             f"flame_param.npz keys) or a [T, {n_expr + TABLE_POSE_COLUMNS}] table")
        motion = shipped
    elif isinstance(source, MotionTrack):
        raise DriveError("an ARKit motion drives ARKit speakers; this FLAME speaker takes FLAME parameters")
    elif isinstance(source, FlameMotion):
        motion = source
    elif isinstance(source, (str, os.PathLike)):
        if Path(source).suffix.lower() == ".json":
            raise DriveError(f"{source}: a JSON motion holds ARKit weights; this FLAME speaker takes a FLAME motion "
                             "npz (GaussianAvatars' flame_param.npz keys)")
        with _naming(source):
            return load_flame_motion(source, fps).with_expressions(n_expr).at_fps(fps)
    else:
        motion = FlameMotion.from_table(np.asarray(source, dtype=np.float64), fps)
    return motion.with_expressions(n_expr).at_fps(fps)


__all__ = ["MotionSource", "arkit_motion", "flame_motion"]
