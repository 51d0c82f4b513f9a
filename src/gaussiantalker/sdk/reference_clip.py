"""A speaker's reference clip: its original video frames I_ori, facial masks M and the camera that aligns them.

The composited frame is I = (1 - M) I_ori + M F(I_gau + (1 - M) I_ori) (docs/compositing.md). A clip is stored
encoded, one entry per frame and per mask (intra-only H.264 frames, 8-bit PNG masks; the choice is measured in
docs/compositing.md), so a player decodes any frame alone, one at a time, and never holds the decoded clip. Frame i is
aligned with row i of the speaker's pose track; the clip is played forth and back like the track
(`drive.track_row`).

Encoding and decoding go through PyAV (libavcodec), which the runtime already needs for video out.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from fractions import Fraction

import av
import numpy as np

from .camera import Camera
from .errors import BundleError, CameraError, GaussianTalkerError

# Stored codec name -> (libavcodec encoder, decoder). Frames: intra-only H.264, every frame its own keyframe so it
# decodes alone (fewer bytes than JPEG at the same PSNR on the demo clip: docs/compositing.md); masks: 8-bit grey
# PNG (lossless).
FRAME_CODECS = {"h264": ("libx264", "h264")}
MASK_CODECS = {"png": ("png", "png")}
# The PNG row filter of stored masks: "up" (each row minus the one above). On the demo clip's masks it decodes 3.2x
# faster than the Paeth filter libavcodec's encoder chose by default (0.42 against 1.35 ms at 480x600, once per
# composited frame) and the files are 4% smaller; "none" is smaller still but decodes a little slower
# (docs/compositing.md, "The reference clip"). Any filter decodes: bundles with Paeth masks play as before.
MASK_PNG_FILTER = "up"
# x264 constant-rate factor of stored frames: 18 keeps the demo clip visually lossless (its PSNR:
# docs/compositing.md, "The reference clip"). An export may re-encode a clip at a larger CRF (`reencode_frame`;
# the `reference` export knob, docs/precision.md).
H264_CRF = 18
# x264's CRF range for 8-bit pictures: 0 (lossless) .. 51 (coarsest).
MAX_H264_CRF = 51
# The colour description written into each frame's H.264 stream (its VUI): what swscale's RGB -> yuv420p conversion
# does (the BT.601 matrix, limited range) on sRGB pictures, so a native decoder that honours the tags converts back
# exactly as the runtime does, and one that guesses from the size (BT.709 for HD) is told otherwise.
H264_COLOUR_TAGS = "colorprim=bt709:transfer=iec61966-2-1:colormatrix=bt470bg:range=tv"
MAX_CLIP_FRAMES = 100_000
# A mask must have at least this many pixels at M >= 0.5: a clip "with no face in the mask" is refused.
MIN_FACE_PIXELS = 16
# The crop the inpainting generator F sees (the bundle records both; docs/compositing.md): pixels of context around
# the mask's support on every side (its receptive field at half resolution), and the multiple every crop side is
# padded to (the generator pools by 2 and has up to 3 stride-2 levels).
CROP_MARGIN_PX = 16
CROP_MULTIPLE = 16
_MASK_LEVELS = 255.0


class ReferenceClipError(GaussianTalkerError, ValueError):
    """A reference clip is unusable: counts or sizes disagree, a mask is out of range or empty, a frame is not
    decodable. Callers add where the clip came from (a checkpoint or a bundle)."""


def frame_entry(index: int) -> str:
    """Bundle entry holding encoded frame `index`."""
    return f"reference/frame/{index:05d}"


def mask_entry(index: int) -> str:
    """Bundle entry holding encoded mask `index`."""
    return f"reference/mask/{index:05d}"


@dataclass(frozen=True)
class ClipLayout:
    """What the manifest (and checkpoint) records about a clip: frame count, codecs and the aligning camera
    (its width and height are the clip's frame size)."""

    count: int
    camera: Camera
    frame_codec: str = "h264"
    mask_codec: str = "png"

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

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) of every frame and mask."""
        return self.camera.width, self.camera.height

    def to_dict(self) -> dict:
        return {"count": self.count, "camera": self.camera.to_dict(), "frame_codec": self.frame_codec,
                "mask_codec": self.mask_codec}

    @classmethod
    def from_dict(cls, data) -> ClipLayout:
        """Inverse of to_dict; ReferenceClipError naming the bad field."""
        if not isinstance(data, dict):
            raise ReferenceClipError(f"reference clip description must be a table, got {type(data).__name__}")
        unknown = sorted(set(data) - {"count", "camera", "frame_codec", "mask_codec"})
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
                   data.get("mask_codec", "png"))


def _encode(encoder: str, frame: av.VideoFrame, pix_fmt: str, options: dict[str, str]) -> bytes:
    """One picture -> one self-contained packet (a fresh encoder each time: no state shared between frames)."""
    try:
        context = av.CodecContext.create(encoder, "w")
    except av.error.FFmpegError as exc:
        raise ReferenceClipError(f"this PyAV build cannot encode with {encoder}: {exc}") from None
    context.width, context.height, context.pix_fmt = frame.width, frame.height, pix_fmt
    context.time_base = Fraction(1, 25)
    context.gop_size = 1
    context.options = options
    picture = frame.reformat(format=pix_fmt)
    picture.pts = 0
    packets = context.encode(picture) + context.encode(None)
    return b"".join(bytes(packet) for packet in packets)


def _check_crf(crf: int) -> int:
    if isinstance(crf, bool) or not isinstance(crf, int | np.integer) or not 0 <= crf <= MAX_H264_CRF:
        raise ReferenceClipError(f"an H.264 CRF must be an integer 0..{MAX_H264_CRF}, got {crf!r}")
    return int(crf)


def _encode_h264(picture: av.VideoFrame, codec: str, crf: int) -> bytes:
    return _encode(FRAME_CODECS[codec][0], picture, "yuv420p",
                   {"crf": str(_check_crf(crf)), "bf": "0", "x264-params": H264_COLOUR_TAGS})


def encode_frame(rgb: np.ndarray, codec: str = "h264", crf: int = H264_CRF) -> bytes:
    """uint8 [H, W, 3] RGB (even sides) -> one intra-coded H.264 frame (4:2:0, CRF `crf`, colour tags
    H264_COLOUR_TAGS)."""
    rgb = np.ascontiguousarray(rgb)
    if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ReferenceClipError(f"a reference frame must be uint8 [H, W, 3], got {rgb.dtype} {list(rgb.shape)}")
    return _encode_h264(av.VideoFrame.from_ndarray(rgb, format="rgb24"), codec, crf)


def quantise_mask(mask: np.ndarray) -> np.ndarray:
    """float [H, W] in [0, 1] -> the uint8 levels a mask is stored as (round(M * 255))."""
    return np.floor(np.asarray(mask, dtype=np.float32) * np.float32(_MASK_LEVELS) + np.float32(0.5)).astype(np.uint8)


def encode_mask(mask: np.ndarray, codec: str = "png") -> bytes:
    """float [H, W] in [0, 1] (checked by `check_mask`) -> 8-bit grey PNG of round(M * 255)."""
    frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(quantise_mask(mask)), format="gray")
    return _encode(MASK_CODECS[codec][0], frame, "gray", {"pred": MASK_PNG_FILTER})


def _decode(codec: str, data: bytes, label: str) -> av.VideoFrame:
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


def _check_size(label: str, picture: av.VideoFrame, size: tuple[int, int]) -> None:
    if (picture.width, picture.height) != size:
        raise ReferenceClipError(f"{label} is {picture.width}x{picture.height}, the clip is {size[0]}x{size[1]}")


def decode_frame(data: bytes, layout: ClipLayout, label: str) -> np.ndarray:
    """One encoded frame -> uint8 [H, W, 3] RGB, checked against the clip's size."""
    picture = _decode(FRAME_CODECS[layout.frame_codec][1], data, label)
    _check_size(label, picture, layout.size)
    return picture.to_ndarray(format="rgb24")


