"""Compositing into the reference clip (docs/compositing.md): the clip's storage and its bad input, the crop F
runs on, the composite formula (outside M the reference frame bit for bit), the premultiplied and semantic
outputs, and TalkingHead's composited frames, on the small speaker with a small procedural clip."""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest
import torch
from clip_speaker import CLIP_FRAMES, CLIP_SIZE

from gaussiantalker.runtime.composite import CROP_MARGIN_PX, CROP_MULTIPLE, composite, crop_box, opencv_fallback
from gaussiantalker.sdk.camera import Camera
from gaussiantalker.sdk.drive import FrameDrive, track_row
from gaussiantalker.sdk.errors import BundleError, CheckpointError, RenderError
from gaussiantalker.sdk.image import psnr_db, seam_step, to_uint8
from gaussiantalker.sdk.reference_clip import (
    ClipLayout,
    EncodedClip,
    ReferenceClipError,
    decode_frame,
    decode_mask,
    frame_entry,
)


def _identity(x, mask, render):
    return x


# -- the clip's storage ------------------------------------------------------------------------------------------

def test_clip_entries_round_trip_and_play_forth_and_back():
    camera = Camera(32, 24, 30.0, 30.0, 16.0, 12.0)
    ramp = np.linspace(0, 120, 32)[None, :, None] + np.linspace(0, 60, 24)[:, None, None] + [0, 30, 60]
    frames = [np.clip(ramp + 20 * k, 0, 255).astype(np.uint8) for k in range(3)]
    masks = [np.pad(np.full((8, 8), 0.5 + 0.25 * k, np.float32), ((8, 8), (12, 12))) for k in range(3)]
    clip = EncodedClip.from_arrays(frames, masks, camera)
    clip.check(3)
    for k in range(3):
        # H.264 at CRF 18 (4:2:0) on smooth frames: PSNR well above the demo clip's measured ~39 dB.
        decoded = decode_frame(clip.frames[k], clip.layout, "f")
        assert psnr_db(frames[k], decoded) > 40.0
        # Masks are stored as their 8-bit levels, losslessly: exactly round(M * 255) / 255.
        np.testing.assert_array_equal(decode_mask(clip.masks[k], clip.layout, "m"),
                                      np.round(masks[k] * 255).astype(np.float32) / 255)
    assert [track_row(3, i) for i in range(8)] == [0, 1, 2, 1, 0, 1, 2, 1]
    assert ClipLayout.from_dict(clip.layout.to_dict()).to_dict() == clip.layout.to_dict()


def test_masks_are_stored_with_the_up_filter_and_decode_losslessly():
    """Every row of a stored mask PNG below the first uses the "up" filter (MASK_PNG_FILTER: the fastest to decode;
    the first row has no row above it), and the levels come back exactly."""
    from png_rows import png_rows

    from gaussiantalker.sdk.reference_clip import encode_mask

    rng = np.random.default_rng(3)
    mask = np.clip(np.pad(np.ones((20, 30), np.float32), 10) * 1.2 - rng.random((40, 50), np.float32) * 0.4, 0, 1)
    data = encode_mask(mask)
    width, height, rows = png_rows(data)
    assert (width, height, rows.shape[1]) == (50, 40, 51) and np.all(rows[1:, 0] == 2)  # filter type 2: "up"
    layout = ClipLayout(1, Camera(50, 40, 30.0, 30.0, 25.0, 20.0))
    np.testing.assert_array_equal(decode_mask(data, layout, "m"), np.floor(mask * 255 + 0.5) / np.float32(255))


def test_frames_carry_the_colour_tags_of_their_conversion():
    """Each stored frame's stream says how its RGB became YUV (BT.601 matrix, limited range; sRGB), and the tags
    change nothing for the runtime: the same picture encoded without them decodes to the same pixels."""
    import av

    from gaussiantalker.sdk.reference_clip import H264_CRF, decode_picture, encode_frame, encode_picture

    ramp = np.linspace(0, 200, 64)[None, :, None] + np.linspace(0, 50, 48)[:, None, None] + [0, 20, 40]
    rgb = np.clip(ramp, 0, 255).astype(np.uint8)
    tagged = decode_picture("h264", encode_frame(rgb), "tagged")
    assert (tagged.colorspace, tagged.color_range) == (av.video.reformatter.Colorspace.ITU601,
                                                      av.video.reformatter.ColorRange.MPEG)
    assert (tagged.color_primaries, tagged.color_trc) == (1, 13)  # BT.709 primaries, IEC 61966-2-1 (sRGB)
    picture = av.VideoFrame.from_ndarray(rgb, format="rgb24")
    untagged = decode_picture("h264", encode_picture("libx264", picture, "yuv420p",
                                                     {"crf": str(H264_CRF), "bf": "0"}), "untagged")
    assert untagged.colorspace != tagged.colorspace  # what older bundles hold: unspecified
    np.testing.assert_array_equal(tagged.to_ndarray(format="rgb24"), untagged.to_ndarray(format="rgb24"))


