"""The video outputs the SDK writes, and the check that runs before the first frame is rendered.

`plan_video` turns an output path plus options into a `VideoPlan` (container, codec, pixel format, encoded size),
or raises `VideoError` naming what is wrong: a folder given as the output, an unwritable folder, an unknown
extension, a codec the container cannot hold, alpha where the codec has no alpha plane, a size the encoder
refuses. It opens the encoder once with the real size, so nothing found later can waste a render.
docs/video.md lists every output with its pixel format and what odd sizes become.
"""

from __future__ import annotations

import os
import re
import tempfile
from dataclasses import dataclass, field
from fractions import Fraction
from pathlib import Path

from .errors import VideoError

# A printf-style frame number in an image-sequence path: %d or %0Nd (exactly one).
SEQUENCE_PATTERN = re.compile(r"%0?\d*d")


@dataclass(frozen=True)
class CodecSpec:
    """A video codec as offered to users: its libav encoder, pixel formats, quality range and speed presets."""

    name: str
    encoder: str
    pix_fmt: str  # opaque frames
    alpha_pix_fmt: str | None  # frames with an alpha plane; None: the codec has none
    even_sides: bool = False  # 4:2:0 chroma: an odd side is padded by repeating the last row/column
    crf: tuple[int, int, int] | None = None  # (lowest, highest, default) constant-rate factor; None: no such knob
    presets: tuple[str, ...] = ()  # speed presets; the first is the default
    options: dict[str, str] = field(default_factory=dict)  # fixed encoder options
    max_side: int | None = None  # largest width or height the encoder takes (None: checked by opening it)


@dataclass(frozen=True)
class ContainerSpec:
    """A container: libav muxer, file extensions, codecs it holds (default first), audio codec or None."""

    name: str
    muxer: str
    extensions: tuple[str, ...]
    codecs: tuple[str, ...]
    audio_codec: str | None
    sequence: bool = False  # one image file per frame, the path holds a %d frame number


# No HEVC: the libx265 in PyAV's wheel corrupted the heap (abort at exit) writing 48x32 frames while 64x32 and
# 66x66 worked; an encoder that can crash the app on some sizes is not offered (docs/video.md).
_X264_PRESETS = ("veryfast", "ultrafast", "superfast", "faster", "fast", "medium", "slow", "slower", "veryslow")

CODECS: dict[str, CodecSpec] = {
    # "veryfast": libx264 encodes far faster than the runtime renders, so encoding never competes with rendering
    # for the CPU; "medium" (x264's default) makes slightly smaller files at several times the CPU time
    # (measured: docs/video.md, "Codec settings").
    "h264": CodecSpec("h264", "libx264", "yuv420p", None, even_sides=True, crf=(0, 51, 18), presets=_X264_PRESETS,
                      max_side=16384),
    # libvpx's constant-quality mode needs a zero target bitrate. "deadline=realtime" with cpu-used 5: faster than
    # rendering (cpu-used 0 is slower than rendering; 8 is barely faster but makes much larger files); the
    # measured times: docs/video.md, "Codec settings".
    "vp9": CodecSpec("vp9", "libvpx-vp9", "yuv420p", "yuva420p", crf=(0, 63, 32),
                     presets=("realtime", "good", "best"), options={"b": "0", "row-mt": "1", "cpu-used": "5"}),
    # ProRes 4444 (profile 4) for alpha, 422 HQ (profile 3) otherwise; both 10-bit and intra-only.
    "prores": CodecSpec("prores", "prores_ks", "yuv422p10le", "yuva444p10le"),
    "ffv1": CodecSpec("ffv1", "ffv1", "yuv444p", "yuva444p"),
    "gif": CodecSpec("gif", "gif", "pal8", None),
    "png": CodecSpec("png", "png", "rgb24", "rgba"),
}