def reencode_frame(data: bytes, layout: ClipLayout, label: str, crf: int) -> bytes:
    """One stored frame re-encoded at CRF `crf` (intra-only, the same colour tags). The decoded 4:2:0 picture goes
    to the encoder as it is, so the only loss added is the new encode's (no RGB round trip)."""
    picture = _decode(FRAME_CODECS[layout.frame_codec][1], data, label)
    _check_size(label, picture, layout.size)
    if picture.format.name != "yuv420p":
        raise ReferenceClipError(f"{label} must be 4:2:0 (yuv420p), got pixel format {picture.format.name}")
    return _encode_h264(picture, layout.frame_codec, crf)


def decode_mask_levels(data: bytes, layout: ClipLayout, label: str) -> np.ndarray:
    """One encoded mask -> its uint8 levels [H, W] (M * 255); a colour or 16-bit PNG is refused."""
    picture = _decode(MASK_CODECS[layout.mask_codec][1], data, label)
    _check_size(label, picture, layout.size)
    if picture.format.name != "gray":
        raise ReferenceClipError(f"{label} must be an 8-bit grey image, got pixel format {picture.format.name}")
    return picture.to_ndarray()


def decode_mask(data: bytes, layout: ClipLayout, label: str) -> np.ndarray:
    """One encoded mask -> float32 [H, W] in [0, 1] (its 8-bit levels / 255)."""
    return decode_mask_levels(data, layout, label).astype(np.float32) / np.float32(_MASK_LEVELS)


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
        for index in range(self.layout.count):
            decode_frame(self.frames[index], self.layout, f"reference frame {index}")
            mask = decode_mask(self.masks[index], self.layout, f"reference mask {index}")
            check_mask(mask, self.layout.size, f"reference mask {index}")

    def reencoded(self, crf: int) -> EncodedClip:
        """This clip with every frame re-encoded at CRF `crf` (`reencode_frame`); the masks (lossless) and the
        layout are kept as they are."""
        _check_crf(crf)
        frames = [reencode_frame(data, self.layout, f"reference frame {index}", crf)
                  for index, data in enumerate(self.frames)]
        return EncodedClip(self.layout, frames, list(self.masks))

    @property
    def frame_bytes(self) -> int:
        """Encoded size of every frame."""
        return sum(len(b) for b in self.frames)

    @property
    def nbytes(self) -> int:
        """Encoded size of every frame and mask."""
        return sum(len(b) for b in self.frames) + sum(len(b) for b in self.masks)


class ReferenceClip:
    """A bundle's reference clip, decoded one frame at a time (optionally resized to an output size).

    Opening it reads every entry once to check its checksum and decodes the first frame and mask, so a damaged
    clip is refused at load, never mid-video; after that only the entry a frame needs is read.
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

    def frame(self, index: int) -> np.ndarray:
        """Original frame I_ori `index`: uint8 [H, W, 3] RGB at the output size."""
        index = self._index(index)
        data = self.bundle.buffer(frame_entry(index)).tobytes()
        return self._resized(decode_frame(data, self.layout, f"reference frame {index}"), "rgb24")

    def mask(self, index: int) -> np.ndarray:
        """Facial mask M `index`: float32 [H, W] in [0, 1] at the output size."""
        index = self._index(index)
        data = self.bundle.buffer(mask_entry(index)).tobytes()
        levels = decode_mask_levels(data, self.layout, f"reference mask {index}")
        return self._resized(levels, "gray").astype(np.float32) / np.float32(_MASK_LEVELS)