@pytest.mark.parametrize("change, message", [
    (lambda f, m: (f, m[:2]), "zip"),
    (lambda f, m: (f, [m[0][:-1]] + m[1:]), "reference mask 0 has shape"),
    (lambda f, m: (f, [m[0] * 2.0] + m[1:]), r"must lie in \[0, 1\]"),
    (lambda f, m: (f, [np.where(m[0] > 0, np.nan, 0.0).astype(np.float32)] + m[1:]), r"must lie in \[0, 1\]"),
    (lambda f, m: (f, [np.zeros_like(m[0])] + m[1:]), "has no face in it"),
    (lambda f, m: (f, [m[0].astype(np.uint8)] + m[1:]), "must hold floats"),
    (lambda f, m: ([f[0][:, :-1]] + f[1:], m), "reference frame 0 must be uint8"),
])
def test_bad_clip_arrays_are_refused_naming_the_problem(change, message):
    camera = Camera(32, 24, 30.0, 30.0, 16.0, 12.0)
    frames = [np.zeros((24, 32, 3), np.uint8)] * 3
    masks = [np.pad(np.ones((8, 8), np.float32), ((8, 8), (12, 12)))] * 3
    frames, masks = change(list(frames), list(masks))
    with pytest.raises((ReferenceClipError, ValueError), match=message if message != "zip" else None):
        EncodedClip.from_arrays(frames, masks, camera)


def test_layout_refuses_odd_sides_and_unknown_fields():
    with pytest.raises(ReferenceClipError, match="even sides"):
        ClipLayout(2, Camera(33, 24, 30.0, 30.0, 16.0, 12.0))
    with pytest.raises(ReferenceClipError, match="even sides"):  # before the encoder sees an odd frame
        EncodedClip.from_arrays([np.zeros((24, 33, 3), np.uint8)], [np.ones((24, 33), np.float32)],
                                Camera(33, 24, 30.0, 30.0, 16.0, 12.0))
    data = ClipLayout(2, Camera(32, 24, 30.0, 30.0, 16.0, 12.0)).to_dict()
    with pytest.raises(ReferenceClipError, match="unknown field"):
        ClipLayout.from_dict({**data, "fps": 25})
    with pytest.raises(ReferenceClipError, match="'count'"):
        ClipLayout.from_dict({**data, "count": 0})
    with pytest.raises(ReferenceClipError, match="'frame_codec'"):
        ClipLayout.from_dict({**data, "frame_codec": "gif"})


def test_checkpoint_clip_that_disagrees_with_the_pose_track_is_refused(clip_export, tmp_path):
    from gaussiantalker.exporter.export.checkpoint import load_checkpoint

    loaded = load_checkpoint(clip_export.checkpoint)
    assert loaded.reference.layout.to_dict() == clip_export.speaker.reference.layout.to_dict()
    assert loaded.reference.frames == clip_export.speaker.reference.frames
    payload = torch.load(clip_export.checkpoint, weights_only=True)
    for edit, message in (
        (lambda p: p["reference"]["masks"].pop(), "3 masks"),
        (lambda p: p.__setitem__("pose_track", p["pose_track"][:3]), "pose track has 3 rows"),
        (lambda p: p["reference"]["frames"].__setitem__(1, torch.zeros(40, dtype=torch.uint8)), "frame 1 is not"),
        (lambda p: p["reference"].__setitem__("frames", "not a list"), "list of 1-D uint8 tensors"),
    ):
        broken = copy.deepcopy(payload)
        edit(broken)
        torch.save(broken, tmp_path / "broken.ckpt")
        with pytest.raises(CheckpointError, match=message):
            load_checkpoint(tmp_path / "broken.ckpt")


