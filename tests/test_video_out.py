"""Video out: every container and codec the SDK offers, odd sizes, alpha, refusals before rendering, an encoder
failure mid-clip (docs/video.md)."""

from __future__ import annotations

import subprocess
import sys
import textwrap
import time
from pathlib import Path

import av
import numpy as np
import pytest

from gaussiantalker.runtime import TalkingHead
from gaussiantalker.sdk.errors import VideoError
from gaussiantalker.sdk.image import psnr_db, straight_rgba, to_uint8
from gaussiantalker.sdk.video import VideoWriter, probe_video
from gaussiantalker.sdk.video_formats import plan_video

ROOT = Path(__file__).resolve().parents[1]
FPS = 25
AUDIO = (0.3 * np.sin(np.arange(16_000) * 2 * np.pi * 440 / 16_000)).astype(np.float32)  # 1 s, 25 frames


def _frames(width: int, height: int, count: int, alpha: bool = False) -> list[np.ndarray]:
    """Smooth gradients that move per frame (codecs keep them well), alpha a horizontal ramp."""
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float32)
    frames = []
    for i in range(count):
        rgb = np.stack([xx / max(width - 1, 1), yy / max(height - 1, 1), np.full_like(xx, i / count)], axis=-1)
        channels = [rgb] + ([((xx + 1) / width)[..., None]] if alpha else [])
        frames.append(to_uint8(np.concatenate(channels, axis=-1)))
    return frames


def _write(path: Path, frames: list[np.ndarray], **options) -> Path:
    height, width = frames[0].shape[:2]
    with VideoWriter(path, FPS, (width, height), audio=AUDIO, **options) as out:
        for frame in frames:
            out.write(frame)
    return path


def _decode(path: Path, alpha: bool = False) -> list[np.ndarray]:
    """Every frame as uint8 RGB(A); VP9's alpha plane needs libvpx's own decoder."""
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        decoder = av.CodecContext.create("libvpx-vp9", "r") if alpha and stream.codec_context.name == "vp9" else None
        frames = []
        for packet in container.demux(stream):
            for frame in (decoder or stream.codec_context).decode(packet) if packet.size else []:
                frames.append(frame.to_ndarray(format="rgba" if alpha else "rgb24"))
        for frame in (decoder or stream.codec_context).decode(None):
            frames.append(frame.to_ndarray(format="rgba" if alpha else "rgb24"))
    return frames


# -- every container and codec -------------------------------------------------------------------------------------

# (file name, options, codec probed, pixel format probed, alpha, audio codec or None, decoded min PSNR dB).
# The PSNR floors sit ~3 dB under what these 48x32 gradients measured: 4:2:0 H.264/VP9 at their default quality
# ~37 dB (chroma subsampling of a per-pixel colour ramp), ProRes 4444 56 dB, FFV1 (lossless, after the 8-bit
# RGB -> YUV conversion) 52 dB, GIF (a 256-colour palette per frame) 31 dB; a misplaced or garbled frame is < 15 dB.
OUTPUTS = [
    ("talk.mp4", {}, "h264", "yuv420p", False, "aac", 34.0),
    ("talk.mov", {}, "h264", "yuv420p", False, "aac", 34.0),
    ("talk.mov", {"codec": "prores", "alpha": True}, "prores", "yuva444p12le", True, "aac", 53.0),
    ("talk.webm", {}, "vp9", "yuv420p", False, "opus", 34.0),
    ("talk.webm", {"alpha": True}, "vp9", "yuv420p", True, "opus", 34.0),
    ("talk.mkv", {"codec": "ffv1", "alpha": True}, "ffv1", "yuva444p", True, "aac", 49.0),
    ("talk.mkv", {"codec": "vp9"}, "vp9", "yuv420p", False, "aac", 34.0),
    ("talk.gif", {}, "gif", "bgra", False, None, 28.0),
]


@pytest.mark.parametrize("name, options, codec, pix_fmt, alpha, audio, min_psnr", OUTPUTS,
                         ids=[f"{n}-{o.get('codec', 'default')}{'-alpha' if o.get('alpha') else ''}"
                              for n, o, *_ in OUTPUTS])
