"""Encoding and decoding a reference clip's pictures: H.264 frames (intra-only, or in groups of pictures), masks as
PNG or as the luma plane of an H.264 stream (docs/compositing.md, "The reference clip").

Every stored entry is one encoded picture (one H.264 access unit, one PNG file). In a clip coded in groups of `gop`
pictures, entry k*gop is a keyframe carrying its parameter sets and the entries after it up to the next keyframe
predict from the ones before, so a frame decodes from its group's keyframe on (`GroupDecoder`).

Encoding and decoding go through PyAV (libavcodec), which the runtime already needs for video out.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterable, Iterator
from fractions import Fraction
from typing import Generic, TypeVar

import av
import numpy as np

from .errors import GaussianTalkerError

# Stored codec name -> (libavcodec encoder, decoder). Frames: H.264 (fewer bytes than JPEG at the same PSNR on the
# demo clip: docs/compositing.md). Masks: 8-bit grey PNG (lossless), or "h264": the mask's 8-bit levels as the luma
# plane of a 4:2:0 H.264 picture (chroma constant), lossy and a tenth of PNG's bytes in groups of pictures.
FRAME_CODECS = {"h264": ("libx264", "h264")}
MASK_CODECS = {"png": ("png", "png"), "h264": ("libx264", "h264")}
# The PNG row filter of stored masks: "up" (each row minus the one above). On the demo clip's masks it decodes 3.2x
# faster than the Paeth filter libavcodec's encoder chose by default (0.42 against 1.35 ms at 480x600, once per
# composited frame) and the files are 4% smaller; "none" is smaller still but decodes a little slower
# (docs/compositing.md, "The reference clip"). Any filter decodes: bundles with Paeth masks play as before.
MASK_PNG_FILTER = "up"
# x264 constant-rate factor of stored frames: 18 keeps the demo clip visually lossless (its PSNR:
# docs/compositing.md, "The reference clip"). An export may re-encode a clip at a larger CRF, in groups of pictures
# (`encode_stream`; the `reference` export knob, docs/precision.md).
H264_CRF = 18
# x264's CRF range for 8-bit pictures: 0 (lossless) .. 51 (coarsest).
MAX_H264_CRF = 51
# x264's speed preset for clips coded in groups of pictures: "veryslow" spends ~10 ms a 480x600 picture at export
# and, on the demo clip, is the only preset whose bytes fall steadily with the CRF ("medium" and "slow" spent more
# bytes at CRF 28 than at 24). Decoding costs the same whatever the preset (docs/compositing.md).
GOP_ENCODER_PRESET = "veryslow"
# The colour description written into each frame's H.264 stream (its VUI): what swscale's RGB -> yuv420p conversion
# does (the BT.601 matrix, limited range) on sRGB pictures, so a native decoder that honours the tags converts back
# exactly as the runtime does, and one that guesses from the size (BT.709 for HD) is told otherwise.
H264_COLOUR_TAGS = "colorprim=bt709:transfer=iec61966-2-1:colormatrix=bt470bg:range=tv"
# An H.264 mask is levels, not colour: tagged full range so that no player rescales its luma.
H264_MASK_TAGS = "range=pc"
# The mask's chroma planes (no colour: the middle level).
_NEUTRAL_CHROMA = 128
MASK_LEVELS = 255.0
T = TypeVar("T")


class ReferenceClipError(GaussianTalkerError, ValueError):
    """A reference clip is unusable: counts or sizes disagree, a mask is out of range or empty, a frame is not
    decodable. Callers add where the clip came from (a checkpoint or a bundle)."""


def check_crf(crf: int) -> int:
    """An x264 CRF as an int; ReferenceClipError unless an integer 0..MAX_H264_CRF."""
    if isinstance(crf, bool) or not isinstance(crf, int | np.integer) or not 0 <= crf <= MAX_H264_CRF:
        raise ReferenceClipError(f"an H.264 CRF must be an integer 0..{MAX_H264_CRF}, got {crf!r}")
    return int(crf)


def _h264_options(crf: int, tags: str, gop: int) -> dict[str, str]:
    options = {"crf": str(check_crf(crf)), "bf": "0", "x264-params": tags}
    if gop > 1:  # a keyframe every `gop` pictures exactly (no scene cuts), parameter sets repeated in each
        options["preset"] = GOP_ENCODER_PRESET
        options["x264-params"] += f":keyint={gop}:min-keyint={gop}:scenecut=0:repeat-headers=1"
    return options


def _context(encoder: str, width: int, height: int, pix_fmt: str, options: dict[str, str]):
    try:
        context = av.CodecContext.create(encoder, "w")
    except av.error.FFmpegError as exc:
        raise ReferenceClipError(f"this PyAV build cannot encode with {encoder}: {exc}") from None
    context.width, context.height, context.pix_fmt = width, height, pix_fmt
    context.time_base = Fraction(1, 25)
    context.options = options
    return context


def encode_picture(encoder: str, frame: av.VideoFrame, pix_fmt: str, options: dict[str, str]) -> bytes:
    """One picture -> one self-contained packet (a fresh encoder each time: no state shared between frames)."""
    context = _context(encoder, frame.width, frame.height, pix_fmt, options)
    context.gop_size = 1
    picture = frame.reformat(format=pix_fmt)
    picture.pts = 0
    packets = context.encode(picture) + context.encode(None)
    return b"".join(bytes(packet) for packet in packets)


def encode_stream(pictures: Iterable[av.VideoFrame], size: tuple[int, int], crf: int, gop: int, tags: str,
                  label: str) -> list[bytes]:
    """4:2:0 pictures -> one H.264 access unit each, a keyframe every `gop` (gop 1: each picture its own encoder,
    as `encode_frame`). ReferenceClipError if the encoder's packets do not follow that pattern."""
    options = _h264_options(crf, tags, gop)
    if gop == 1:
        return [encode_picture("libx264", _fresh(picture), "yuv420p", options) for picture in pictures]
    context = _context("libx264", *size, "yuv420p", options)
    packets = []
    for index, picture in enumerate(pictures):
        picture = _fresh(picture)
        picture.pts = index
        packets += context.encode(picture)
    packets += context.encode(None)
    keys = [packet.is_keyframe for packet in packets]
    if keys != [index % gop == 0 for index in range(len(packets))]:
        raise ReferenceClipError(f"{label}: the encoder did not put a keyframe exactly every {gop} pictures")
    return [bytes(packet) for packet in packets]


