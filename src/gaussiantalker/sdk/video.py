"""Writing frames to a video (or an image sequence) with the audio muxed in, through PyAV (libav in process).

PyAV rather than piping raw frames to an ffmpeg process (imageio-ffmpeg): an encoder or muxer failure comes back
as an exception carrying libav's own message (disk full, file too large) instead of a broken pipe, the encoder is
opened, and so checked, before the first frame is rendered, and the audio is encoded from the samples in memory
with no temporary WAV. The formats and the checks are in `sdk/video_formats.py`; docs/video.md lists them.
"""

from __future__ import annotations

import math
import os
from contextlib import ExitStack
from fractions import Fraction

import numpy as np

from .audio import TARGET_SAMPLE_RATE
from .errors import VideoError
from .files import atomic_files, atomic_path
from .video_formats import VideoPlan, plan_video

MIN_FPS, MAX_FPS = 1.0, 120.0  # the frame rates a video may be written at (runtime/frame_rate.py)


def video_rate(fps: float) -> Fraction:
    """The exact frame rate a video of `fps` is written at (the writer's: 29.97 stays 2997/100)."""
    return Fraction(fps).limit_denominator(1001)


def check_fps(fps: float) -> float:
    """`fps` as a float, ValueError unless it is a number in MIN_FPS..MAX_FPS."""
    if isinstance(fps, bool) or not isinstance(fps, int | float) or not MIN_FPS <= fps <= MAX_FPS:
        raise ValueError(f"fps must be a number {MIN_FPS:g}..{MAX_FPS:g}, got {fps!r}")
    return float(fps)


def frames_at(duration_s: Fraction, fps: float) -> int:
    """Frames of a video of `duration_s` at `fps` (the last one partial, as the speaker's own count)."""
    return max(1, math.ceil(duration_s * video_rate(fps)))


def pad_to_whole_frames(audio: np.ndarray, sample_rate: int, fps: float) -> np.ndarray:
    """Zero-pad audio to cover whole video frames, so the audio stream lasts as long as the last (partial) frame.

    Without it a clip ending mid-frame would have a shorter audio than video stream.
    """
    audio = np.asarray(audio, dtype=np.float32).reshape(-1)
    frames = math.ceil(audio.shape[0] * fps / sample_rate - 1e-9)
    target = max(1, math.ceil(frames * sample_rate / fps - 1e-9))
    return np.pad(audio, (0, max(0, target - audio.shape[0])))


class _PaletteFilter:
    """rgb24 frames -> pal8 frames with a palette chosen per frame (libav's palettegen + paletteuse), for GIF."""

    def __init__(self, width: int, height: int, rate: Fraction) -> None:
        import av.filter

        self.graph = av.filter.Graph()
        source = self.graph.add_buffer(width=width, height=height, format="rgb24", time_base=1 / rate)
        split = self.graph.add("split")
        palette = self.graph.add("palettegen", "stats_mode=single")
        use = self.graph.add("paletteuse", "new=1")
        sink = self.graph.add("buffersink")
        source.link_to(split)
        split.link_to(use, 0, 0)
        split.link_to(palette, 1, 0)
        palette.link_to(use, 0, 1)
        use.link_to(sink)
        self.graph.configure()

    def __call__(self, frame):
        """Push one frame (None: end of stream), return the paletted frames that are ready."""
        import av

        self.graph.push(frame)
        ready = []
        while True:
            try:
                ready.append(self.graph.pull())
            except (av.BlockingIOError, av.error.EOFError):
                return ready


