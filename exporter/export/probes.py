"""Speech clips and the torch speaker's drives for them: what pruning and scene specialisation measure on, and
what verification drives both sides with (one definition, so every consumer sees the same frames)."""

from __future__ import annotations

import numpy as np
import torch

from gaussiantalker.runtime.translate import translate_audio
from gaussiantalker.sdk.drive import FrameDrive, HeadPose, pose_track_frame

from ..model.speaker import Speaker
from .speech import synth_speech


def speech_clip(speaker: Speaker, frames: int, seed: int) -> np.ndarray:
    """Speech-like audio of exactly `frames` video frames, float32 [640 * frames] at the speaker's rate."""
    spf = speaker.config.samples_per_frame
    return synth_speech(frames * spf / speaker.config.sample_rate, seed=seed)[: frames * spf]


def driven_clip(speaker: Speaker, frames: int, seed: int = 1) -> tuple[np.ndarray, list[FrameDrive]]:
    """A speech-like clip of `frames` video frames and the torch speaker's drives for it (pose track applied)."""
    spf = speaker.config.samples_per_frame
    audio = speech_clip(speaker, frames, seed)

    def run(chunk: np.ndarray) -> dict:
        with torch.no_grad():
            expression, jaw = speaker.translate(torch.from_numpy(chunk)[None])
        return {"expression": expression.numpy(), "jaw_pose": jaw.numpy()}

    expression, jaw = translate_audio(run, audio, spf)
    track = None if speaker.pose_track is None else speaker.pose_track.numpy()
    drives = []
    for index in range(frames):
        pose = HeadPose.make() if track is None else pose_track_frame(track, index)
        drives.append(FrameDrive.make(speaker.config.n_expr, expression[index], jaw[index], head_pose=pose))
    return audio, drives


__all__ = ["driven_clip", "speech_clip"]