CONTAINERS: dict[str, ContainerSpec] = {
    "mp4": ContainerSpec("mp4", "mp4", (".mp4", ".m4v"), ("h264",), "aac"),
    "mov": ContainerSpec("mov", "mov", (".mov",), ("h264", "prores"), "aac"),
    "webm": ContainerSpec("webm", "webm", (".webm",), ("vp9",), "libopus"),
    "mkv": ContainerSpec("mkv", "matroska", (".mkv",), ("h264", "vp9", "ffv1", "prores"), "aac"),
    "gif": ContainerSpec("gif", "gif", (".gif",), ("gif",), None),
    "png": ContainerSpec("png", "image2", (".png",), ("png",), None, sequence=True),
}

# With alpha and no --codec, the container's first codec that has an alpha plane.
_ALPHA_HINT = "webm (vp9), mov (--codec prores), mkv (vp9, ffv1, prores) or a png sequence (frames/%05d.png)"


@dataclass(frozen=True)
class VideoPlan:
    """Everything decided before rendering: where, which container and codec, at what size and pixel format."""

    path: Path
    container: ContainerSpec
    codec: CodecSpec
    size: tuple[int, int]  # (width, height) of the frames the caller writes
    encoded_size: tuple[int, int]  # (width, height) in the file: size, or padded to even sides (4:2:0 codecs)
    pix_fmt: str
    alpha: bool
    crf: int | None
    preset: str | None

    @property
    def with_audio(self) -> bool:
        """Whether the container holds an audio stream (image sequences and gif do not)."""
        return self.container.audio_codec is not None

    def encoder_options(self) -> dict[str, str]:
        """libav options of the video encoder: fixed ones, quality, speed preset, ProRes profile."""
        options = dict(self.codec.options)
        if self.crf is not None:
            options["crf"] = str(self.crf)
        if self.preset is not None:
            options["deadline" if self.codec.name == "vp9" else "preset"] = self.preset
        if self.codec.name == "prores":
            options["profile"] = "4" if self.alpha else "3"
        return options

    def describe_size(self) -> str:
        """'WxH', with the padded size when the codec needs even sides (docs/video.md says why it cannot crop)."""
        padded = "" if self.encoded_size == self.size else (
            f" (padded to {self.encoded_size[0]}x{self.encoded_size[1]}: {self.codec.name} 4:2:0 needs even sides; "
            "webm/VP9 keeps odd sizes)")
        return f"{self.size[0]}x{self.size[1]}{padded}"

    def describe(self) -> str:
        """One line for logs: container, codec, pixel format, size (and padding)."""
        codec = f"{self.codec.name} ({self.codec.encoder}, {self.pix_fmt})"
        return f"{self.container.name} / {codec}, {self.describe_size()}"


def _container_for(path: Path, name: str | None) -> ContainerSpec:
    if name is not None:
        if name not in CONTAINERS:
            raise VideoError(f"unknown video format {name!r} (known: {', '.join(CONTAINERS)})")
        return CONTAINERS[name]
    suffix = path.suffix.lower()
    for container in CONTAINERS.values():
        if suffix in container.extensions:
            return container
    known = ", ".join(ext for c in CONTAINERS.values() for ext in c.extensions)
    shown = f"extension {suffix!r}" if suffix else "no extension"
    raise VideoError(f"{path}: {shown} is not a video format the SDK writes (known: {known}; or pass a format)")


def _check_destination(path: Path, container: ContainerSpec) -> None:
    """The output is not a folder, and its folder (or the nearest existing parent) takes a new file."""
    if container.sequence and len(SEQUENCE_PATTERN.findall(path.name)) != 1:
        raise VideoError(f"{path}: an image sequence needs exactly one frame number like %05d in the file name")
    parent = path.parent.absolute()
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise VideoError(f"{path}: {parent} is not a folder")
    try:  # a real file, not os.access: root passes os.access on read-only file systems
        with tempfile.TemporaryFile(dir=parent):
            pass
    except OSError as exc:
        raise VideoError(f"{path}: cannot write in folder {parent} ({exc.strerror or exc})") from None