def _fresh(picture: av.VideoFrame) -> av.VideoFrame:
    """A 4:2:0 copy of a picture without the decoder's picture type (an "I" type makes libx264 code a keyframe)."""
    copy = av.VideoFrame.from_ndarray(picture.reformat(format="yuv420p").to_ndarray(), format="yuv420p")
    copy.color_range, copy.colorspace = picture.color_range, picture.colorspace
    return copy


def encode_frame(rgb: np.ndarray, codec: str = "h264", crf: int = H264_CRF) -> bytes:
    """uint8 [H, W, 3] RGB (even sides) -> one intra-coded H.264 frame (4:2:0, CRF `crf`, colour tags
    H264_COLOUR_TAGS)."""
    rgb = np.ascontiguousarray(rgb)
    if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ReferenceClipError(f"a reference frame must be uint8 [H, W, 3], got {rgb.dtype} {list(rgb.shape)}")
    return encode_picture(FRAME_CODECS[codec][0], av.VideoFrame.from_ndarray(rgb, format="rgb24"), "yuv420p",
                   _h264_options(crf, H264_COLOUR_TAGS, 1))


def quantise_mask(mask: np.ndarray) -> np.ndarray:
    """float [H, W] in [0, 1] -> the uint8 levels a mask is stored as (round(M * 255))."""
    return np.floor(np.asarray(mask, dtype=np.float32) * np.float32(MASK_LEVELS) + np.float32(0.5)).astype(np.uint8)


def encode_mask(mask: np.ndarray, codec: str = "png") -> bytes:
    """float [H, W] in [0, 1] (checked by `check_mask`) -> 8-bit grey PNG of round(M * 255)."""
    frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(quantise_mask(mask)), format="gray")
    return encode_picture(MASK_CODECS[codec][0], frame, "gray", {"pred": MASK_PNG_FILTER})


