"""A reference clip coded in groups of pictures and with H.264 masks (sdk/clip_codec.py, sdk/reference_clip.py;
docs/compositing.md, "The reference clip"): the knob's grammar, the stored pattern of keyframes, random access in
any order, exact mask luma, and what a damaged or inconsistent clip is told."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from gaussiantalker.exporter.export.presets import parse_reference
from gaussiantalker.sdk.camera import Camera
from gaussiantalker.sdk.drive import track_row
from gaussiantalker.sdk.errors import BundleError
from gaussiantalker.sdk.image import psnr_db
from gaussiantalker.sdk.reference_clip import (
    ClipCoding,
    ClipLayout,
    EncodedClip,
    ReferenceClip,
    ReferenceClipError,
    decode_frame,
    frame_entry,
    mask_entry,
)

FRAMES = 11
SIZE = (48, 32)  # width, height


def _clip() -> tuple[EncodedClip, list[np.ndarray], list[np.ndarray]]:
    """FRAMES frames of a textured picture sliding one pixel a frame (so P-pictures predict it) and a mask that
    grows; encoded as a checkpoint stores them (intra H.264, PNG masks)."""
    width, height = SIZE
    rng = np.random.default_rng(7)
    coarse = rng.random((height // 4, (width + FRAMES) // 4 + 1, 3)) * 120 + 60  # smooth: 4x4 blocks, then a ramp
    texture = (np.kron(coarse, np.ones((4, 4, 1)))[:, :width + FRAMES] + np.arange(width + FRAMES)[None, :, None]
               ).astype(np.uint8)
    frames = [np.ascontiguousarray(texture[:, k:k + width]) for k in range(FRAMES)]
    yy, xx = np.mgrid[0:height, 0:width]
    masks = [np.clip(1.5 - np.hypot(xx - 24, yy - 16) / (6 + k / 2), 0, 1).astype(np.float32) for k in range(FRAMES)]
    return EncodedClip.from_arrays(frames, masks, Camera(width, height, 40.0, 40.0, 24.0, 16.0)), frames, masks


def _bundle(clip: EncodedClip) -> SimpleNamespace:
    """What ReferenceClip reads of a bundle: the manifest's layout and one entry per frame and mask."""
    entries = {frame_entry(i): f for i, f in enumerate(clip.frames)} | {mask_entry(i): m for i, m in
                                                                         enumerate(clip.masks)}
    return SimpleNamespace(path="test.gtb", manifest={"reference": clip.layout.to_dict()},
                           has_buffer=lambda name: name in entries,
                           buffer=lambda name: np.frombuffer(entries[name], np.uint8))


def test_the_reference_knob_grammar():
    assert parse_reference("keep") is None
    assert parse_reference("crf:28") == ClipCoding(28)
    assert parse_reference("crf:20,gop:25,mask-crf:24") == ClipCoding(20, 25, 24)
    assert parse_reference("gop:5, crf:30") == ClipCoding(30, 5)
    for bad, message in [("gop:25", "names no crf"), ("crf:20,crf:21", "unknown reference clip setting"),
                         ("crf:20,gop:0", "pictures per group must be an integer"), ("crf:20,fps:1", "unknown"),
                         ("crf:52", "CRF must be an integer 0..51"), ("crf:-1", "unknown"), ("crf:1.5", "unknown"),
                         ("", "unknown")]:
        with pytest.raises(BundleError, match=message):
            parse_reference(bad)


def test_groups_put_a_keyframe_every_gop_pictures_and_shrink_the_clip():
    """Entry k * gop is a keyframe that decodes alone (its parameter sets in it); the others are predicted and do
    not decode alone. On a sliding texture the groups are much smaller than intra pictures at the same CRF."""
    clip, frames, _ = _clip()
    intra, grouped = clip.reencoded(ClipCoding(23)), clip.reencoded(ClipCoding(23, gop=4))
    assert grouped.layout.gop == 4 and grouped.layout.to_dict()["gop"] == 4 and "gop" not in intra.layout.to_dict()
    # Measured: 0.16 of the intra bytes; 0.5 leaves room for another x264 build and still needs real prediction.
    assert grouped.frame_bytes < 0.5 * intra.frame_bytes
    for index, data in enumerate(grouped.frames):
        if index % 4 == 0:
            assert psnr_db(frames[index], decode_frame(data, grouped.layout, "f")) > 30.0
        else:
            with pytest.raises(ReferenceClipError, match=f"frame {index} is not decodable"):
                decode_frame(data, grouped.layout, f"frame {index}")
    grouped.check(FRAMES)
    assert ClipLayout.from_dict(grouped.layout.to_dict()).to_dict() == grouped.layout.to_dict()


def test_random_access_in_any_order_gives_the_same_pictures():
    """Forwards, backwards (as the clip plays forth and back), jumping between groups and repeating an index: each
    frame and mask is the one sequential decoding gives, and a picture handed out cannot be changed."""
    clip, _, _ = _clip()
    grouped = clip.reencoded(ClipCoding(23, gop=4, mask_crf=0))
    truth = [picture.to_ndarray(format="rgb24") for picture in grouped.frame_pictures()]
    stored_levels = list(clip.mask_levels())  # the PNG masks' levels
    reference = ReferenceClip(_bundle(grouped))
    order = [track_row(FRAMES, i) for i in range(3 * FRAMES)] + [9, 2, 10, 3, 3, 0, 7]
    for index in order:
        np.testing.assert_array_equal(reference.frame(index), truth[index])
        # x264 at CRF 0 is lossless: the mask's levels come back exactly from the luma plane.
        np.testing.assert_array_equal(reference.mask(index), stored_levels[index] / np.float32(255))
    with pytest.raises(ValueError, match="read-only"):
        reference.frame(3)[0, 0, 0] = 1
    with pytest.raises(IndexError, match="outside 0..10"):
        reference.frame(FRAMES)