def _check_encoder_opens(plan: VideoPlan) -> None:
    """Open the encoder in memory with the real size and options: whatever it refuses is refused now."""
    import av

    try:
        context = av.CodecContext.create(plan.codec.encoder, "w")
    except Exception:
        raise VideoError(f"codec {plan.codec.name}: encoder {plan.codec.encoder} is not in this ffmpeg build") from None
    context.width, context.height = plan.encoded_size
    context.pix_fmt = plan.pix_fmt
    context.time_base = Fraction(1, 25)
    context.framerate = Fraction(25)
    context.options = plan.encoder_options()
    try:
        context.open()
    except av.error.FFmpegError as exc:
        raise VideoError(f"codec {plan.codec.name} ({plan.codec.encoder}) refuses {plan.describe_size()} frames "
                         f"with these settings: {exc.strerror}") from None


def plan_video(path: str | os.PathLike, size: tuple[int, int], *, alpha: bool = False, codec: str | None = None,
               crf: int | None = None, preset: str | None = None, container: str | None = None) -> VideoPlan:
    """Decide and check a video output before rendering (see the module docstring); VideoError if it cannot work."""
    path = Path(path)
    if path.is_dir():
        raise VideoError(f"{path} is a folder; give a file name such as {path / 'talk.mp4'}")
    spec = _container_for(path, container)
    _check_destination(path, spec)
    width, height = (int(v) for v in size)
    if width < 1 or height < 1:
        raise VideoError(f"frame size must be at least 1x1, got {width}x{height}")
    if codec is None:
        candidates = [c for c in spec.codecs if not alpha or CODECS[c].alpha_pix_fmt]
        if not candidates:
            raise VideoError(f"{spec.name} cannot hold an alpha channel; use {_ALPHA_HINT}")
        codec_spec = CODECS[candidates[0]]
    else:
        if codec not in spec.codecs:
            raise VideoError(f"{spec.name} cannot hold codec {codec!r} (it holds: {', '.join(spec.codecs)})")
        codec_spec = CODECS[codec]
    if alpha and codec_spec.alpha_pix_fmt is None:
        raise VideoError(f"codec {codec_spec.name} has no alpha plane; for alpha use {_ALPHA_HINT}")
    if crf is not None:
        if codec_spec.crf is None:
            raise VideoError(f"codec {codec_spec.name} has no crf setting")
        if not codec_spec.crf[0] <= crf <= codec_spec.crf[1]:
            raise VideoError(f"crf {crf} is outside {codec_spec.name}'s range {codec_spec.crf[0]}..{codec_spec.crf[1]}")
    if preset is not None and preset not in codec_spec.presets:
        offered = ", ".join(codec_spec.presets) if codec_spec.presets else "none"
        raise VideoError(f"preset {preset!r} is not one of {codec_spec.name}'s presets ({offered})")
    encoded = (width + width % 2, height + height % 2) if codec_spec.even_sides else (width, height)
    if codec_spec.max_side is not None and max(encoded) > codec_spec.max_side:
        raise VideoError(f"codec {codec_spec.name} encodes at most {codec_spec.max_side} pixels a side, got "
                         f"{width}x{height}")
    plan = VideoPlan(
        path=path, container=spec, codec=codec_spec, size=(width, height), encoded_size=encoded,
        pix_fmt=codec_spec.alpha_pix_fmt if alpha else codec_spec.pix_fmt, alpha=alpha,
        crf=crf if crf is not None else (codec_spec.crf[2] if codec_spec.crf else None),
        preset=preset if preset is not None else (codec_spec.presets[0] if codec_spec.presets else None))
    _check_encoder_opens(plan)
    return plan


__all__ = ["CODECS", "CONTAINERS", "CodecSpec", "ContainerSpec", "VideoPlan", "plan_video"]
