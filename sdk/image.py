"""Frame conversions and the error metrics used by every parity check (PSNR, max pixel error)."""

from __future__ import annotations

import numpy as np


def to_uint8(image: np.ndarray) -> np.ndarray:
    """Float frame -> 8 bit, once, at the end: floor(clamp(v, 0, 1) * 255 + 0.5) in float32; NaN maps to 0."""
    work = np.clip(np.nan_to_num(np.asarray(image, dtype=np.float32), nan=0.0), 0.0, 1.0, dtype=np.float32)
    work *= np.float32(255.0)
    work += np.float32(0.5)
    np.floor(work, out=work)
    return work.astype(np.uint8)


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
