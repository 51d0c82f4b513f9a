"""Frame conversions, PNG files, and the error metrics used by every parity check (PSNR, max pixel error)."""

from __future__ import annotations

import os
from pathlib import Path

import av
import numpy as np


def to_uint8(image: np.ndarray) -> np.ndarray:
    """Float frame -> 8 bit, once, at the end: floor(clamp(v, 0, 1) * 255 + 0.5) in float32; NaN maps to 0."""
    work = np.clip(np.nan_to_num(np.asarray(image, dtype=np.float32), nan=0.0), 0.0, 1.0, dtype=np.float32)
    work *= np.float32(255.0)
    work += np.float32(0.5)
    np.floor(work, out=work)
    return work.astype(np.uint8)


def png_bytes(rgb: np.ndarray) -> bytes:
    """uint8 [H, W, 3] RGB -> an 8-bit RGB PNG file's bytes (PyAV's PNG encoder: no extra dependency)."""
    rgb = np.ascontiguousarray(rgb)
    if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3 or 0 in rgb.shape:
        raise ValueError(f"a PNG image must be uint8 [H, W, 3], got {rgb.dtype} {list(rgb.shape)}")
    context = av.CodecContext.create("png", "w")
    context.width, context.height, context.pix_fmt = rgb.shape[1], rgb.shape[0], "rgb24"
    frame = av.VideoFrame.from_ndarray(rgb, format="rgb24")
    return b"".join(bytes(packet) for packet in context.encode(frame) + context.encode(None))


def write_png(path: str | os.PathLike, rgb: np.ndarray) -> Path:
    """Write uint8 [H, W, 3] RGB as a PNG file (its folder made if missing); returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(png_bytes(rgb))
    return path


def straight_rgba(premultiplied: np.ndarray, background) -> np.ndarray:
    """(C, 1 - T) float [H, W, 4] as splatted -> uint8 [H, W, 4] straight (not premultiplied) RGBA.

    Colour C / (1 - T) is a weighted mean of the Gaussians' colours (the weights sum to 1 - T), so dividing keeps
    it in their range; an uncovered pixel (1 - T = 0) gets the background colour, so players that ignore alpha
    show the plain frame there. Compositing the result over the background gives the opaque frame to within
    the two 8-bit roundings (docs/video.md).
    """
    premultiplied = np.asarray(premultiplied, dtype=np.float32)
    coverage = premultiplied[..., 3:4]
    covered = coverage > 0.0
    with np.errstate(divide="ignore", invalid="ignore"):
        colour = np.where(covered, premultiplied[..., :3] / np.where(covered, coverage, 1.0),
                          np.asarray(background, dtype=np.float32).reshape(1, 1, 3))
    return to_uint8(np.concatenate([colour, coverage], axis=-1))


def psnr_db(reference: np.ndarray, test: np.ndarray, peak: float = 1.0) -> float:
    """Peak signal-to-noise ratio in dB; identical frames give +inf. uint8 frames use peak 255."""
    if reference.shape != test.shape:
        raise ValueError(f"frames differ in shape: {reference.shape} vs {test.shape}")
    if reference.dtype == np.uint8:
        peak = 255.0
    diff = reference.astype(np.float64) - test.astype(np.float64)
    mse = float(np.mean(diff * diff))
    return float("inf") if mse == 0.0 else float(10.0 * np.log10(peak * peak / mse))


def max_abs_error(reference: np.ndarray, test: np.ndarray) -> float:
    """Largest absolute per-element difference (in the frames' own units)."""
    return float(np.max(np.abs(reference.astype(np.float64) - test.astype(np.float64)), initial=0.0))


def seam_step(image: np.ndarray, mask: np.ndarray, distance: int = 2) -> float:
    """Mean absolute colour step across a mask's 0.5 contour: over every pixel pair `distance` apart along a row
    or column with M >= 0.5 on one side and M < 0.5 on the other, the mean over pairs and channels of
    |I(p) - I(q)| (in the image's units). A paste whose colours do not continue across the boundary scores high."""
    image = np.asarray(image, dtype=np.float64)
    inside = np.asarray(mask) >= 0.5
    steps = []
    for axis in (0, 1):
        count = inside.shape[axis] - distance
        a = np.take(inside, range(count), axis=axis)
        b = np.take(inside, range(distance, distance + count), axis=axis)
        crossing = a != b
        if crossing.any():
            diff = np.abs(np.take(image, range(count), axis=axis) - np.take(image, range(distance, distance + count),
                                                                           axis=axis))
            steps.append(diff[crossing])
    if not steps:
        raise ValueError("the mask has no 0.5 contour inside the image: no seam to measure")
    return float(np.concatenate(steps).mean())