def test_every_container_and_codec(tmp_path, name, options, codec, pix_fmt, alpha, audio, min_psnr):
    frames = _frames(48, 32, 10, alpha=alpha)
    info = probe_video(_write(tmp_path / name, frames, **options))
    assert (info["frames"], info["width"], info["height"]) == (10, 48, 32)
    assert (info["codec"], info["pix_fmt"], info["has_alpha"]) == (codec, pix_fmt, alpha)
    assert info["has_audio"] == (audio is not None) and info["audio_codec"] == audio
    decoded = _decode(tmp_path / name, alpha=alpha)
    assert len(decoded) == 10
    channels = 4 if alpha else 3
    assert min(psnr_db(a[..., :channels], b[..., :channels]) for a, b in zip(frames, decoded, strict=True)) > min_psnr
    assert [p.name for p in tmp_path.iterdir()] == [name]  # nothing staged is left


def test_png_sequence_with_alpha_is_exact(tmp_path):
    frames = _frames(7, 5, 4, alpha=True)
    _write(tmp_path / "frames" / "%05d.png", frames, alpha=True)
    written = sorted((tmp_path / "frames").iterdir())
    assert [p.name for p in written] == ["00001.png", "00002.png", "00003.png", "00004.png"]  # ffmpeg numbers from 1
    for frame, path in zip(frames, written, strict=True):
        assert probe_video(path)["pix_fmt"] == "rgba"
        np.testing.assert_array_equal(_decode(path, alpha=True)[0], frame)


def test_failed_png_sequence_leaves_no_frame(tmp_path):
    with pytest.raises(RuntimeError, match="render failed"), \
            VideoWriter(tmp_path / "frames" / "%05d.png", FPS, (8, 8)) as out:
        out.write(np.zeros((8, 8, 3), np.uint8))
        raise RuntimeError("render failed")
    assert list((tmp_path / "frames").iterdir()) == []


# -- any size --------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("width, height", [(1, 1), (333, 211), (4097, 3)])
def test_odd_sizes_keep_every_pixel(tmp_path, width, height):
    """H.264 (4:2:0) pads an odd side by repeating the last row/column; VP9 and PNG keep the exact size."""
    frames = _frames(width, height, 3)
    h264 = probe_video(_write(tmp_path / "a.mp4", frames))
    assert (h264["width"], h264["height"]) == (width + width % 2, height + height % 2)
    decoded = _decode(tmp_path / "a.mp4")[0]
    if width > 8 and height > 8:  # big enough for a meaningful PSNR of the requested pixels (see OUTPUTS)
        assert psnr_db(frames[0], decoded[:height, :width]) > 34.0
    vp9 = probe_video(_write(tmp_path / "b.webm", frames))
    assert (vp9["width"], vp9["height"], vp9["frames"]) == (width, height, 3)
    _write(tmp_path / "seq" / "%03d.png", frames)
    np.testing.assert_array_equal(_decode(tmp_path / "seq" / "001.png")[0], frames[0])


def test_padding_repeats_the_edge(tmp_path):
    frame = np.zeros((3, 5, 3), np.uint8)
    frame[:, -1] = 200  # last column bright, so a black pad column would show
    frame[-1, :] = 100
    with VideoWriter(tmp_path / "a.mkv", FPS, (5, 3), codec="h264", crf=0) as out:
        out.write(frame)
    decoded = _decode(tmp_path / "a.mkv")[0]
    assert decoded.shape == (4, 6, 3)
    assert np.abs(decoded[:3, 5].astype(int) - decoded[:3, 4]).max() <= 8  # pad column copies the last column
    assert np.abs(decoded[3, :5].astype(int) - decoded[2, :5]).max() <= 8  # pad row copies the last row


# -- refusals: before any frame, nothing written ------------------------------------------------------------------


