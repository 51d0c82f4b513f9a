"""Speech clips and the torch speaker's drives for them: what pruning and scene specialisation measure on, and
what verification drives both sides with (one definition, so every consumer sees the same frames)."""

from __future__ import annotations

import numpy as np
import torch

from gaussiantalker.runtime.translate import translate_audio
from gaussiantalker.sdk.drive import BlendshapeDrive, FrameDrive, HeadPose, pose_track_frame

from ..model.arkit_speaker import ArkitSpeaker
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


def motion_clip(speaker: ArkitSpeaker | Speaker, frames: int, seed: int = 1) -> list[BlendshapeDrive | FrameDrive]:
    """`frames` drives of a speaker played without audio (an ARKit speaker, an imported FLAME avatar): its shipped
    motion sampled evenly over the track, or, without a motion track, random drives: ARKit weights (each blendshape
    on with probability 0.3, uniform in [0, 1]) with the pose track's head poses, or FLAME expressions N(0, 0.7)
    with the jaw opening up to 0.3 rad."""
    length = 0 if speaker.motion_track is None else int(speaker.motion_track.shape[0])
    rows = np.linspace(0, max(length - 1, 0), frames).round().astype(int)
    rng = np.random.default_rng(seed)
    if isinstance(speaker, Speaker):
        if length:
            return [speaker.motion_drive(int(row)) for row in rows]
        n_expr = speaker.config.n_expr
        return [FrameDrive.make(n_expr, rng.normal(0.0, 0.7, n_expr), [rng.uniform(0.0, 0.3), 0.0, 0.0])
                for _ in range(frames)]
    drives = []
    for index, row in enumerate(rows):
        drive = speaker.motion_drive(int(row) if length else index)
        if not length:
            weights = rng.uniform(0.0, 1.0, speaker.n_blendshapes) * (rng.random(speaker.n_blendshapes) < 0.3)
            drive = BlendshapeDrive(weights.astype(np.float32), drive.head_rotation, drive.head_translation)
        drives.append(drive)
    return drives


def plays_audio(speaker: Speaker | ArkitSpeaker) -> bool:
    """Whether the torch speaker turns audio into drives itself (a FLAME speaker with its trained translator)."""
    return isinstance(speaker, Speaker) and speaker.translator is not None


__all__ = ["driven_clip", "motion_clip", "plays_audio", "speech_clip"]