def mask_picture(levels: np.ndarray) -> av.VideoFrame:
    """A mask's uint8 levels [H, W] (even sides) -> the 4:2:0 picture an H.264 mask codes: luma = the levels."""
    height, width = levels.shape
    chroma = np.full((height // 2, width), _NEUTRAL_CHROMA, np.uint8)  # U then V, each [H/2, W/2], row-packed
    return av.VideoFrame.from_ndarray(np.concatenate([levels, chroma]), format="yuv420p")


def encode_mask_stream(levels: Iterable[np.ndarray], size: tuple[int, int], crf: int, gop: int,
                       label: str) -> list[bytes]:
    """Masks' uint8 levels -> H.264 access units whose luma planes are the levels (`mask_picture`)."""
    return encode_stream((mask_picture(mask) for mask in levels), size, crf, gop, H264_MASK_TAGS, label)


def decode_picture(codec: str, data: bytes, label: str) -> av.VideoFrame:
    """The one picture of a self-contained packet (a fresh decoder, flushed: no state shared between frames)."""
    if not data:
        raise ReferenceClipError(f"{label} is empty")
    try:
        decoder = av.CodecContext.create(codec, "r")
        frames = decoder.decode(av.Packet(bytes(data))) + decoder.decode(None)
    except (av.error.FFmpegError, ValueError) as exc:
        raise ReferenceClipError(f"{label} is not decodable as {codec}: {exc}") from None
    if len(frames) != 1:
        raise ReferenceClipError(f"{label} is not decodable as {codec}: {len(frames)} pictures in the entry")
    return frames[0]


def decode_group(codec: str, packets: Iterable[bytes], labels: list[str]) -> Iterator[av.VideoFrame]:
    """The pictures of one group of entries (a keyframe and those predicted from it), one per entry, in order.
    Each picture is yielded as soon as the decoder gives it; ReferenceClipError naming the entry that fails."""
    try:
        decoder = av.CodecContext.create(codec, "r")
    except av.error.FFmpegError as exc:
        raise ReferenceClipError(f"this PyAV build cannot decode {codec}: {exc}") from None
    given = 0
    for index, data in enumerate(packets):
        if not data:
            raise ReferenceClipError(f"{labels[index]} is empty")
        try:
            pictures = decoder.decode(av.Packet(bytes(data)))
        except (av.error.FFmpegError, ValueError) as exc:
            raise ReferenceClipError(f"{labels[index]} is not decodable as {codec}: {exc}") from None
        for picture in pictures:
            if given == len(labels):
                break
            given += 1
            yield picture
    try:
        pictures = decoder.decode(None)
    except (av.error.FFmpegError, ValueError) as exc:
        raise ReferenceClipError(f"{labels[-1]} is not decodable as {codec}: {exc}") from None
    for picture in pictures[:len(labels) - given]:
        given += 1
        yield picture
    if given != len(labels):
        raise ReferenceClipError(f"{labels[given]} is not decodable as {codec}: its group of pictures gave "
                                 f"{given} pictures for {len(labels)} entries")


def luma_levels(picture: av.VideoFrame, label: str) -> np.ndarray:
    """An H.264 mask's levels: the luma plane of its 4:2:0 picture, uint8 [H, W]."""
    if picture.format.name not in ("yuv420p", "yuvj420p"):
        raise ReferenceClipError(f"{label} must be 4:2:0 (yuv420p), got pixel format {picture.format.name}")
    plane = picture.planes[0]
    rows = np.frombuffer(plane, np.uint8).reshape(picture.height, plane.line_size)
    return rows[:, :picture.width].copy()


class GroupDecoder(Generic[T]):
    """Random access to a stream stored in groups of `gop` pictures: the group a requested index falls in is
    decoded from its keyframe, each picture converted once (`convert`) and held until another group is asked for.
    Played forwards a picture costs one decode; played backwards a group is decoded once when it is entered, and
    at most `gop` converted pictures are held. Thread-safe (one decode at a time)."""

    def __init__(self, codec: str, count: int, gop: int, packet: Callable[[int], bytes],
                 convert: Callable[[av.VideoFrame, int], T], label: Callable[[int], str]) -> None:
        self.codec, self.count, self.gop = codec, count, gop
        self._packet, self._convert, self._label = packet, convert, label
        self._lock = threading.Lock()
        self._group: int | None = None
        self._held: list[T] = []
        self._pictures: Iterator[av.VideoFrame] | None = None

    def __getitem__(self, index: int) -> T:
        with self._lock:
            group, offset = divmod(index, self.gop)
            if group != self._group:
                first, end = group * self.gop, min(self.count, (group + 1) * self.gop)
                packets = (self._packet(i) for i in range(first, end))
                self._pictures = decode_group(self.codec, packets, [self._label(i) for i in range(first, end)])
                self._group, self._held = group, []
            try:  # offset < the group's length, so decode_group gives the picture or raises
                while len(self._held) <= offset:
                    position = group * self.gop + len(self._held)
                    self._held.append(self._convert(next(self._pictures), position))
            except ReferenceClipError:  # a failed group is decoded afresh when next asked for
                self._group, self._held = None, []
                raise
            return self._held[offset]


__all__ = ["FRAME_CODECS", "GOP_ENCODER_PRESET", "H264_COLOUR_TAGS", "H264_CRF", "H264_MASK_TAGS", "MASK_CODECS",
           "MASK_LEVELS", "MASK_PNG_FILTER", "MAX_H264_CRF", "GroupDecoder", "ReferenceClipError", "check_crf",
           "decode_group", "decode_picture", "encode_frame", "encode_mask", "encode_mask_stream", "encode_picture",
           "encode_stream", "luma_levels", "mask_picture", "quantise_mask"]