@pytest.mark.parametrize("name, options, message", [
    ("talk.txt", {}, "extension '.txt' is not a video format"),
    ("talk", {}, "no extension is not a video format"),
    ("talk.mp4", {"alpha": True}, "mp4 cannot hold an alpha channel"),
    ("talk.gif", {"alpha": True}, "gif cannot hold an alpha channel"),
    ("talk.mov", {"alpha": True, "codec": "h264"}, "codec h264 has no alpha plane"),
    ("talk.webm", {"codec": "h264"}, "webm cannot hold codec 'h264'"),
    ("talk.mp4", {"codec": "zip"}, "mp4 cannot hold codec 'zip'"),
    ("talk.mp4", {"crf": 52}, "crf 52 is outside h264's range 0..51"),
    ("talk.mov", {"codec": "prores", "crf": 10}, "codec prores has no crf setting"),
    ("talk.webm", {"preset": "veryfast"}, "preset 'veryfast' is not one of vp9's presets"),
    ("talk.mp4", {"container": "avi"}, "unknown video format 'avi'"),
    ("frames/%d_%d.png", {}, "exactly one frame number"),
    ("frames/still.png", {}, "exactly one frame number"),
])
def test_bad_outputs_are_named(tmp_path, name, options, message):
    with pytest.raises(VideoError, match=message):
        plan_video(tmp_path / name, (64, 48), **options)
    assert list(tmp_path.iterdir()) == []


def test_bad_destinations_are_named(tmp_path):
    with pytest.raises(VideoError, match="is a folder"):
        plan_video(tmp_path, (64, 48))
    (tmp_path / "file").write_text("")
    with pytest.raises(VideoError, match="is not a folder"):
        plan_video(tmp_path / "file" / "talk.mp4", (64, 48))
    with pytest.raises(VideoError, match="cannot write in folder /proc"):  # writable by nobody, root included
        plan_video("/proc/talk.mp4", (64, 48))
    with pytest.raises(VideoError, match="encodes at most 16384 pixels a side"):
        plan_video(tmp_path / "a.mp4", (16385, 2))
    with pytest.raises(VideoError, match="mp4 cannot hold codec 'hevc'"):  # not offered: see sdk/video_formats.py
        plan_video(tmp_path / "a.mp4", (64, 64), codec="hevc")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file"]


@pytest.fixture(scope="module")
def head(small_export):
    with TalkingHead(small_export.path, resolution=(64, 48)) as talking_head:
        yield talking_head


def test_write_video_refuses_before_the_first_frame(head, tmp_path, monkeypatch):
    def no_rendering(*args, **kwargs):
        raise AssertionError("a frame was rendered before the output was checked")

    monkeypatch.setattr(head, "frames", no_rendering)
    for path, options in [(tmp_path / "a.txt", {}), (tmp_path / "a.mp4", {"alpha": True}), (tmp_path, {})]:
        start = time.perf_counter()
        with pytest.raises(VideoError):
            head.write_video(path, AUDIO, **options)
        assert time.perf_counter() - start < 0.5
    assert list(tmp_path.iterdir()) == []


def test_player_refuses_before_loading_the_speaker(small_export, tmp_path, monkeypatch):
    from typer.testing import CliRunner

    import gaussiantalker.runtime.head as head_module

    sys.path.insert(0, str(ROOT / "samples"))
    try:
        import play
    finally:
        sys.path.remove(str(ROOT / "samples"))
    monkeypatch.setattr(head_module.TalkingHead, "__init__", lambda *a, **k: pytest.fail("the speaker was loaded"))
    monkeypatch.setattr(play, "TalkingHead", head_module.TalkingHead)
    for output, extra, message in [
        ("talk.txt", [], "extension '.txt' is not a video format"),
        ("talk.mp4", ["--alpha"], "mp4 cannot hold an alpha channel"),
        (str(tmp_path), [], "is a folder"),
        ("talk.mp4", ["-r", "333x"], "resolution must be N or WxH"),
        ("talk.mp4", ["--background", "red"], "background must be r,g,b"),
    ]:
        speech = str(ROOT / "samples" / "demo_speech.wav")
        result = CliRunner().invoke(play.app, [str(small_export.path), "--audio", speech, "-o", str(tmp_path / output),
                                               *extra])
        assert result.exit_code == 2, result.output
        assert result.stderr.startswith("error: ") and message in result.stderr
        assert len(result.stderr.strip().splitlines()) == 1
    assert list(tmp_path.iterdir()) == []