def test_damaged_clip_entry_fails_at_load_not_mid_video(clip_export, tmp_path):
    from gaussiantalker.runtime import TalkingHead
    from gaussiantalker.sdk.bundle import Bundle

    bundle = Bundle(clip_export.path)
    entry = bundle.manifest["buffers"][frame_entry(2)]
    data = bytearray(clip_export.path.read_bytes())
    data[bundle.payload_start + entry["offset"] + entry["nbytes"] // 2] ^= 0xFF
    damaged = tmp_path / "damaged.gtb"
    damaged.write_bytes(bytes(data))
    with pytest.raises(BundleError, match=r"checksum mismatch in buffer 'reference/frame/00002'"):
        TalkingHead(damaged)


# -- the crop and the formula ------------------------------------------------------------------------------------

@pytest.mark.parametrize("shape, box", [((200, 150), (40, 60, 90, 100)), ((20, 30), (5, 8, 12, 20)),
                                        ((200, 150), (0, 0, 200, 150)), ((64, 64), (60, 60, 64, 64))])
def test_crop_box_holds_the_mask_and_margin_in_multiples(shape, box):
    mask = np.zeros(shape, np.float32)
    top, left, bottom, right = box
    mask[top:bottom, left:right] = 0.3
    crop = crop_box(mask)
    assert (crop.height + crop.pad_bottom) % CROP_MULTIPLE == 0
    assert (crop.width + crop.pad_right) % CROP_MULTIPLE == 0
    assert 0 <= crop.top and crop.top + crop.height <= shape[0] and 0 <= crop.left
    assert crop.left + crop.width <= shape[1]
    assert crop.top <= max(top - CROP_MARGIN_PX, 0) and crop.top + crop.height >= min(bottom + CROP_MARGIN_PX, shape[0])
    assert crop.left <= max(left - CROP_MARGIN_PX, 0)
    assert crop.left + crop.width >= min(right + CROP_MARGIN_PX, shape[1])
    assert crop_box(np.zeros(shape, np.float32)) is None


def test_composite_applies_the_formula_and_keeps_the_reference_outside_the_mask():
    rng = np.random.default_rng(1)
    height, width = 70, 90
    reference = rng.integers(0, 256, (height, width, 3), dtype=np.uint8)
    head = np.zeros((height, width, 4), np.float32)
    head[20:50, 30:60] = rng.uniform(0.0, 1.0, (30, 30, 4)).astype(np.float32)
    head[..., :3] *= head[..., 3:]  # premultiplied
    mask = np.zeros((height, width), np.float32)
    mask[18:52, 28:62] = rng.uniform(0.0, 1.0, (34, 34)).astype(np.float32)
    mask[25:45, 35:55] = 1.0
    out = composite(head, reference, mask, _identity)
    outside = mask == 0.0
    np.testing.assert_array_equal(out[outside], reference[outside])  # bit for bit
    original = reference.astype(np.float32) / 255
    x = head[..., :3] + (1 - mask[..., None]) * original
    expected = to_uint8((1 - mask[..., None]) * original + mask[..., None] * x)
    np.testing.assert_array_equal(out[~outside], expected[~outside])


class _ScaledInpainter:
    """A stand-in F that reads the image and the coverage, in both layouts an inpainter may offer."""

    def chw(self, image, mask, coverage):
        return image[0] * np.float32(0.7) + coverage[0] * np.float32(0.2)

    def __call__(self, x, mask, render):
        return x * np.float32(0.7) + render[..., 3:4] * np.float32(0.2)


@pytest.mark.parametrize("passes", ["numba", "numpy"])  # with the cpu extra, and without numba
@pytest.mark.parametrize("shape", [(20, 30), (200, 150)])  # a frame shorter than the crop multiple: edge padding
def test_composite_passes_match_the_formula_in_numpy_in_both_layouts(shape, passes, monkeypatch):
    """The passes around F (numba's kernels, and the numpy functions an install without numba runs) give the
    formula's float32 steps bit for bit, with the crop padded by edge pixels where the frame is short, whether F
    takes the graph's channel-first layout (`chw`) or channel-last crops."""
    import gaussiantalker.runtime.composite as composite_module

    if passes == "numpy":
        monkeypatch.setattr(composite_module, "_passes", lambda: (composite_module.crop_inputs,
                                                                  composite_module.blend_crop))
    else:
        from gaussiantalker.runtime import composite_kernels

        assert composite_module._passes() == (composite_kernels.crop_inputs, composite_kernels.blend_crop)
    rng = np.random.default_rng(3)
    height, width = shape
    reference = rng.integers(0, 256, (height, width, 3), dtype=np.uint8)
    head = rng.uniform(0.0, 1.0, (height, width, 4)).astype(np.float32)
    head[..., :3] *= head[..., 3:]
    mask = rng.uniform(0.0, 1.0, shape).astype(np.float32) * (rng.random(shape) < 0.8)
    if shape != (20, 30):  # the large frame's mask leaves room for the crop inside it
        mask[: height // 4] = mask[-height // 4:] = 0.0
        mask[:, : width // 4] = mask[:, -width // 4:] = 0.0
    box = crop_box(mask)
    assert (box.pad_bottom > 0) == (shape == (20, 30))  # the premise: only the small frame pads

    def padded(array):
        return np.pad(array, [(0, box.pad_bottom), (0, box.pad_right)] + [(0, 0)] * (array.ndim - 2), mode="edge")

    m = padded(mask[box.rows, box.columns])
    original = padded(reference[box.rows, box.columns]).astype(np.float32) * np.float32(1 / 255)
    original *= 1.0 - m[..., None]
    render = padded(head[box.rows, box.columns])
    filled = _ScaledInpainter()(render[..., :3] + original, m, render)
    blended = to_uint8(filled * m[..., None] + original)[: box.height, : box.width]
    expected = reference.copy()
    inside = mask[box.rows, box.columns] > 0
    expected[box.rows, box.columns][inside] = blended[inside]
    channel_first = composite(head, reference, mask, _ScaledInpainter())
    channel_last = composite(head, reference, mask, lambda x, mk, r: _ScaledInpainter()(x, mk, r))
    np.testing.assert_array_equal(channel_first, expected)
    np.testing.assert_array_equal(channel_last, expected)


def test_an_inpainter_of_the_wrong_size_is_named():
    mask = np.zeros((40, 40), np.float32)
    mask[10:20, 10:20] = 1.0
    head, reference = np.zeros((40, 40, 4), np.float32), np.zeros((40, 40, 3), np.uint8)
    with pytest.raises(RenderError, match=r"the inpainter returned shape \[\d+, \d+, 2\]"):
        composite(head, reference, mask, lambda x, m, r: x[..., :2])


def test_opencv_fallback_fills_the_uncovered_rim_from_its_surroundings():
    height, width = 48, 64
    background = np.zeros((height, width, 3), np.float32) + np.array([0.2, 0.5, 0.8], np.float32)
    reference = to_uint8(background)
    head = np.zeros((height, width, 4), np.float32)
    head[16:32, 20:44] = (0.9, 0.6, 0.5, 1.0)  # a fully covered face
    mask = np.zeros((height, width), np.float32)
    mask[12:36, 16:48] = 1.0  # the mask reaches 4 px past it: a rim the render leaves empty
    plain = to_uint8((1 - mask[..., None]) * background + mask[..., None] * head[..., :3])
    filled = composite(head, reference, mask, opencv_fallback)
    np.testing.assert_array_equal(filled[16:32, 20:44], to_uint8(head[16:32, 20:44, :3]))  # the face is kept
    rim = (mask > 0) & (head[..., 3] == 0)
    # The rim takes the background's colour: within 2 levels (Telea averages in 8 bits, between two roundings).
    assert np.abs(filled[rim].astype(int) - reference[rim]).max() <= 2
    assert seam_step(filled / 255.0, mask) < 0.01 < seam_step(plain / 255.0, mask)


def test_fallback_without_opencv_says_what_to_install(monkeypatch):
    import builtins

    real_import = builtins.__import__

    def no_cv2(name, *args, **kwargs):
        if name == "cv2":
            raise ImportError("no cv2")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_cv2)
    with pytest.raises(RenderError, match=r"gaussiantalker-sdk\[opencv\].*composite=False"):
        opencv_fallback(np.zeros((16, 16, 3), np.float32), np.ones((16, 16), np.float32),
                        np.zeros((16, 16, 4), np.float32))


# -- the runtime -------------------------------------------------------------------------------------------------

def test_head_composites_into_the_clip_following_its_track(clip_export, tmp_path):
    from gaussiantalker.exporter.verify.compositing import composite_reference
    from gaussiantalker.runtime import TalkingHead

    with TalkingHead(clip_export.path) as head:
        assert head.compositor is not None and len(head.reference) == CLIP_FRAMES
        assert (head.camera.width, head.camera.height) == CLIP_SIZE
        audio = np.zeros(head.driver.config.samples_per_frame * 6, np.float32)
        frames = list(head.frames(audio, head.driver.config.sample_rate))
        drives = list(head.drives(audio, head.driver.config.sample_rate))
        assert len(frames) == 6 and frames[0].shape == (CLIP_SIZE[1], CLIP_SIZE[0], 3)
        for index in (0, 5):  # frame 5 shows clip frame 1 (forth and back through 4 frames)
            row = track_row(CLIP_FRAMES, index)
            picture, mask = head.reference.frame(row), head.reference.mask(row)
            outside = mask == 0
            np.testing.assert_array_equal(frames[index][outside], picture[outside])
            bare = head.render(drives[index], output="rgba_float")
            expected = composite_reference(bare, picture, mask, clip_export.speaker.inpaint)
            # The same render through the torch F instead of the inpaint graph: fp32 graph parity, so at most
            # one 8-bit level apart (rounding of values within ~1e-6 of a level boundary).
            assert np.abs(frames[index].astype(int) - expected).max() <= 1
        with pytest.raises(RenderError, match="follows the reference clip's pose track"):
            next(head.frames(audio, head.driver.config.sample_rate, head_pose=np.zeros((1, 6), np.float32)))
        with pytest.raises(RenderError, match="composited frames are uint8"):
            next(head.frames(audio, head.driver.config.sample_rate, output="float"))
        with pytest.raises(RenderError, match="alpha=True needs the bare head"):
            head.write_video(tmp_path / "talk.webm", audio, head.driver.config.sample_rate, alpha=True)
    with TalkingHead(clip_export.path, composite=False) as bare:
        assert bare.compositor is None and bare.camera.width == clip_export.speaker.camera.width
    with TalkingHead(clip_export.path, resolution=(48, 56)) as small:
        assert small.reference.frame(0).shape == (56, 48, 3) and small.reference.mask(0).shape == (56, 48)
        assert next(small.frames(audio, small.sample_rate)).shape == (56, 48, 3)


def test_inpaint_codec_is_a_precision_knob(clip_export, replay_onnx_exports, tmp_path):
    """F's weights take the `inpaint` group's codec (`gt-export --inpaint-codec`) and nothing else changes; the
    composited frames differ from the fp32 F's only inside the mask, by what 8-bit weights change in F's output."""
    from gaussiantalker.exporter.export.bundle_export import export_bundle
    from gaussiantalker.exporter.export.presets import PRESETS, ExportSettings
    from gaussiantalker.runtime import TalkingHead
    from gaussiantalker.sdk.bundle import Bundle

    replay_onnx_exports(clip_export.protos)
    path = tmp_path / "q8.gtb"
    export_bundle(clip_export.speaker, path, settings=ExportSettings(inpaint="q8"), progress=False)
    plain, quantised = Bundle(clip_export.path).manifest["buffers"], Bundle(path).manifest["buffers"]
    assert plain.keys() == quantised.keys()
    for name, entry in quantised.items():
        codec = entry["codec"]["name"]
        if not name.startswith("inpaint/"):
            assert codec == plain[name]["codec"]["name"], name
        else:  # F's larger convolutions 8-bit, those under QUANT_MIN_VALUES values fp16
            assert codec == ("q8" if np.prod(entry["shape"]) >= 4096 else "fp16"), name
    assert sum(e["nbytes"] for n, e in quantised.items() if n.startswith("inpaint/")) < \
        0.35 * sum(e["nbytes"] for n, e in plain.items() if n.startswith("inpaint/"))
    audio = np.random.default_rng(0).normal(0.0, 0.1, 6 * clip_export.speaker.config.samples_per_frame)
    with TalkingHead(clip_export.path) as reference, TalkingHead(path) as head:
        rate = head.driver.config.sample_rate
        inside_psnr = []
        for index, (want, got) in enumerate(zip(reference.frames(audio, rate), head.frames(audio, rate),
                                                 strict=True)):
            inside = head.reference.mask(track_row(CLIP_FRAMES, index)) > 0
            np.testing.assert_array_equal(got[~inside], want[~inside])
            inside_psnr.append(psnr_db(want[inside], got[inside]))
    # Measured 67.3-67.9 dB (1 level at most): the knob reaches the pixels, and only by 8-bit weights' error;
    # 55 dB leaves room for other platforms' rounding.
    assert 55.0 <= min(inside_psnr) < float("inf")
    assert {PRESETS[name].export.inpaint for name in PRESETS} == {"raw", "q8", "q4", "fp16"}


def test_composite_bench_end_to_end(clip_export, replay_onnx_exports, tmp_path):
    """`gt-bench composite` on the small clip speaker: every table is written, the reference codec matches
    itself exactly, a lossy F codec is finite and close, and the seam rows are there (speed is not judged)."""
    from tools.bench.composite_cost import run_composite_bench

    replay_onnx_exports(clip_export.protos * 3)  # the bench's own export, then one per F codec
    out = tmp_path / "composite.md"
    text = run_composite_bench(clip_export.checkpoint, None, seconds=0.4, rounds=1, pairs=2, out=out,
                               codecs=("raw", "q8"), progress=False)
    assert out.read_text() == text
    rows = {line.split("|")[1].strip(): line for line in text.splitlines() if line.startswith("| ")}
    assert {"96x112 composited", "96x112 bare", "512x512 composited", "512x512 bare"} <= rows.keys()
    assert {"F", "fallback", "F q8", "plain paste", "true frame"} <= rows.keys()
    assert "| raw |" in text and " inf dB | inf dB | 0 |" in rows["raw"]
    q8_min = float(rows["q8"].split("|")[3].split()[0])
    assert 55.0 <= q8_min < float("inf")  # as in test_inpaint_codec_is_a_precision_knob


def test_composite_true_without_a_clip_and_a_custom_camera_are_refused(clip_export, small_export):
    from gaussiantalker.runtime import TalkingHead

    with pytest.raises(RenderError, match="needs a bundle with a reference clip"):
        TalkingHead(small_export.path, composite=True)
    with pytest.raises(RenderError, match="reference clip's camera"):
        TalkingHead(clip_export.path, camera=clip_export.speaker.camera)



def test_the_cpu_splatter_composites_like_gl(clip_export):
    """renderer="cpu" (runtime/splat/cpu.py) through the whole compositing path: the clip's frames, F's
    inpainting and the mask blend, against GL's composited frames (both splatters' bare frames agree at >= 60 dB,
    tests/test_cpu_splatter.py; the compositing after them is the same numpy)."""
    from gaussiantalker.exporter.export.speech import synth_speech
    from gaussiantalker.runtime import TalkingHead

    pytest.importorskip("numba", reason="the cpu extra is not installed")
    speech = synth_speech(0.4, seed=3)
    frames = {}
    for renderer in ("gl", "cpu"):
        with TalkingHead(clip_export.path, renderer=renderer) as head:
            assert head.compositor is not None and head.renderer == renderer
            frames[renderer] = list(head.frames(speech, 16000))
    assert len(frames["cpu"]) == len(frames["gl"]) > 0
    for mine, theirs in zip(frames["cpu"], frames["gl"], strict=True):
        assert psnr_db(mine.astype(np.float64) / 255, theirs.astype(np.float64) / 255) >= 60.0


def test_a_composited_head_does_not_play_a_motion(clip_export, tmp_path):
    """A FLAME motion plays on the bare head only: composited frames follow the clip and its audio."""
    from gaussiantalker.runtime import TalkingHead

    n_expr = clip_export.speaker.config.n_expr
    with TalkingHead(clip_export.path) as head:
        with pytest.raises(RenderError, match="play a motion with composite=False"):
            head.write_video(tmp_path / "m.mp4", motion=np.zeros((2, n_expr + 18), np.float32))
    with TalkingHead(clip_export.path, composite=False, resolution=(32, 32)) as head:
        assert len(list(head.frames(motion=np.zeros((2, n_expr + 18), np.float32)))) == 2


def test_output_view_of_a_clip_bundle_is_the_heads(clip_export, tmp_path):
    """What TalkingHead.output_view says from the manifest (camera, compositing) is what the loaded head does, and a
    composited head's frames are the same from the output group as from the shortcut keyword."""
    from gaussiantalker.runtime import OutputSettings, TalkingHead
    from gaussiantalker.sdk.video_formats import plan_video

    assert TalkingHead.output_view(clip_export.path).size == CLIP_SIZE
    audio = np.zeros(640 * 3, np.float32)
    for settings in (OutputSettings(), OutputSettings(resolution=(48, 56)), OutputSettings(composite=False)):
        view = TalkingHead.output_view(clip_export.path, settings)
        with TalkingHead(clip_export.path, output_settings=settings) as head:
            assert (view.composite, view.camera.to_dict()) == (head.compositor is not None, head.camera.to_dict())
            if head.compositor is None:
                continue
            frames = list(head.frames(audio, 16000))
            with pytest.raises(RenderError, match="alpha=True needs the bare head"):
                view.plan_video(tmp_path / "talk.webm", alpha=True)
            with pytest.raises(RenderError, match="alpha=True needs the bare head"):
                head.write_video(plan_video(tmp_path / "talk.webm", head.frame_size, alpha=True), audio, 16000)
        if settings.resolution is not None:
            with TalkingHead(clip_export.path, resolution=settings.resolution) as shortcut:
                for frame, expected in zip(shortcut.frames(audio, 16000), frames, strict=True):
                    np.testing.assert_array_equal(frame, expected)
    assert list(tmp_path.iterdir()) == []


def test_rgba_float_is_the_premultiplied_frame_of_the_same_draw(small_export):
    from gaussiantalker.runtime import TalkingHead

    with TalkingHead(small_export.path, resolution=(64, 64), background=(0.2, 0.4, 0.6)) as head:
        drive = FrameDrive.make(head.driver.config.n_expr, jaw_pose=[0.2, 0.0, 0.0])
        premultiplied = head.render(drive, output="rgba_float")
        opaque = head.render(drive, output="float")
        assert premultiplied.shape == (64, 64, 4) and premultiplied.dtype == np.float32
        over = premultiplied[..., :3] + (1 - premultiplied[..., 3:]) * np.array([0.2, 0.4, 0.6], np.float32)
        # The background pass adds T * background in the same float32 framebuffer: equal to float rounding.
        np.testing.assert_allclose(over, opaque, atol=1e-6)


def test_semantic_pass_and_region_weights(clip_export):
    from gaussiantalker.runtime import TalkingHead

    with TalkingHead(clip_export.path, composite=False, resolution=(64, 64)) as head:
        regions = head.frame_renderer.regions
        assert regions.names == clip_export.speaker.flame_arrays.region_names
        faces = clip_export.speaker.flame_arrays.regions[clip_export.speaker.gaussians.parent.numpy()]
        np.testing.assert_array_equal(regions.ids, faces)
        drive = FrameDrive.make(head.driver.config.n_expr, jaw_pose=[0.25, 0.0, 0.0])
        weights = head.frame_renderer.region_weights(drive)
        coverage = head.render(drive, output="rgba_float")[..., 3]
        assert weights.shape == (64, 64, len(regions.names))
        # Each region's weight is the blend weight of its Gaussians; together they are the frame's coverage.
        np.testing.assert_allclose(weights.sum(axis=-1), coverage, atol=1e-5)
        semantic = head.render(drive, output="semantic")
        expected = to_uint8(weights @ regions.colors)
        assert np.abs(semantic.astype(int) - expected).max() <= 1
        lips = weights[..., regions.names.index("lips")]
        assert lips.max() > 0.5 and (weights.argmax(-1) == regions.names.index("skin")).sum() > 100


def test_scene_export_leaves_the_clip_out(clip_export, small_scene_export, replay_onnx_exports):
    """The clip speaker exported for the small speaker's scene: no clip, no F. Its Gaussians, translator and
    deformation are the small speaker's, so that scene's specialisation and recorded graphs are its own (checked:
    every buffer but the clip's equals the small speaker's scene bundle's)."""
    from gaussiantalker.exporter.export.bundle_export import export_bundle
    from gaussiantalker.sdk.bundle import Bundle

    path = clip_export.folder / "scene.gtb"
    replay_onnx_exports(small_scene_export.protos)
    export_bundle(clip_export.speaker, path, scene=small_scene_export.result.specialisation, progress=False)
    manifest = Bundle(path).manifest
    assert "scene" in manifest and "reference" not in manifest and "inpaint" not in manifest["graphs"]
    assert clip_export.speaker.reference is not None  # the caller's speaker keeps its clip
    assert _entries(path) == _entries(small_scene_export.path)


# -- the clip's codec knob (`ExportSettings.reference`, docs/compositing.md) -------------------------------------

CLIP_TEST_CRF = 33  # far above the stored CRF 18, so the re-encoded frames are clearly smaller and coarser


def _entries(path) -> dict:
    from gaussiantalker.sdk.bundle import Bundle

    return {name: entry["sha256"] for name, entry in Bundle(path).manifest["buffers"].items()}


def test_reference_keep_stores_the_checkpoints_bytes(clip_export):
    """"keep" (the default, `quality`'s) writes every frame and mask entry byte for byte as the checkpoint holds it."""
    from gaussiantalker.exporter.export.presets import ExportSettings
    from gaussiantalker.sdk.bundle import Bundle
    from gaussiantalker.sdk.reference_clip import mask_entry

    assert ExportSettings().reference == "keep"
    bundle, clip = Bundle(clip_export.path), clip_export.speaker.reference
    assert bundle.manifest["export_settings"]["reference"] == "keep"
    for index in range(CLIP_FRAMES):
        assert bundle.buffer(frame_entry(index)).tobytes() == clip.frames[index]
        assert bundle.buffer(mask_entry(index)).tobytes() == clip.masks[index]


def test_reference_crf_reencodes_the_frames_only(clip_export, replay_onnx_exports, tmp_path):
    """crf:N re-encodes every frame (smaller, intra-only, colour tags kept, decodable alone); masks and every other
    entry are unchanged; the composited frames stay close to the stored clip's."""
    import av

    from gaussiantalker.exporter.export.bundle_export import export_bundle
    from gaussiantalker.exporter.export.presets import ExportSettings
    from gaussiantalker.runtime import TalkingHead
    from gaussiantalker.sdk.bundle import Bundle
    from gaussiantalker.sdk.reference_clip import decode_picture

    replay_onnx_exports(clip_export.protos)
    path = tmp_path / "crf.gtb"
    result = export_bundle(clip_export.speaker, path, settings=ExportSettings(reference=f"crf:{CLIP_TEST_CRF}"),
                           progress=False)
    keep, coarse = _entries(clip_export.path), _entries(path)
    frames = {frame_entry(i) for i in range(CLIP_FRAMES)}
    assert keep.keys() == coarse.keys()
    assert {name for name in keep if keep[name] != coarse[name]} == frames  # only the frames changed
    manifest, plain = Bundle(path).manifest, Bundle(clip_export.path).manifest
    assert manifest["export_settings"]["reference"] == f"crf:{CLIP_TEST_CRF}"
    assert manifest["reference"] == plain["reference"]
    assert sum(manifest["buffers"][n]["nbytes"] for n in frames) < \
        0.7 * sum(plain["buffers"][n]["nbytes"] for n in frames)
    assert 0 < result.reference_bytes < sum(e["nbytes"] for n, e in plain["buffers"].items()
                                            if n.startswith("reference/"))
    bundle = Bundle(path)
    for index in range(CLIP_FRAMES):  # each entry one intra picture with the stored frames' colour description
        picture = decode_picture("h264", bundle.buffer(frame_entry(index)).tobytes(), "frame")
        assert picture.key_frame and picture.pict_type == av.video.frame.PictureType.I
        assert (picture.colorspace, picture.color_range, picture.color_primaries, picture.color_trc) == \
            (av.video.reformatter.Colorspace.ITU601, av.video.reformatter.ColorRange.MPEG, 1, 13)
    audio = np.random.default_rng(0).normal(0.0, 0.1, 6 * clip_export.speaker.config.samples_per_frame)
    with TalkingHead(clip_export.path) as stored, TalkingHead(path) as head:
        rate = head.driver.config.sample_rate
        clip_psnr = [psnr_db(stored.reference.frame(i), head.reference.frame(i)) for i in range(CLIP_FRAMES)]
        frame_psnr = [psnr_db(want, got) for want, got in zip(stored.frames(audio, rate), head.frames(audio, rate),
                                                               strict=True)]
    # Measured on this 96x112 clip at CRF 33: clip frames 32.5-32.6 dB and composited frames 35.9-36.1 dB against
    # the stored clip's (the demo clip at CRF 33: 38.3 and 40.7 dB, docs/compositing.md). 29 and 32 dB leave ~3.5 dB
    # for another x264 build's rate control; a coarser clip than this CRF's, or a colour or alignment slip (tens of
    # levels), fails, and so does a re-encode that changed nothing (inf).
    assert 29.0 <= min(clip_psnr) and max(clip_psnr) < float("inf")
    assert 32.0 <= min(frame_psnr) and max(frame_psnr) < float("inf")


def test_reference_knob_in_presets_and_without_a_clip(clip_export, small_export, replay_onnx_exports, tmp_path):
    """A preset re-encodes the clip as its knob says (the same bytes as `EncodedClip.reencoded`: frames in groups of
    pictures, masks as H.264), and the manifest records the new layout; a speaker without a clip exports the same
    entries whatever the knob says."""
    from gaussiantalker.exporter.export.bundle_export import export_bundle
    from gaussiantalker.exporter.export.presets import PRESETS, ExportSettings, parse_reference
    from gaussiantalker.sdk.bundle import Bundle
    from gaussiantalker.sdk.reference_clip import mask_entry

    replay_onnx_exports(clip_export.protos)
    preset = PRESETS["balanced"]
    path = tmp_path / "balanced.gtb"
    export_bundle(clip_export.speaker, path, preset="balanced", progress=False)
    bundle = Bundle(path)
    assert bundle.manifest["export_settings"]["reference"] == preset.export.reference
    expected = clip_export.speaker.reference.reencoded(parse_reference(preset.export.reference))
    assert [bundle.buffer(frame_entry(i)).tobytes() for i in range(CLIP_FRAMES)] == expected.frames
    assert [bundle.buffer(mask_entry(i)).tobytes() for i in range(CLIP_FRAMES)] == expected.masks
    assert bundle.manifest["reference"] == expected.layout.to_dict()
    assert (expected.layout.gop, expected.layout.mask_codec) == (25, "h264")

    replay_onnx_exports(small_export.protos)
    bare = tmp_path / "bare.gtb"
    result = export_bundle(small_export.speaker, bare, settings=ExportSettings(reference="crf:40"), progress=False)
    assert result.reference_bytes == 0 and _entries(bare) == _entries(small_export.path)
    assert "reference" not in Bundle(bare).manifest


def test_reencoding_refuses_a_bad_crf(clip_export):
    with pytest.raises(ReferenceClipError, match="CRF must be an integer 0..51, got 52"):
        clip_export.speaker.reference.reencoded(52)


def test_clip_crf_bench_end_to_end(clip_export, replay_onnx_exports, tmp_path):
    """`gt-bench clip-crf` on the small clip speaker: "keep" matches itself exactly, a CRF row is smaller and finite,
    and the presets table compares whole files and bare heads (ratios from the files' sizes)."""
    from tools.bench.clip_crf import run_clip_crf_bench

    with_f, bare = clip_export.protos, clip_export.protos[:4]  # a bare head has no inpaint graph
    replay_onnx_exports(with_f * 3 + bare + with_f + bare)  # keep, crf:33, quality (+ bare), balanced (+ bare)
    out = tmp_path / "clip-crf.md"
    text = run_clip_crf_bench(clip_export.checkpoint, (CLIP_TEST_CRF,), ("quality", "balanced"), seconds=0.2,
                              out=out, progress=False)
    assert out.read_text() == text
    rows = {line.split("|")[1].strip(): [c.strip() for c in line.split("|")[2:-1]] for line in text.splitlines()
            if line.startswith("| ") and not line.startswith("| clip setting") and not line.startswith("| preset")}
    assert rows["keep"][2:] == ["identical"] * 4
    measured = json.loads(out.with_suffix(".json").read_text())
    keep, coarse = measured["clip"]
    assert coarse["frame_bytes"] < keep["frame_bytes"] and coarse["clip_bytes"] < keep["clip_bytes"]
    assert keep["clip_bytes"] - keep["frame_bytes"] == coarse["clip_bytes"] - coarse["frame_bytes"]  # masks kept
    worst = [float("inf") if cell == "identical" else float(cell.split(" / ")[0])
             for cell in rows[f"crf:{CLIP_TEST_CRF}"][2:]]
    assert min(worst) < float("inf") and all(value >= 29.0 for value in worst)  # as above
    quality, balanced = rows["quality"], rows["balanced"]
    assert quality[0] == "keep" and quality[3] == quality[6] == "1.0" and quality[4] == ""
    sizes = {row["preset"]: row for row in measured["presets"]}
    assert sizes["balanced"]["bundle_bytes"] < sizes["quality"]["bundle_bytes"]
    assert sizes["balanced"]["bare_bytes"] < sizes["quality"]["bare_bytes"]
    assert sizes["balanced"]["clip_bytes"] < sizes["quality"]["clip_bytes"]  # balanced re-encodes the clip
    assert sizes["quality"]["bare_bytes"] < sizes["quality"]["bundle_bytes"] - sizes["quality"]["clip_bytes"]
    ratio = sizes["quality"]["bundle_bytes"] / sizes["balanced"]["bundle_bytes"]
    assert balanced[3] == f"{ratio:.1f}" and balanced[4] == f"≥ 5: {'met' if ratio >= 5 else 'missed'}"
