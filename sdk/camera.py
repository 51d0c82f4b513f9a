"""The camera model every part of the SDK uses: OpenCV pinhole, world-to-camera [R|t], +z forward, +y down.

Pixel (x, y) has its centre at (x + 0.5, y + 0.5) (see `numerics.PIXEL_CENTER_OFFSET`), so a camera-space
point (X, Y, Z) lands at u = fx * X / Z + cx, v = fy * Y / Z + cy in the same continuous pixel coordinates.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .errors import CameraError
from .numerics import DEFAULT_NEAR, FOV_CLAMP_MARGIN

MAX_IMAGE_SIDE = 16384


@dataclass(frozen=True)
class Camera:
    """A pinhole camera: image size in pixels, intrinsics in pixels, extrinsics world -> camera."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    R: np.ndarray = field(default_factory=lambda: np.eye(3, dtype=np.float64))  # [3, 3] world -> camera
    t: np.ndarray = field(default_factory=lambda: np.zeros(3, dtype=np.float64))  # [3]
    near: float = DEFAULT_NEAR

    def __post_init__(self) -> None:
        object.__setattr__(self, "R", np.asarray(self.R, dtype=np.float64).reshape(3, 3))
        object.__setattr__(self, "t", np.asarray(self.t, dtype=np.float64).reshape(3))
        self.validate()

    def validate(self) -> None:
        """Raise CameraError naming the first unusable field."""
        for name in ("width", "height"):
            value = getattr(self, name)
            if int(value) != value or not 1 <= value <= MAX_IMAGE_SIDE:
                raise CameraError(f"camera {name} must be an integer in 1..{MAX_IMAGE_SIDE}, got {value!r}")
        for name in ("fx", "fy"):
            value = getattr(self, name)
            if not np.isfinite(value) or value <= 0:
                raise CameraError(f"camera focal length {name} must be finite and > 0, got {value!r}")
        for name in ("cx", "cy"):
            if not np.isfinite(getattr(self, name)):
                raise CameraError(f"camera principal point {name} must be finite, got {getattr(self, name)!r}")
        if not np.isfinite(self.near) or self.near <= 0:
            raise CameraError(f"camera near plane must be finite and > 0, got {self.near!r}")
        if not (np.all(np.isfinite(self.R)) and np.all(np.isfinite(self.t))):
            raise CameraError("camera extrinsics R, t must be finite")
        if not np.allclose(self.R @ self.R.T, np.eye(3), atol=1e-5) or np.linalg.det(self.R) < 0:
            raise CameraError("camera R must be a proper rotation (orthonormal, det +1)")

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates, -R^T t. # [3]"""
        return -self.R.T @ self.t

    def fov_clamp_limits(self) -> tuple[float, float, float, float]:
        """(x_min, x_max, y_min, y_max) for clamping x/z and y/z before the projection Jacobian (contract)."""
        mx = FOV_CLAMP_MARGIN * self.width / (2.0 * self.fx)
        my = FOV_CLAMP_MARGIN * self.height / (2.0 * self.fy)
        return (
            -self.cx / self.fx - mx,
            (self.width - self.cx) / self.fx + mx,
            -self.cy / self.fy - my,
            (self.height - self.cy) / self.fy + my,
        )

    def resized(self, width: int, height: int) -> Camera:
        """The same view at another resolution: intrinsics scale with the image (pixel-centre convention kept)."""
        sx, sy = width / self.width, height / self.height
        return Camera(width, height, self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy, self.R, self.t,
                      self.near)

    def with_pose(self, R: np.ndarray, t: np.ndarray) -> Camera:
        """The same intrinsics with new extrinsics."""
        return Camera(self.width, self.height, self.fx, self.fy, self.cx, self.cy, R, t, self.near)

    def to_dict(self) -> dict:
        """JSON-safe description (used by bundle manifests and checkpoints)."""
        return {
            "width": int(self.width), "height": int(self.height),
            "fx": float(self.fx), "fy": float(self.fy), "cx": float(self.cx), "cy": float(self.cy),
            "R": self.R.tolist(), "t": self.t.tolist(), "near": float(self.near),
        }

    @classmethod
    def from_dict(cls, data: dict) -> Camera:
        """Inverse of to_dict; raises CameraError on a missing key."""
        try:
            return cls(int(data["width"]), int(data["height"]), float(data["fx"]), float(data["fy"]),
                       float(data["cx"]), float(data["cy"]), np.asarray(data["R"]), np.asarray(data["t"]),
                       float(data.get("near", DEFAULT_NEAR)))
        except (KeyError, TypeError, ValueError) as exc:
            raise CameraError(f"camera description is incomplete or malformed: {exc}") from exc

    @classmethod
    def looking_at(cls, eye, target, up, width: int, height: int, fov_y_deg: float,
                   near: float = DEFAULT_NEAR) -> Camera:
        """A centred camera at `eye` looking at `target`, world `up` appearing up in the image (+y down)."""
        eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
        forward = target - eye
        forward /= np.linalg.norm(forward)
        right = np.cross(forward, up)
        right /= np.linalg.norm(right)
        down = np.cross(forward, right)
        R = np.stack([right, down, forward])  # rows: camera x, y, z axes in world coordinates
        t = -R @ eye
        fy = 0.5 * height / np.tan(np.radians(fov_y_deg) / 2.0)
        return cls(width, height, fy, fy, width / 2.0, height / 2.0, R, t, near)
