"""The tests' reading of a PNG's pixel rows as stored: each row's filter byte, then its filtered bytes (only what
the tests check of the files the SDK and its tools write; images are decoded with libav elsewhere)."""

from __future__ import annotations

import struct
import zlib

import numpy as np

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def png_rows(data: bytes) -> tuple[int, int, np.ndarray]:
    """(width, height, rows uint8 [height, 1 + row bytes]) of a non-interlaced PNG: its IDAT chunks joined and
    inflated; column 0 of each row is that row's filter type."""
    assert data[:8] == PNG_SIGNATURE
    chunks, pos = {}, 8  # length / type / body / CRC chunks after the signature
    while pos < len(data):
        (length,), kind = struct.unpack(">I", data[pos:pos + 4]), data[pos + 4:pos + 8]
        chunks[kind] = chunks.get(kind, b"") + data[pos + 8:pos + 8 + length]
        pos += 12 + length
    width, height = struct.unpack(">II", chunks[b"IHDR"][:8])
    return width, height, np.frombuffer(zlib.decompress(chunks[b"IDAT"]), np.uint8).reshape(height, -1)