# -- alpha from the same draw ------------------------------------------------------------------------------------


def test_straight_rgba_unpremultiplies_safely():
    premultiplied = np.array([[[0.5, 0.25, 0.0, 0.5], [0.0, 0.0, 0.0, 0.0], [1e-30, 0.0, 0.0, 1e-30],
                               [0.9, 0.9, 0.9, 1.0]]], np.float32)
    rgba = straight_rgba(premultiplied, (0.2, 0.4, 0.6))
    np.testing.assert_array_equal(rgba[0, 0], [255, 128, 0, 128])  # colour (1, 0.5, 0) at half coverage
    np.testing.assert_array_equal(rgba[0, 1], [51, 102, 153, 0])  # uncovered: the background colour
    np.testing.assert_array_equal(rgba[0, 2], [255, 0, 0, 0])  # tiny coverage: finite, no NaN
    np.testing.assert_array_equal(rgba[0, 3], [230, 230, 230, 255])


def test_rgba_frames_composite_back_to_the_opaque_frames(head):
    drive = next(iter(head.drives(AUDIO[:3200], 16_000)))
    opaque = head.render(drive, output="float")
    rgba = head.render(drive, output="rgba")
    assert rgba.dtype == np.uint8 and rgba.shape == (48, 64, 4)
    alpha = rgba[..., 3:4] / 255.0
    composite = rgba[..., :3] / 255.0 * alpha + head.frame_renderer.background * (1.0 - alpha)
    # Two 8-bit roundings (colour, alpha) and the straight colour's amplification at low coverage: within 2 levels.
    assert np.abs(composite - opaque).max() <= 2.0 / 255.0
    assert 0 < np.count_nonzero(rgba[..., 3]) < rgba[..., 3].size  # the head is covered, the corners are not
    assert rgba[0, 0, 3] == 0


def test_write_video_with_alpha(head, tmp_path):
    path = head.write_video(tmp_path / "talk.webm", AUDIO[:6400], 16_000, alpha=True)  # 0.4 s: 10 frames
    info = probe_video(path)
    assert (info["frames"], info["has_alpha"], info["has_audio"]) == (10, True, True)
    decoded = _decode(path, alpha=True)
    assert decoded[0][0, 0, 3] < 8 and decoded[0][24, 32, 3] > 247  # a corner is clear, the face covered


# -- never lose a render ------------------------------------------------------------------------------------------


def test_encoder_failure_mid_clip_is_named_and_leaves_nothing(tmp_path):
    """The file-size limit makes the muxer's write fail after a few frames, as a full disk does."""
    code = textwrap.dedent(f"""
        import resource, signal
        import numpy as np
        from gaussiantalker.sdk.errors import VideoError
        from gaussiantalker.sdk.video import VideoWriter
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # the write then fails with EFBIG instead of killing us
        resource.setrlimit(resource.RLIMIT_FSIZE, (200_000, 200_000))
        noise = np.random.default_rng(0).integers(0, 255, (30, 128, 128, 3), dtype=np.uint8)
        try:
            with VideoWriter({str(tmp_path / 'talk.mov')!r}, 25, (128, 128), codec="prores") as out:
                for frame in noise:
                    out.write(frame)
        except VideoError as error:
            print(error)
    """)
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert "talk.mov failed at frame" in result.stdout and "File too large" in result.stdout
    assert list(tmp_path.iterdir()) == []


def test_rendering_failure_leaves_nothing(head, tmp_path, monkeypatch):
    def failing(*args, **kwargs):
        yield np.zeros((48, 64, 3), np.uint8)
        raise RuntimeError("render failed")

    monkeypatch.setattr(head, "frames", failing)
    with pytest.raises(RuntimeError, match="render failed"):
        head.write_video(tmp_path / "talk.mp4", AUDIO, 16_000)
    assert list(tmp_path.iterdir()) == []
