"""PNG files (sdk/image.py): what is written reads back the same pixels (through Pillow, a reader of its own), and a
wrong image is refused with what it is."""

from __future__ import annotations

import io

import numpy as np
import pytest

from gaussiantalker.sdk.image import png_bytes, write_png


@pytest.mark.parametrize("shape", [(1, 1, 3), (33, 47, 3), (64, 2, 3)])
def test_png_round_trips_every_pixel(shape, tmp_path):
    from PIL import Image

    rgb = np.random.default_rng(sum(shape)).integers(0, 256, shape, dtype=np.uint8)
    path = write_png(tmp_path / "sub" / "a.png", rgb)
    with Image.open(path) as picture:
        assert picture.mode == "RGB" and np.array_equal(np.asarray(picture), rgb)
    with Image.open(io.BytesIO(png_bytes(rgb[:, ::-1]))) as picture:  # a non-contiguous view
        assert np.array_equal(np.asarray(picture), rgb[:, ::-1])


@pytest.mark.parametrize("bad", [np.zeros((4, 4), np.uint8), np.zeros((4, 4, 4), np.uint8),
                                 np.zeros((4, 4, 3), np.float32), np.zeros((0, 4, 3), np.uint8)])
def test_png_refuses_what_is_not_an_rgb_image(bad):
    with pytest.raises(ValueError, match=r"must be uint8 \[H, W, 3\]"):
        png_bytes(bad)
