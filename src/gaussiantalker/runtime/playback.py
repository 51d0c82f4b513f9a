"""What a video of a head plays, as explicit drives and frames (docs/embedding.md, "Stages"): `write_video`'s
choice between the audio through the translator and a motion, the drives at another frame rate than the
speaker's (runtime/frame_rate.py), and the frames of explicit drives, so that a job split into segments
(docs/batch.md, "Long audio") makes each segment's frames as the unsplit video does. Also the head's camera
swung about the head (`orbited_camera`)."""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from fractions import Fraction
from typing import Protocol

import numpy as np

from gaussiantalker.sdk.camera import Camera
from gaussiantalker.sdk.errors import AudioError, RenderError
from gaussiantalker.sdk.rig import FLAME_RIG
from gaussiantalker.sdk.video import check_fps, frames_at, video_rate

from .compositor import check_composited_output
from .driver import AudioSource, Drive, HeadPoseSource
from .frame_loops import bare_frames, composited_frames
from .frame_rate import resampled
from .motions import MotionSource


class PlayingHead(Protocol):
    """What these functions use of a `runtime.head.TalkingHead` (named here, not imported: the head imports this
    module)."""

    driver: object
    frame_renderer: object
    compositor: object | None
    backend_settings: object
    camera: Camera
    fps: int
    sample_rate: int

    def drives(self, audio=None, sample_rate=None, head_pose=None, *, motion=None) -> Iterator[Drive]: ...

    def frames(self, audio=None, sample_rate=None, head_pose=None, output="uint8", *,
               motion=None) -> Iterator[np.ndarray]: ...


@dataclass(frozen=True)
class Playback:
    """What a video of a head plays: the audio to mux (None: silent), the motion track played instead of the
    translator (None: the audio drives the translator), its frames at the speaker's fps, and whether composited."""

    samples: np.ndarray | None
    track: object | None  # a MotionTrack or FlameMotion at the head's fps
    frames: int
    composited: bool


def playback(head: PlayingHead, audio: AudioSource | None = None, sample_rate: int | None = None, *,
             motion: MotionSource = None) -> Playback:
    """What `head.write_video` plays for these arguments, checked: a speaker with a translator renders the audio
    through it; given a motion, or without a translator or audio, it plays the motion (None: the bundle's own)."""
    driver = head.driver
    samples = None if audio is None else driver.load_audio(audio, sample_rate)
    if driver.rig == FLAME_RIG and samples is None and motion is None and driver.has_translator \
            and driver.motion_track is None:
        raise AudioError("this speaker's video needs audio (its translator turns speech into motion) or a motion")
    if motion is not None or samples is None or not driver.has_translator:
        if head.compositor is not None:
            raise RenderError("a composited head follows the reference clip and its audio; play a motion with "
                              "composite=False")
        track = driver.motion(motion)
        return Playback(samples, track, len(track), composited=False)
    return Playback(samples, None, driver.frame_count(samples.shape[0]), composited=head.compositor is not None)


def playback_drives(head: PlayingHead, play: Playback) -> Iterator[Drive]:
    """One drive per speaker frame of a playback, as `write_video` makes them."""
    if play.track is not None:
        return head.drives(motion=play.track)
    return head.drives(play.samples, head.sample_rate)


def other_rate(head: PlayingHead, fps: float | None) -> bool:
    """Whether a video at `fps` (checked) has another frame rate than the speaker's."""
    return fps is not None and video_rate(check_fps(fps)) != video_rate(head.fps)


def video_drives(head: PlayingHead, play: Playback, fps: float | None = None) -> tuple[list[Drive], list[int]]:
    """The drives of a playback's video at `fps` (None: the speaker's) and the speaker frame each shows (its
    reference picture when composited), sampled at the video's frame times (runtime/frame_rate.py)."""
    drives = list(playback_drives(head, play))
    if not other_rate(head, fps):
        return drives, list(range(len(drives)))
    seconds = Fraction(len(drives), head.fps) if play.samples is None else Fraction(len(play.samples),
                                                                                      head.sample_rate)
    return resampled(drives, head.fps, fps, frames_at(seconds, fps), blend=not play.composited)


def drive_frames(head: PlayingHead, drives: Iterable[Drive], output: str = "uint8", *, composited: bool = False,
                 reference_frames: Iterable[int] | None = None) -> Iterator[np.ndarray]:
    """Frames of explicit drives, pipelined as `head.frames` makes them; `composited`: each drive into the
    reference picture of its video frame (`reference_frames`, None: 0, 1, 2, ...; uint8 only)."""
    pipelined = head.backend_settings.pipeline is not False
    if not composited:
        return bare_frames(head.frame_renderer, drives, output, pipelined)
    check_composited_output(head.compositor, output)
    return composited_frames(head.frame_renderer, head.compositor, drives, pipelined, reference_frames)


def video_frames(head: PlayingHead, play: Playback, output: str, head_pose: HeadPoseSource,
                 fps: float | None) -> tuple[Iterator[np.ndarray], int]:
    """`write_video`'s frames of a playback at `fps` (None: the speaker's), and how many: streamed at the
    speaker's rate, from the resampled drives at another."""
    if other_rate(head, fps):
        if head_pose is not None:
            raise RenderError("write_video with fps takes the drives' own head pose; set head_pose at the "
                              "speaker's fps")
        drives, shown = video_drives(head, play, fps)
        return drive_frames(head, drives, output, composited=play.composited, reference_frames=shown), len(drives)
    if play.track is not None:
        return head.frames(head_pose=head_pose, output=output, motion=play.track), play.frames
    return head.frames(play.samples, head.sample_rate, head_pose, output=output), play.frames


def orbited_camera(head: PlayingHead, yaw_deg: float, pitch_deg: float) -> Camera:
    """The head's camera swung about the head's centre (the median of its rest-pose Gaussians) by yaw, then pitch
    (`Camera.orbited`): a view from elsewhere at the same distance, for `head.camera` (bare heads: a composited
    frame is seen through the reference clip's camera)."""
    means = head.frame_renderer.deform(head.driver.drive())["means"]
    finite = means[np.isfinite(means).all(axis=1)]
    if finite.shape[0] == 0:
        raise RenderError("the rest pose has no finite Gaussian to orbit about")
    return head.camera.orbited(yaw_deg, pitch_deg, np.median(finite.astype(np.float64), axis=0))