class VideoWriter:
    """Context manager: `with VideoWriter(path, fps, (w, h), audio=a) as out: out.write(frame_uint8)`.

    The output is checked when the writer is made (`plan_video`; or pass a `plan`), before any frame exists.
    Frames are uint8 [H, W, 3], or [H, W, 4] straight (not premultiplied) RGBA with `alpha=True`. The file is
    staged beside the target (`sdk.files.atomic_path`; an image sequence in a staging folder, `atomic_files`) and
    appears under its name only when complete: a failure leaves no partial video. The audio (mono float samples)
    is muxed where the container holds audio, cut to the frames written.

    With `encoded_like` (a video file written by this class with the same plan), the writer encodes no frames: it
    copies that file's stream parameters, and `append_encoded` appends the packets of such files one after the
    other (segments of one clip, joined without decoding them: docs/batch.md, "Long audio").
    """

    def __init__(self, path: str | os.PathLike, fps: float, size: tuple[int, int], *,
                 audio: np.ndarray | None = None, sample_rate: int = TARGET_SAMPLE_RATE, alpha: bool = False,
                 codec: str | None = None, crf: int | None = None, preset: str | None = None,
                 container: str | None = None, plan: VideoPlan | None = None,
                 encoded_like: str | os.PathLike | None = None) -> None:
        self.plan = plan or plan_video(path, size, alpha=alpha, codec=codec, crf=crf, preset=preset,
                                       container=container)
        self.path = self.plan.path
        self.rate = video_rate(fps)
        self.audio = None if audio is None or not self.plan.with_audio else pad_to_whole_frames(audio, sample_rate, fps)
        self.sample_rate = sample_rate
        self.frames_written = 0
        self._audio_written = 0
        self._stack: ExitStack | None = None
        self._output = self._video = self._audio_stream = self._palette = None
        self._encoded_like = encoded_like

    def __enter__(self) -> VideoWriter:
        import av

        plan = self.plan
        with ExitStack() as stack:
            if plan.container.sequence:
                target = stack.enter_context(atomic_files(self.path.parent)) / self.path.name
            else:  # the staged name keeps the target's extension, as some muxers look at it
                target = stack.enter_context(atomic_path(self.path, suffix=".partial" + self.path.suffix)).path
            try:
                self._output = av.open(str(target), "w", format=plan.container.muxer)
                stack.callback(self._abandon)
                if self._encoded_like is not None:
                    with av.open(str(self._encoded_like)) as like:
                        self._video = self._output.add_stream_from_template(like.streams.video[0])
                else:
                    self._video = self._output.add_stream(plan.codec.encoder, rate=self.rate,
                                                          options=plan.encoder_options())
                    self._video.width, self._video.height = plan.encoded_size
                    self._video.pix_fmt = plan.pix_fmt
                    self._video.codec_context.open()
                if self.audio is not None:
                    self._audio_stream = self._output.add_stream(plan.container.audio_codec, rate=self.sample_rate,
                                                                 layout="mono")
            except av.error.FFmpegError as exc:
                raise VideoError(f"cannot start writing {self.path} ({plan.describe()}): {exc.strerror}") from None
            if plan.codec.name == "gif":
                self._palette = _PaletteFilter(*plan.encoded_size, self.rate)
            self._stack = stack.pop_all()  # kept open until __exit__ commits or removes the staged output
        return self

    def write(self, frame: np.ndarray) -> None:
        """Append one uint8 frame: [H, W, 3], or [H, W, 4] with alpha."""
        import av

        if self._encoded_like is not None:
            raise VideoError("a writer made with encoded_like takes encoded files (append_encoded), not frames")
        width, height = self.plan.size
        channels = 4 if self.plan.alpha else 3
        if frame.dtype != np.uint8 or frame.shape != (height, width, channels):
            raise VideoError(f"video frames must be uint8 [{height}, {width}, {channels}], got {frame.dtype} "
                             f"{list(frame.shape)}")
        pad_w, pad_h = self.plan.encoded_size[0] - width, self.plan.encoded_size[1] - height
        if pad_w or pad_h:  # 4:2:0 codecs need even sides: repeat the last column/row, every pixel is kept
            frame = np.pad(frame, ((0, pad_h), (0, pad_w), (0, 0)), mode="edge")
        picture = av.VideoFrame.from_ndarray(np.ascontiguousarray(frame), format="rgba" if self.plan.alpha else "rgb24")
        picture.pts = self.frames_written
        picture.time_base = 1 / self.rate
        try:
            for paletted in self._palette(picture) if self._palette is not None else [picture]:
                self._mux(self._video.encode(paletted))
            self.frames_written += 1
            self._write_audio_until(self._audio_end(self.frames_written))
        except av.error.FFmpegError as exc:
            raise VideoError(f"writing {self.path} failed at frame {self.frames_written}: {exc.strerror}") from None

    def append_encoded(self, path: str | os.PathLike) -> int:
        """Append every video packet of `path` (written like `encoded_like`, no audio) after the frames so far,
        unchanged but for their timestamps, and the audio up to its end; returns the frames appended."""
        import av

        if self._encoded_like is None:
            raise VideoError("append_encoded needs a writer made with encoded_like")
        frame_tb = 1 / self.rate
        appended = 0
        try:
            with av.open(str(path)) as part:
                stream = part.streams.video[0]
                to_frames = stream.time_base / frame_tb
                # Timestamps in frames of this part (exact at any fps), shifted by the frames before it. Decode
                # order advances one frame a packet, so a dts the demuxer left unset (Matroska's first ones behind
                # B-frames) is the first known one minus the packets between them: those few wait for it.
                waiting, anchor = [], None
                for packet in part.demux(stream):
                    if not packet.size or packet.pts is None:  # the demuxer's end-of-stream marker
                        continue
                    if anchor is None and packet.dts is not None:
                        anchor = appended - round(packet.dts * to_frames)  # decode index minus dts, in frames
                        for index, held in waiting:
                            self._mux_copied(held, index - anchor, to_frames)
                        waiting = []
                    if anchor is None:
                        waiting.append((appended, packet))
                    else:
                        self._mux_copied(packet, None if packet.dts is not None else appended - anchor, to_frames)
                    appended += 1
                for _, held in waiting:  # no dts at all: no reordering, decode order is presentation order
                    self._mux_copied(held, round(held.pts * to_frames), to_frames)
            self.frames_written += appended
            self._write_audio_until(self._audio_end(self.frames_written))
        except av.error.FFmpegError as exc:
            raise VideoError(f"joining {path} into {self.path} failed: {exc.strerror}") from None
        return appended

    def _mux_copied(self, packet, dts_frames: int | None, to_frames: Fraction) -> None:
        """Mux a packet of an appended part after the frames written so far: its timestamps in frames (dts given
        in frames, or None: its own), shifted by them."""
        first = self.frames_written
        packet.pts = first + round(packet.pts * to_frames)
        packet.dts = first + (round(packet.dts * to_frames) if dts_frames is None else dts_frames)
        packet.duration = 1
        packet.time_base = 1 / self.rate
        packet.stream = self._video
        self._output.mux(packet)

    def _audio_end(self, frames: int) -> int:
        """Audio samples that belong to the first `frames` video frames (all of them for the last frame)."""
        if self.audio is None:
            return 0
        return min(self.audio.shape[0], math.ceil(frames * self.sample_rate / self.rate - 1e-9))

    def _write_audio_until(self, end: int) -> None:
        """Encode the audio up to sample `end`, so audio and video packets interleave as the frames go."""
        import av

        if self._audio_stream is None or end <= self._audio_written:
            return
        chunk = self.audio[self._audio_written:end]
        samples = av.AudioFrame.from_ndarray(chunk[None, :], format="flt", layout="mono")
        samples.sample_rate = self.sample_rate
        samples.pts = self._audio_written
        samples.time_base = Fraction(1, self.sample_rate)
        self._mux(self._audio_stream.encode(samples))
        self._audio_written = end

    def _mux(self, packets) -> None:
        for packet in packets:
            self._output.mux(packet)

    def _finish(self) -> None:
        """Flush the encoders and write the container's trailer."""
        import av

        try:
            if self._palette is not None:  # frames the palette filter still holds, if any
                for paletted in self._palette(None):
                    self._mux(self._video.encode(paletted))
            for stream in (None if self._encoded_like is not None else self._video, self._audio_stream):
                if stream is not None:
                    self._mux(stream.encode(None))
            self._output.close()
        except av.error.FFmpegError as exc:
            raise VideoError(f"finishing {self.path} failed: {exc.strerror}") from None
        self._output = None

    def _abandon(self) -> None:
        """Close the container without caring about errors (the staged output is about to be removed)."""
        if self._output is not None:
            output, self._output = self._output, None
            try:
                output.close()
            except Exception:  # noqa: BLE001 - already failing; the original error is the one to report
                pass

    def __exit__(self, exc_type, exc, tb) -> None:
        stack, self._stack = self._stack, None
        try:
            if exc_type is None:
                if self.frames_written == 0:
                    raise VideoError(f"no frames were written to {self.path}; a video needs at least one")
                self._finish()
        except BaseException as error:
            stack.__exit__(type(error), error, error.__traceback__)  # removes the staged output
            raise
        stack.__exit__(exc_type, exc, tb)  # commits it, or removes it if the body raised


def probe_video(path: str | os.PathLike) -> dict:
    """What a written video holds (for tests and reports): frames, seconds, size, pixel format, alpha, audio."""
    import av

    with av.open(str(path)) as container:
        video = container.streams.video[0]
        codec = video.codec_context.name
        pix_fmt = video.codec_context.pix_fmt
        # VP9 keeps alpha in side data that only libvpx decodes; the container marks it with alpha_mode. GIF
        # decodes to bgra whatever the file holds; the SDK never writes GIF transparency.
        has_alpha = codec != "gif" and (video.metadata.get("alpha_mode") == "1" or any(
            component.is_alpha for component in av.VideoFormat(pix_fmt).components))
        frames = sum(1 for packet in container.demux(video) if packet.size)
        audio = list(container.streams.audio)
        seconds = float(container.duration / av.time_base) if container.duration else 0.0
        return {"frames": frames, "seconds": seconds, "width": video.width, "height": video.height,
                "pix_fmt": pix_fmt, "codec": codec, "has_alpha": has_alpha,
                "has_audio": bool(audio), "audio_codec": audio[0].codec_context.name if audio else None}
