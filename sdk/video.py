"""Writing frames to an mp4 with the audio muxed in, through imageio-ffmpeg (libx264 + AAC)."""

from __future__ import annotations

import math
import os
import tempfile
from contextlib import ExitStack
from pathlib import Path

import numpy as np

from .audio import TARGET_SAMPLE_RATE, write_wav
from .errors import GaussianTalkerError
from .files import atomic_path

# libx264 speed/size trade-off: "veryfast" encodes 512x512 at several hundred fps on one core, so encoding never
# competes with rendering for the CPU; "medium" (x264's default) makes ~10% smaller files at ~3x the CPU time.
DEFAULT_X264_PRESET = "veryfast"


def pad_to_whole_frames(audio: np.ndarray, sample_rate: int, fps: float) -> np.ndarray:
    """Zero-pad audio to cover whole video frames, so ffmpeg's -shortest keeps the last (partial) frame.

    Without it a clip ending mid-frame loses its last frame, and one shorter than a frame gives no video at all.
    """
    audio = np.asarray(audio, dtype=np.float32).reshape(-1)
    frames = math.ceil(audio.shape[0] * fps / sample_rate - 1e-9)
    target = max(1, math.ceil(frames * sample_rate / fps - 1e-9))
    return np.pad(audio, (0, max(0, target - audio.shape[0])))


class VideoWriter:
    """Context manager: `with VideoWriter(path, fps, (w, h), audio=a) as out: out.write(frame_uint8)`.

    ffmpeg writes a hidden temporary file in the target's own folder (`sdk.files.atomic_path`), renamed onto
    `path` only when the video is complete, so a failed run leaves no half video and the rename never crosses a
    file system. The audio to mux goes to a WAV in the system temp folder (read by ffmpeg, never renamed).
    """

    def __init__(self, path: str | os.PathLike, fps: float, size: tuple[int, int],
                 audio: np.ndarray | None = None, sample_rate: int = TARGET_SAMPLE_RATE, quality: int = 8,
                 preset: str = DEFAULT_X264_PRESET) -> None:
        self.path = Path(path)
        self.fps, self.size, self.quality = fps, (int(size[0]), int(size[1])), quality
        self.audio, self.sample_rate, self.preset = audio, sample_rate, preset
        self.frames_written = 0
        self._writer = None
        self._stack: ExitStack | None = None

    def __enter__(self) -> VideoWriter:
        import imageio_ffmpeg

        with ExitStack() as stack:
            # ffmpeg picks the container from the extension, so the temporary name ends with the target's.
            staged = stack.enter_context(atomic_path(self.path, suffix=".partial" + (self.path.suffix or ".mp4")))
            audio_path = None
            if self.audio is not None:
                tmp_dir = stack.enter_context(tempfile.TemporaryDirectory(prefix="gt-video-"))
                audio_path = os.path.join(tmp_dir, "audio.wav")
                write_wav(audio_path, pad_to_whole_frames(self.audio, self.sample_rate, self.fps), self.sample_rate)
            self._writer = imageio_ffmpeg.write_frames(
                str(staged.path), self.size, fps=self.fps, quality=self.quality, macro_block_size=1,
                audio_path=audio_path, audio_codec="aac" if audio_path else None,
                output_params=["-preset", self.preset] + (["-shortest"] if audio_path else []),
                ffmpeg_log_level="error")
            self._writer.send(None)
            self._stack = stack.pop_all()  # kept open until __exit__ commits or removes the staged file
        return self

    def write(self, frame: np.ndarray) -> None:
        """Append one [H, W, 3] uint8 frame."""
        if frame.dtype != np.uint8 or frame.shape != (self.size[1], self.size[0], 3):
            raise GaussianTalkerError(f"video frames must be uint8 [{self.size[1]}, {self.size[0]}, 3], got "
                                      f"{frame.dtype} {list(frame.shape)}")
        self._writer.send(np.ascontiguousarray(frame))
        self.frames_written += 1

    def __exit__(self, exc_type, exc, tb) -> None:
        stack, self._stack = self._stack, None
        try:
            self._writer.close()  # ffmpeg finishes the file
            if exc_type is None and self.frames_written == 0:
                raise GaussianTalkerError(f"no frames were written to {self.path}; an mp4 needs at least one")
        except BaseException as error:
            stack.__exit__(type(error), error, error.__traceback__)  # removes the staged file
            raise
        stack.__exit__(exc_type, exc, tb)  # commits it, or removes it if the body raised


def probe_video(path: str | os.PathLike) -> dict:
    """Frame count and whether an audio stream exists (via the bundled ffmpeg), for tests and reports."""
    import subprocess

    import imageio_ffmpeg

    frames, seconds = imageio_ffmpeg.count_frames_and_secs(str(path))
    result = subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-nostdin", "-i", str(path)],
                            capture_output=True, check=False)
    has_audio = "Audio:" in result.stderr.decode("utf-8", "replace")
    return {"frames": int(frames), "seconds": float(seconds), "has_audio": has_audio}
