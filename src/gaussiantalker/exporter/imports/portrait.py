"""Portrait framing, the default camera of imported avatars (docs/import.md, "Portrait framing"): a level front
view whose frame holds the head's box at PORTRAIT_FILL of its height, centred, with room for the shoulders below."""

from __future__ import annotations

import numpy as np

from gaussiantalker.sdk.camera import Camera

# The head's box height over the frame's height: the middle of 40-55%, a head-and-shoulders portrait.
PORTRAIT_FILL = 0.475
# A portrait lens (about 85 mm on a full-frame camera is 16 degrees): little perspective on the face at 1-2 m.
PORTRAIT_FOV_DEG = 20.0
# The box's width may fill this much of the frame's width at most (a very narrow frame is framed by width).
PORTRAIT_MAX_WIDTH_FILL = 0.9
# The head's box: these percentiles of its points, so a few stray Gaussians do not widen it.
BOX_PERCENTILES = (1.0, 99.0)
CAMERA_CHOICES = ("portrait", "source")


def head_box(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(low, high) corners of the head's box: the BOX_PERCENTILES of `points` [N, 3] on each axis; ValueError for
    no points or non-finite ones."""
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or points.shape[0] == 0 or not np.isfinite(points).all():
        raise ValueError(f"the head's box needs finite [N, 3] points, got shape {points.shape}")
    return np.percentile(points, BOX_PERCENTILES[0], axis=0), np.percentile(points, BOX_PERCENTILES[1], axis=0)


def portrait_camera(low: np.ndarray, high: np.ndarray, width: int, height: int, *,
                    fov_y_deg: float = PORTRAIT_FOV_DEG, fill: float = PORTRAIT_FILL) -> Camera:
    """A level camera in front of the head (the face toward +z, y up, as FLAME and LAM place it) aimed at the centre
    of the head's box [low, high], at the distance where the box's nearest face spans `fill` of the frame's height
    (or PORTRAIT_MAX_WIDTH_FILL of its width, whichever is further)."""
    if not 0.0 < fill < 1.0:
        raise ValueError(f"fill must be in (0, 1), got {fill!r}")
    low, high = np.asarray(low, dtype=np.float64), np.asarray(high, dtype=np.float64)
    centre, half = (low + high) / 2.0, np.maximum((high - low) / 2.0, 1e-6)
    tan_y = np.tan(np.radians(fov_y_deg) / 2.0)
    tan_x = tan_y * width / height
    # A point at depth d spans y / (d tan) of the half frame: the box's front face (depth distance - half z) is the
    # widest part of its image.
    distance = half[2] + max(half[1] / (fill * tan_y), half[0] / (PORTRAIT_MAX_WIDTH_FILL * tan_x))
    eye = centre + np.array([0.0, 0.0, distance])
    return Camera.looking_at(eye, centre, (0.0, 1.0, 0.0), width, height, fov_y_deg)


def projected(camera: Camera, points: np.ndarray) -> np.ndarray:
    """Pixel positions [N, 2] (column, row) of world `points` [N, 3] in `camera`'s image; ValueError for a point
    not in front of the camera."""
    view = np.asarray(points, dtype=np.float64).reshape(-1, 3) @ np.asarray(camera.R).T + np.asarray(camera.t)
    if not (view[:, 2] > 0).all():
        raise ValueError("a point lies behind the camera")
    return np.stack([camera.fx * view[:, 0] / view[:, 2] + camera.cx, camera.fy * view[:, 1] / view[:, 2] + camera.cy],
                    axis=1)


def box_height_fill(camera: Camera, low: np.ndarray, high: np.ndarray) -> float:
    """How much of the frame's height the box [low, high] covers in `camera`'s image (its 8 corners projected; all
    must lie in front of the camera)."""
    corners = np.array([[x, y, z] for x in (low[0], high[0]) for y in (low[1], high[1]) for z in (low[2], high[2])])
    rows = projected(camera, corners)[:, 1]
    return float((rows.max() - rows.min()) / camera.height)


__all__ = ["BOX_PERCENTILES", "CAMERA_CHOICES", "PORTRAIT_FILL", "PORTRAIT_FOV_DEG", "box_height_fill", "head_box",
           "portrait_camera", "projected"]
