"""Many live sessions' frames made together, as arrays: each session's own bookkeeping of its frame (the ease to
idle, a blink, its stats), then one pass for every frame's head pose and drive values (docs/live.md, "Steady frames
made together"). For a pool that sends frames as packets, which need each drive's values, not a drive object: a
frame's `FrameDrive` and its encoding cost some 20 µs a frame, a hundred frames' arrays a few µs each."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .live import FramePlan, LiveFrame, LiveSession


@dataclass
class FrameRows:
    """Frames of sessions on one driver, made but for their drives: row k is `lives[k]`'s frame `indices[k]`."""

    lives: list[LiveSession]
    indices: np.ndarray  # [R]
    pts: np.ndarray  # [R] seconds on each session's audio clock
    speaking: np.ndarray  # [R] bool
    params: np.ndarray  # [R, D] each frame's parameters, idle motion added (before the rig's clamp)
    poses: np.ndarray  # [R, 6] each frame's head pose (rotation, translation)
    audio: list[np.ndarray]  # each frame's audio
    errors: dict[int, BaseException]  # rows whose session failed making its frame (it stopped): no frame

    def values(self) -> np.ndarray | None:
        """Every frame's drive as its fields' values in order [R, count] (what `make_frame`'s drive carries); None when
        the driver makes drives one at a time or a row fails the drive's check (then `frame(k)` each)."""
        return self.lives[0].driver.drive_rows(self.params, self.poses)

    def frame(self, k: int) -> LiveFrame:
        """Row k's LiveFrame, its drive made alone (the drive's check raises for a bad row: the session stops)."""
        live, index = self.lives[k], int(self.indices[k])
        try:
            drive = live.drive_of(self.params[k], index)
        except Exception as error:
            live.fail(error)
            raise
        return LiveFrame(index, float(self.pts[k]), None, self.audio[k], live.sample_rate, bool(self.speaking[k]),
                         drive)


def make_rows(lives: list[LiveSession], plans: list[FramePlan]) -> FrameRows:
    """The frames of `plans` (each its session's `next_plan`'s or `SteadyFrames.take`'s; sessions on one driver,
    output=None), every session's bookkeeping done as `make_frame` does it; their drives are `FrameRows.values`."""
    count = len(lives)
    indices = np.zeros(count, np.int64)
    pts = np.zeros(count)
    speaking = np.zeros(count, bool)
    params = np.zeros((count, lives[0].driver.param_count), np.float32)
    poses = np.zeros((count, 6), np.float32)
    swaying, errors = [], {}
    for k, (live, plan) in enumerate(zip(lives, plans, strict=True)):
        try:
            index, params[k], speaking[k] = live.frame_params(plan)
            live.count_frame(plan)
            indices[k], pts[k] = index, index / live.fps
            if live.sways:  # no pose track: the session's idle sway
                pose = live.pose(index)
                poses[k, :3], poses[k, 3:] = pose.rotation, pose.translation
                swaying.append(k)
        except Exception as error:
            live.fail(error)
            errors[k] = error
    tracked = np.ones(count, bool)
    tracked[swaying] = False
    if tracked.any():
        poses[tracked] = lives[0].driver.head_pose_rows(indices[tracked])
    return FrameRows(lives, indices, pts, speaking, params, poses, [plan.out_audio for plan in plans], errors)


__all__ = ["FrameRows", "make_rows"]