def test_h264_masks_are_small_and_close():
    """Masks as H.264 luma at CRF 18 in groups: a fraction of the PNG bytes and close to the stored levels. Measured
    on this clip: 0.24 of the PNG bytes; the worst frame's mean error 1.7 levels, the largest 16 (on the soft edge).
    The bounds leave room for another x264 build; a shifted or scaled luma (tens of levels everywhere) fails."""
    clip, _, _ = _clip()
    coded = clip.reencoded(ClipCoding(23, gop=FRAMES, mask_crf=18))
    assert coded.layout.mask_codec == "h264"
    assert sum(map(len, coded.masks)) < 0.5 * sum(map(len, clip.masks))
    errors = [np.abs(levels.astype(int) - stored) for levels, stored in zip(coded.mask_levels(), clip.mask_levels(),
                                                                           strict=True)]
    assert max(float(e.mean()) for e in errors) < 4.0 and max(int(e.max()) for e in errors) <= 64
    coded.check(FRAMES)


def test_inconsistent_or_damaged_groups_are_refused():
    clip, _, _ = _clip()
    grouped = clip.reencoded(ClipCoding(23, gop=4, mask_crf=10))
    with pytest.raises(ReferenceClipError, match="cannot be kept in a clip re-grouped by 2"):
        grouped.reencoded(ClipCoding(30, gop=2))
    for bad in (0, "4", True, 100_001):
        with pytest.raises(ReferenceClipError, match="'gop' must be an integer"):
            ClipLayout.from_dict(grouped.layout.to_dict() | {"gop": bad})
    # A group whose keyframe is missing (a predicted picture where the keyframe should be) is refused at load.
    broken = EncodedClip(grouped.layout, [grouped.frames[1], *grouped.frames[1:]], grouped.masks)
    with pytest.raises(BundleError, match="reference frame 0 is not decodable"):
        ReferenceClip(_bundle(broken))
    with pytest.raises(ReferenceClipError, match="reference frame 0 is not decodable"):
        broken.check(FRAMES)
    # An empty entry in the middle of a group is named when its group is reached.
    holed = EncodedClip(grouped.layout, [*grouped.frames[:5], b"", *grouped.frames[6:]], grouped.masks)
    reference = ReferenceClip(_bundle(holed))
    reference.frame(3)
    with pytest.raises(ReferenceClipError, match="reference frame 5 is empty"):
        reference.frame(6)
    np.testing.assert_array_equal(reference.frame(2), ReferenceClip(_bundle(grouped)).frame(2))


def test_fuzzed_entries_give_pictures_or_a_clip_error():
    """Hostile entries (the checksums aside: a bundle writer can sign anything): bytes flipped, entries cut short,
    swapped or emptied, in a clip of groups with H.264 masks. Every frame and mask asked for, forth and back, is a
    picture of the clip's shape or a ReferenceClipError (BundleError at load) naming an entry; nothing else
    escapes, and no mask leaves [0, 1]."""
    clip, _, _ = _clip()
    grouped = clip.reencoded(ClipCoding(23, gop=4, mask_crf=10))
    rng = np.random.default_rng(2)
    width, height = SIZE
    for _trial in range(60):
        frames, masks = list(grouped.frames), list(grouped.masks)
        for _edit in range(int(rng.integers(1, 4))):
            entries = frames if rng.random() < 0.5 else masks
            index = int(rng.integers(len(entries)))
            data = bytearray(entries[index])
            kind = rng.integers(4)
            if kind == 0 and data:
                for at in rng.integers(0, len(data), int(rng.integers(1, 8))):
                    data[at] ^= int(rng.integers(1, 256))
            elif kind == 1:
                data = data[:int(rng.integers(0, len(data) + 1))]
            elif kind == 2:
                data = bytearray(entries[int(rng.integers(len(entries)))])
            else:
                data = bytearray(rng.integers(0, 256, int(rng.integers(0, 64)), dtype=np.uint8).tobytes())
            entries[index] = bytes(data)
        try:
            reference = ReferenceClip(_bundle(EncodedClip(grouped.layout, frames, masks)))
        except BundleError as exc:
            assert "reference" in str(exc)
            continue
        for index in [track_row(FRAMES, i) for i in range(2 * FRAMES)]:
            try:
                assert reference.frame(index).shape == (height, width, 3)
                mask = reference.mask(index)
                assert mask.shape == (height, width) and mask.min() >= 0 and mask.max() <= 1
            except ReferenceClipError as exc:
                assert "reference" in str(exc)


def test_a_picture_of_another_size_fails_its_group_every_time_it_is_asked_for():
    """A keyframe of another clip's size inside a group decodes, but is refused when converted; the group is then
    decoded afresh on the next request, so later frames never come out one place off."""
    clip, _, _ = _clip()
    grouped = clip.reencoded(ClipCoding(23, gop=4))
    other = EncodedClip.from_arrays([np.zeros((16, 32, 3), np.uint8)], [np.ones((16, 32), np.float32)],
                                    Camera(32, 16, 20.0, 20.0, 16.0, 8.0)).reencoded(ClipCoding(23))
    frames = [*grouped.frames[:2], other.frames[0], *grouped.frames[3:]]
    reference = ReferenceClip(_bundle(EncodedClip(grouped.layout, frames, grouped.masks)))
    for _attempt in range(2):
        with pytest.raises(ReferenceClipError, match="reference frame 2 is 32x16, the clip is 48x32"):
            reference.frame(3)
    truth = ReferenceClip(_bundle(grouped))
    np.testing.assert_array_equal(reference.frame(1), truth.frame(1))
    np.testing.assert_array_equal(reference.frame(5), truth.frame(5))
