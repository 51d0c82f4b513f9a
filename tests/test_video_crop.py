"""Odd frame sizes in H.264: why the padded stream cannot carry a crop back to the size asked (docs/video.md)."""

from __future__ import annotations

import av
import pytest

from gaussiantalker.sdk.video_formats import plan_video


def _open_x264(width: int, height: int, crop_rect: str) -> None:
    """Open a 4:2:0 libx264 encoder with an SPS crop rectangle (left,top,right,bottom)."""
    stream = av.open("/dev/null", "w", format="mp4").add_stream("libx264", rate=25,
                                                                 options={"x264-params": f"crop-rect={crop_rect}"})
    stream.width, stream.height, stream.pix_fmt = width, height, "yuv420p"
    stream.codec_context.open()


def test_x264_crops_4_2_0_only_in_two_pixel_steps():
    _open_x264(336, 214, "0,0,2,2")  # even crops are written (so the option itself is there)
    level = av.logging.get_level()
    av.logging.set_level(av.logging.ERROR)  # libav's own messages are off by default in PyAV
    try:
        with av.logging.Capture() as messages, pytest.raises(av.error.FFmpegError):
            _open_x264(334, 212, "0,0,1,1")  # the one-pixel crop an odd size needs is not
    finally:
        av.logging.set_level(level)
    assert any("not divisible by 2x2" in message for _, _, message in messages), messages


def test_plan_says_why_an_odd_h264_size_is_padded(tmp_path):
    plan = plan_video(tmp_path / "talk.mp4", (333, 211))
    assert plan.encoded_size == (334, 212)
    assert "padded to 334x212" in plan.describe() and "webm" in plan.describe()
    assert plan_video(tmp_path / "talk.webm", (333, 211)).encoded_size == (333, 211)
