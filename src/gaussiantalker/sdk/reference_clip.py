"""A speaker's reference clip: its original video frames I_ori, facial masks M and the camera that aligns them.

The composited frame is I = (1 - M) I_ori + M F(I_gau + (1 - M) I_ori) (docs/compositing.md). A clip is stored
encoded, one entry per frame and per mask: H.264 frames, intra-only or in groups of pictures, and 8-bit PNG or H.264
masks (`sdk/clip_codec.py`; the choices are measured in docs/compositing.md). A player decodes a frame from its
group's keyframe on and holds at most one group of decoded pictures. Frame i is aligned with row i of the speaker's
pose track; the clip is played forth and back like the track (`drive.track_row`).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass

import av
import numpy as np

from .camera import Camera
from .clip_codec import (
    FRAME_CODECS,
    H264_COLOUR_TAGS,
    H264_CRF,
    MASK_CODECS,
    MASK_LEVELS,
    MASK_PNG_FILTER,
    MAX_H264_CRF,
    GroupDecoder,
    ReferenceClipError,
    check_crf,
    decode_group,
    decode_picture,
    encode_frame,
    encode_mask,
    encode_mask_stream,
    encode_picture,
    encode_stream,
    luma_levels,
    quantise_mask,
)
from .errors import BundleError, CameraError

MAX_CLIP_FRAMES = 100_000
# A mask must have at least this many pixels at M >= 0.5: a clip "with no face in the mask" is refused.
MIN_FACE_PIXELS = 16
# The crop the inpainting generator F sees (the bundle records both; docs/compositing.md): pixels of context around
# the mask's support on every side (its receptive field at half resolution), and the multiple every crop side is
# padded to (the generator pools by 2 and has up to 3 stride-2 levels).
CROP_MARGIN_PX = 16
CROP_MULTIPLE = 16


def frame_entry(index: int) -> str:
    """Bundle entry holding encoded frame `index`."""
    return f"reference/frame/{index:05d}"


def mask_entry(index: int) -> str:
    """Bundle entry holding encoded mask `index`."""
    return f"reference/mask/{index:05d}"


def _check_gop(gop, what: str) -> None:
    """ReferenceClipError naming `what` unless `gop` is an integer 1..MAX_CLIP_FRAMES (pictures per group)."""
    if isinstance(gop, bool) or not isinstance(gop, int) or not 1 <= gop <= MAX_CLIP_FRAMES:
        raise ReferenceClipError(f"{what} must be an integer in 1..{MAX_CLIP_FRAMES}, got {gop!r}")


@dataclass(frozen=True)
class ClipLayout:
    """What the manifest (and checkpoint) records about a clip: frame count, codecs, the aligning camera (its
    width and height are the clip's frame size) and `gop`, the pictures per group of every H.264 stream in the clip
    (1: each entry decodes alone)."""

    count: int
    camera: Camera
    frame_codec: str = "h264"
    mask_codec: str = "png"
    gop: int = 1

    def __post_init__(self) -> None:
        if not (isinstance(self.count, int) and 1 <= self.count <= MAX_CLIP_FRAMES):
            raise ReferenceClipError(f"reference clip 'count' must be an integer in 1..{MAX_CLIP_FRAMES}, "
                                     f"got {self.count!r}")
        if self.frame_codec not in FRAME_CODECS:
            raise ReferenceClipError(f"reference clip 'frame_codec' {self.frame_codec!r} is not one of "
                                     f"{sorted(FRAME_CODECS)}")
        width, height = self.size
        if width % 2 or height % 2:
            raise ReferenceClipError(f"reference clip frames must have even sides (H.264 4:2:0), got "
                                     f"{width}x{height}")
        if self.mask_codec not in MASK_CODECS:
            raise ReferenceClipError(f"reference clip 'mask_codec' {self.mask_codec!r} is not one of "
                                     f"{sorted(MASK_CODECS)}")
        _check_gop(self.gop, "reference clip 'gop'")

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) of every frame and mask."""
        return self.camera.width, self.camera.height

    def to_dict(self) -> dict:
        """The manifest's `reference` table; `gop` only when above 1, so an intra-only clip's table is what players
        written before groups of pictures read."""
        data = {"count": self.count, "camera": self.camera.to_dict(), "frame_codec": self.frame_codec,
                "mask_codec": self.mask_codec}
        return data | ({"gop": self.gop} if self.gop > 1 else {})

    @classmethod
    def from_dict(cls, data) -> ClipLayout:
        """Inverse of to_dict; ReferenceClipError naming the bad field."""
        if not isinstance(data, dict):
            raise ReferenceClipError(f"reference clip description must be a table, got {type(data).__name__}")
        unknown = sorted(set(data) - {"count", "camera", "frame_codec", "mask_codec", "gop"})
        if unknown:
            raise ReferenceClipError(f"reference clip has unknown field(s) {unknown}")
        try:
            camera = Camera.from_dict(data["camera"])
        except KeyError:
            raise ReferenceClipError("reference clip has no 'camera'") from None
        except (CameraError, TypeError, AttributeError) as exc:
            raise ReferenceClipError(f"reference clip 'camera' is invalid: {exc}") from None
        count = data.get("count")
        return cls(count if not isinstance(count, bool) else None, camera, data.get("frame_codec", "h264"),
                   data.get("mask_codec", "png"), data.get("gop", 1))


@dataclass(frozen=True)
class ClipCoding:
    """How an export re-encodes a clip (the `reference` export knob, docs/precision.md): the frames' x264 CRF, the
    pictures per group of every H.264 stream, and the masks' CRF (None: the masks are kept as stored)."""

    crf: int
    gop: int = 1
    mask_crf: int | None = None

    def __post_init__(self) -> None:
        check_crf(self.crf)
        if self.mask_crf is not None:
            check_crf(self.mask_crf)
        _check_gop(self.gop, "a clip's pictures per group")


def _check_size(label: str, picture: av.VideoFrame, size: tuple[int, int]) -> None:
    if (picture.width, picture.height) != size:
        raise ReferenceClipError(f"{label} is {picture.width}x{picture.height}, the clip is {size[0]}x{size[1]}")


def _frame_rgb(picture: av.VideoFrame, layout: ClipLayout, label: str) -> np.ndarray:
    _check_size(label, picture, layout.size)
    return picture.to_ndarray(format="rgb24")


def _mask_levels(picture: av.VideoFrame, layout: ClipLayout, label: str) -> np.ndarray:
    _check_size(label, picture, layout.size)
    if layout.mask_codec == "h264":
        return luma_levels(picture, label)
    if picture.format.name != "gray":
        raise ReferenceClipError(f"{label} must be an 8-bit grey image, got pixel format {picture.format.name}")
    return picture.to_ndarray()


def decode_frame(data: bytes, layout: ClipLayout, label: str) -> np.ndarray:
    """One self-contained encoded frame (a keyframe) -> uint8 [H, W, 3] RGB, checked against the clip's size."""
    return _frame_rgb(decode_picture(FRAME_CODECS[layout.frame_codec][1], data, label), layout, label)


def reencode_frame(data: bytes, layout: ClipLayout, label: str, crf: int) -> bytes:
    """One stored intra frame re-encoded at CRF `crf` (intra-only, the same colour tags). The decoded 4:2:0 picture
    goes to the encoder as it is, so the only loss added is the new encode's (no RGB round trip)."""
    picture = decode_picture(FRAME_CODECS[layout.frame_codec][1], data, label)
    _check_size(label, picture, layout.size)
    if picture.format.name != "yuv420p":
        raise ReferenceClipError(f"{label} must be 4:2:0 (yuv420p), got pixel format {picture.format.name}")
    return encode_stream([picture], layout.size, crf, 1, H264_COLOUR_TAGS, label)[0]


def decode_mask_levels(data: bytes, layout: ClipLayout, label: str) -> np.ndarray:
    """One self-contained encoded mask -> its uint8 levels [H, W] (M * 255); a colour or 16-bit PNG is refused."""
    return _mask_levels(decode_picture(MASK_CODECS[layout.mask_codec][1], data, label), layout, label)


def decode_mask(data: bytes, layout: ClipLayout, label: str) -> np.ndarray:
    """One self-contained encoded mask -> float32 [H, W] in [0, 1] (its 8-bit levels / 255)."""
    return decode_mask_levels(data, layout, label).astype(np.float32) / np.float32(MASK_LEVELS)


def check_mask(mask: np.ndarray, size: tuple[int, int], label: str) -> np.ndarray:
    """A float mask [H, W] of the clip's size, finite, in [0, 1] and with a face in it, as float32."""
    mask = np.asarray(mask)
    if mask.shape != (size[1], size[0]):
        raise ReferenceClipError(f"{label} has shape {list(mask.shape)}, the clip's frames are [{size[1]}, "
                                 f"{size[0]}] (height, width)")
    if not np.issubdtype(mask.dtype, np.floating):
        raise ReferenceClipError(f"{label} must hold floats in [0, 1], got {mask.dtype}")
    bad = ~((mask >= 0.0) & (mask <= 1.0))  # NaN fails too
    if bad.any():
        y, x = np.argwhere(bad)[0]
        raise ReferenceClipError(f"{label} must lie in [0, 1]: value {float(mask[y, x])!r} at row {y}, column {x} "
                                 f"({int(bad.sum())} such pixels)")
    if int((mask >= 0.5).sum()) < MIN_FACE_PIXELS:
        raise ReferenceClipError(f"{label} has no face in it (fewer than {MIN_FACE_PIXELS} pixels at M >= 0.5)")
    return mask.astype(np.float32)


def _pictures(codec: str, entries: list[bytes], gop: int, label: Callable[[int], str]) -> Iterator[av.VideoFrame]:
    """Every picture of a stored stream, in order, decoded group by group."""
    for first in range(0, len(entries), gop):
        indices = range(first, min(len(entries), first + gop))
        yield from decode_group(codec, (entries[i] for i in indices), [label(i) for i in indices])


def _held(picture: np.ndarray) -> np.ndarray:
    """A decoded picture a group decoder holds and hands out again: read-only, so no caller changes it for the
    next."""
    picture.setflags(write=False)
    return picture


def _frame_label(index: int) -> str:
    return f"reference frame {index}"


def _mask_label(index: int) -> str:
    return f"reference mask {index}"


@dataclass
class EncodedClip:
    """A clip as the checkpoint and the bundle carry it: the layout plus one encoded entry per frame and mask."""

    layout: ClipLayout
    frames: list[bytes]
    masks: list[bytes]

    @classmethod
    def from_arrays(cls, frames: Iterable[np.ndarray], masks: Iterable[np.ndarray], camera: Camera) -> EncodedClip:
        """Encode frames (uint8 [H, W, 3]) and masks (float [H, W] in [0, 1]) of `camera`'s size, checking each."""
        size = (camera.width, camera.height)
        ClipLayout(1, camera)  # the camera's size is checked (even sides) before anything is encoded
        encoded_frames, encoded_masks = [], []
        for index, (frame, mask) in enumerate(zip(frames, masks, strict=True)):
            frame = np.asarray(frame)
            if frame.shape != (size[1], size[0], 3) or frame.dtype != np.uint8:
                raise ReferenceClipError(f"reference frame {index} must be uint8 [{size[1]}, {size[0]}, 3], got "
                                         f"{frame.dtype} {list(frame.shape)}")
            encoded_frames.append(encode_frame(frame))
            encoded_masks.append(encode_mask(check_mask(mask, size, f"reference mask {index}")))
        if not encoded_frames:
            raise ReferenceClipError("a reference clip needs at least one frame")
        return cls(ClipLayout(len(encoded_frames), camera), encoded_frames, encoded_masks)

    def frame_pictures(self) -> Iterator[av.VideoFrame]:
        """Every frame's decoded 4:2:0 picture, in order (one group of pictures decoded at a time)."""
        return _pictures(FRAME_CODECS[self.layout.frame_codec][1], self.frames, self.layout.gop, _frame_label)

    def mask_levels(self) -> Iterator[np.ndarray]:
        """Every mask's uint8 levels [H, W], in order."""
        gop = self.layout.gop if self.layout.mask_codec == "h264" else 1
        pictures = _pictures(MASK_CODECS[self.layout.mask_codec][1], self.masks, gop, _mask_label)
        return (_mask_levels(picture, self.layout, _mask_label(index)) for index, picture in enumerate(pictures))

    def check(self, track_frames: int | None) -> None:
        """Decode every entry once: counts agree with each other and the pose track, sizes match, masks have a
        face. Run at export, so a bundle never holds a clip that fails mid-video."""
        if not (len(self.frames) == len(self.masks) == self.layout.count):
            raise ReferenceClipError(f"reference clip has {len(self.frames)} frames and {len(self.masks)} masks "
                                     f"but declares {self.layout.count}")
        if track_frames is None:
            raise ReferenceClipError("a reference clip needs the speaker's pose track (the pose of each frame)")
        if track_frames != self.layout.count:
            raise ReferenceClipError(f"reference clip has {self.layout.count} frames but the pose track has "
                                     f"{track_frames} rows (one pose per frame)")
        for index, picture in enumerate(self.frame_pictures()):  # sizes only: no RGB conversion needed
            _check_size(_frame_label(index), picture, self.layout.size)
        for index, levels in enumerate(self.mask_levels()):
            check_mask(levels.astype(np.float32) / np.float32(MASK_LEVELS), self.layout.size, _mask_label(index))

    def reencoded(self, coding: ClipCoding | int) -> EncodedClip:
        """This clip re-encoded as `coding` says (a bare int: the frames at that CRF, intra-only, masks kept). The
        decoded 4:2:0 pictures go to the encoder as they are, so the only loss added is the new encode's."""
        coding = ClipCoding(coding) if not isinstance(coding, ClipCoding) else coding
        size = self.layout.size
        frames = encode_stream(self.frame_pictures(), size, coding.crf, coding.gop, H264_COLOUR_TAGS,
                               "reference frames")
        masks, mask_codec = list(self.masks), self.layout.mask_codec
        if coding.mask_crf is not None:
            masks = encode_mask_stream(self.mask_levels(), size, coding.mask_crf, coding.gop, "reference masks")
            mask_codec = "h264"
        elif mask_codec == "h264" and coding.gop != self.layout.gop:
            raise ReferenceClipError(f"masks stored as H.264 in groups of {self.layout.gop} cannot be kept in a clip "
                                     f"re-grouped by {coding.gop}: give the masks a CRF too")
        if len(frames) != self.layout.count or len(masks) != self.layout.count:
            raise ReferenceClipError(f"re-encoding gave {len(frames)} frames and {len(masks)} masks for a clip of "
                                     f"{self.layout.count}")
        layout = ClipLayout(self.layout.count, self.layout.camera, self.layout.frame_codec, mask_codec, coding.gop)
        return EncodedClip(layout, frames, masks)

    @property
    def frame_bytes(self) -> int:
        """Encoded size of every frame."""
        return sum(len(b) for b in self.frames)

    @property
    def nbytes(self) -> int:
        """Encoded size of every frame and mask."""
        return sum(len(b) for b in self.frames) + sum(len(b) for b in self.masks)


class ReferenceClip:
    """A bundle's reference clip, decoded one group of pictures at a time (optionally resized to an output size).

    Opening it reads every entry once to check its checksum and decodes the first frame and mask, so a damaged
    clip is refused at load, never mid-video; after that only the entries a frame's group needs are read.
    """

    def __init__(self, bundle, size: tuple[int, int] | None = None) -> None:
        self.bundle = bundle
        try:
            self.layout = ClipLayout.from_dict(bundle.manifest["reference"])
        except ReferenceClipError as exc:
            raise BundleError(f"{bundle.path}: manifest 'reference' is invalid: {exc}") from None
        self.size = tuple(size) if size is not None else self.layout.size
        if len(self.size) != 2 or min(self.size) < 1:
            raise ReferenceClipError(f"reference output size must be (width, height) >= 1, got {size!r}")
        missing = [name for i in range(len(self)) for name in (frame_entry(i), mask_entry(i))
                   if not bundle.has_buffer(name)]
        if missing:
            raise BundleError(f"{bundle.path}: reference clip of {len(self)} frames lacks {len(missing)} entries "
                              f"(first: {missing[0]!r})")
        for index in range(len(self)):  # checksums of every entry: BundleError naming a damaged one
            bundle.buffer(frame_entry(index))
            bundle.buffer(mask_entry(index))
        layout = self.layout
        self._frames = GroupDecoder(FRAME_CODECS[layout.frame_codec][1], len(self), layout.gop,
                                    lambda i: bundle.buffer(frame_entry(i)).tobytes(), self._convert_frame,
                                    lambda i: f"reference frame {i}")
        self._masks = GroupDecoder(MASK_CODECS[layout.mask_codec][1], len(self),
                                   layout.gop if layout.mask_codec == "h264" else 1,
                                   lambda i: bundle.buffer(mask_entry(i)).tobytes(), self._convert_mask,
                                   lambda i: f"reference mask {i}")
        try:
            self.frame(0)
            self.mask(0)
        except ReferenceClipError as exc:
            raise BundleError(f"{bundle.path}: {exc}") from None

    def __len__(self) -> int:
        return self.layout.count

    @property
    def camera(self) -> Camera:
        """The camera that aligns the Gaussians with the clip, at the output size."""
        camera = self.layout.camera
        return camera if self.size == self.layout.size else camera.resized(*self.size)

    def _index(self, index: int) -> int:
        if not (isinstance(index, int | np.integer) and 0 <= index < len(self)):
            raise IndexError(f"reference frame index {index!r} is outside 0..{len(self) - 1}")
        return int(index)

    def _resized(self, picture: np.ndarray, pix_fmt: str) -> np.ndarray:
        if self.size == self.layout.size:
            return picture
        frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(picture), format=pix_fmt)
        return frame.reformat(width=self.size[0], height=self.size[1], interpolation="AREA").to_ndarray()

    def _convert_frame(self, picture: av.VideoFrame, index: int) -> np.ndarray:
        return _held(self._resized(_frame_rgb(picture, self.layout, f"reference frame {index}"), "rgb24"))

    def _convert_mask(self, picture: av.VideoFrame, index: int) -> np.ndarray:
        return _held(self._resized(_mask_levels(picture, self.layout, f"reference mask {index}"), "gray"))

    def frame(self, index: int) -> np.ndarray:
        """Original frame I_ori `index`: uint8 [H, W, 3] RGB at the output size (read-only: held for the next call)."""
        return self._frames[self._index(index)]

    def mask(self, index: int) -> np.ndarray:
        """Facial mask M `index`: float32 [H, W] in [0, 1] at the output size."""
        return self._masks[self._index(index)].astype(np.float32) / np.float32(MASK_LEVELS)


__all__ = ["CROP_MARGIN_PX", "CROP_MULTIPLE", "FRAME_CODECS", "H264_COLOUR_TAGS", "H264_CRF", "MASK_CODECS",
           "MASK_PNG_FILTER", "MAX_CLIP_FRAMES", "MAX_H264_CRF", "MIN_FACE_PIXELS", "ClipCoding", "ClipLayout",
           "EncodedClip", "ReferenceClip", "ReferenceClipError", "check_mask", "decode_frame", "decode_mask",
           "decode_mask_levels", "decode_picture", "encode_frame", "encode_mask", "encode_picture", "frame_entry",
           "mask_entry", "quantise_mask", "reencode_frame"]
