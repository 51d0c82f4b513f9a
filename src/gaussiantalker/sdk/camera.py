"""The camera model every part of the SDK uses: OpenCV pinhole, world-to-camera [R|t], +z forward, +y down.

Pixel (x, y) has its centre at (x + 0.5, y + 0.5) (see `numerics.PIXEL_CENTER_OFFSET`), so a camera-space
point (X, Y, Z) lands at u = fx * X / Z + cx, v = fy * Y / Z + cy in the same continuous pixel coordinates.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from .errors import CameraError
from .numerics import DEFAULT_NEAR, FOV_CLAMP_MARGIN

MAX_IMAGE_SIDE = 16384
# How far R R^T may be from the identity (numpy's allclose, this as both its tolerances): a rotation written to JSON
# and read back stays one.
ROTATION_TOLERANCE = 1e-5
# The keys of a camera's description (`Camera.to_dict`), in order; "near" may be absent (DEFAULT_NEAR).
CAMERA_KEYS = ("width", "height", "fx", "fy", "cx", "cy", "R", "t", "near")

# Both renderers compute in float32, so every camera number must survive the conversion: finite in float32, and
# focal lengths at least the smallest normal float32 (below it fx would become 0 or lose its precision on a GPU).
FLOAT32_MAX = float(np.finfo(np.float32).max)
MIN_FOCAL_PX = float(np.finfo(np.float32).tiny)
# The most characters of a value a CameraError quotes: a camera may come from a file, and a refusal is one short line
# (docs/untrusted-input.md); arrays are described by their shape and first offending entry instead.
MAX_QUOTE = 80


def _line(text: str, limit: int = MAX_QUOTE) -> str:
    """`text` on one line (whitespace collapsed), cut to `limit` characters."""
    text = " ".join(text.split())
    return text if len(text) <= limit else text[:limit - 3] + "..."


def _quote(value) -> str:
    """`value` as a CameraError quotes it: its repr on one line, cut to MAX_QUOTE characters."""
    return _line(repr(value))


def _numbers(array: np.ndarray) -> str:
    """A small float array as nested lists of short numbers (`[[1, 0, 0], ...]`), one line."""
    if array.ndim == 0:
        return f"{float(array):.6g}"
    return "[" + ", ".join(_numbers(row) for row in array) + "]"


def _is_real(value) -> bool:
    """Whether `value` is a real number: not a string, and not a boolean (JSON's `true` is not the number 1)."""
    if isinstance(value, str | bytes | bool | np.bool_):
        return False
    try:
        float(value)
    except (TypeError, ValueError, OverflowError):
        return False
    return True


def _describe(value) -> str:
    """An array-like that is not an array of real numbers, in a few words: its type and shape, and its first entry
    that is not a real number."""
    try:
        array = np.asarray(value, dtype=object)
    except (TypeError, ValueError):
        return f"a ragged {type(value).__name__}"  # numpy refused even an object array
    if array.ndim == 0:
        return _quote(value)
    for index in np.ndindex(array.shape):
        if not _is_real(array[index]):
            return (f"{type(value).__name__} of shape {array.shape} whose entry {list(index)} is "
                    f"{_quote(array[index])}")
    return f"{type(value).__name__} of shape {array.shape}"


def _image_side(name: str, value) -> int:
    """An image side as int, or CameraError naming it (NaN, inf, None, strings and fractions included)."""
    try:
        valid = _is_real(value) and float(value) == int(value) and 1 <= int(value) <= MAX_IMAGE_SIDE
    except (TypeError, ValueError, OverflowError):
        valid = False
    if not valid:
        raise CameraError(f"camera {name} must be an integer in 1..{MAX_IMAGE_SIDE}, got {_quote(value)}")
    return int(value)


def _real(name: str, value) -> float:
    """A real number as float, or CameraError naming it (None, strings, booleans, complex)."""
    if isinstance(value, str | bytes | bool | np.bool_):
        raise CameraError(f"camera {name} must be a real number, got {_quote(value)}")
    try:
        return float(value)
    except OverflowError:
        raise CameraError(f"camera {name} must be a real number within float range, got {_quote(value)}") from None
    except (TypeError, ValueError):
        raise CameraError(f"camera {name} must be a real number, got {_describe(value)}") from None


def _matrix(name: str, value, shape: tuple[int, ...]) -> np.ndarray:
    """A float64 array of exactly `shape`, or CameraError naming it (strings and booleans are not numbers here
    either, though numpy would convert them)."""
    try:
        array = np.array(value, dtype=np.float64)
        numeric = isinstance(value, np.ndarray) and value.dtype.kind in "fiu"  # a renderer's own camera: no walk
        if not numeric and not all(_is_real(entry) for entry in np.asarray(value, dtype=object).reshape(-1)):
            raise ValueError("not real numbers")
    except (TypeError, ValueError, OverflowError):
        raise CameraError(f"camera {name} must be a {shape} array of real numbers within float range, got "
                          f"{_describe(value)}") from None
    if array.shape != shape:
        raise CameraError(f"camera {name} must have shape {shape}, got {array.shape}")
    return array


def _axis_rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    """[3, 3] rotation by `angle` radians about unit-length `axis` (Rodrigues)."""
    x, y, z = axis / np.linalg.norm(axis)
    k = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    return np.eye(3) + np.sin(angle) * k + (1.0 - np.cos(angle)) * (k @ k)


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
        for name in ("width", "height"):
            object.__setattr__(self, name, _image_side(name, getattr(self, name)))
        for name in ("fx", "fy", "cx", "cy", "near"):
            object.__setattr__(self, name, _real(name, getattr(self, name)))
        object.__setattr__(self, "R", _matrix("R", self.R, (3, 3)))
        object.__setattr__(self, "t", _matrix("t", self.t, (3,)))
        self.validate()

    def validate(self) -> None:
        """Raise CameraError naming the first unusable field and its limit."""
        for name in ("width", "height"):
            _image_side(name, getattr(self, name))
        for name in ("fx", "fy"):
            value = getattr(self, name)
            if not MIN_FOCAL_PX <= value <= FLOAT32_MAX:  # NaN fails too
                raise CameraError(f"camera focal length {name} must be finite and > 0 (within float32: "
                                  f"{MIN_FOCAL_PX:.3g}..{FLOAT32_MAX:.3g} px), got {value!r}")
        for name in ("cx", "cy"):
            value = getattr(self, name)
            if not abs(value) <= FLOAT32_MAX:
                raise CameraError(f"camera principal point {name} must be finite (|{name}| <= "
                                  f"{FLOAT32_MAX:.3g} px, float32), got {value!r}")
        if not 0 < self.near <= FLOAT32_MAX:
            raise CameraError(f"camera near plane must be finite and > 0 (float32), got {self.near!r}")
        for name in ("R", "t"):
            value = getattr(self, name)
            bad = np.argwhere(~(np.abs(value) <= FLOAT32_MAX))
            if bad.size:
                where = ", ".join(map(str, bad[0]))
                raise CameraError(f"camera extrinsics {name} must be finite (float32), got {name}[{where}] = "
                                  f"{float(value[tuple(bad[0])])!r}")
        orthonormal = np.allclose(self.R @ self.R.T, np.eye(3), rtol=ROTATION_TOLERANCE, atol=ROTATION_TOLERANCE)
        if not orthonormal or np.linalg.det(self.R) < 0:
            error = float(np.abs(self.R @ self.R.T - np.eye(3)).max())
            raise CameraError("camera R must be a proper rotation (orthonormal to 1e-5, det +1), got "
                              f"{_numbers(self.R)} (|R R^T - I| up to {error:.3g}, det {np.linalg.det(self.R):.3g})")

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates, -R^T t. # [3]"""
        return -self.R.T @ self.t

    def fov_clamp_limits(self) -> tuple[float, float, float, float]:
        """(x_min, x_max, y_min, y_max) for clamping x/z and y/z before the projection Jacobian.

        docs/numerics.md, "2D covariance and field-of-view clamp".
        """
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

    def to_dict(self) -> dict:
        """JSON-safe description (used by bundle manifests and checkpoints)."""
        return {
            "width": int(self.width), "height": int(self.height),
            "fx": float(self.fx), "fy": float(self.fy), "cx": float(self.cx), "cy": float(self.cy),
            "R": self.R.tolist(), "t": self.t.tolist(), "near": float(self.near),
        }

    @classmethod
    def from_dict(cls, data: dict) -> Camera:
        """Inverse of to_dict; raises CameraError naming a missing key or the first unusable value (each value is
        checked as it is, so "512" or 512.5 is not a width)."""
        if not isinstance(data, dict):
            raise CameraError(f"camera description must be an object, got {type(data).__name__}")
        missing = [key for key in CAMERA_KEYS[:-1] if key not in data]
        if missing:
            raise CameraError(f"camera description is incomplete: missing {', '.join(missing)}")
        values = {key: data[key] for key in CAMERA_KEYS[:-1]}
        return cls(**values, near=data.get("near", DEFAULT_NEAR))

    def orbited(self, yaw_deg: float, pitch_deg: float, target) -> Camera:
        """This camera swung around `target` [3]: by yaw about its own up axis, then by pitch about its right axis
        (same intrinsics, same distance): a novel view of what it looks at."""
        target = _matrix("target", target, (3,))
        turn = _axis_rotation(-self.R[1], np.radians(_real("yaw_deg", yaw_deg)))
        turn = _axis_rotation(turn @ self.R[0], np.radians(_real("pitch_deg", pitch_deg))) @ turn
        eye = target + turn @ (self.center - target)
        rotation = self.R @ turn.T  # rows: the turned camera axes
        return replace(self, R=rotation, t=-rotation @ eye)

    @classmethod
    def looking_at(cls, eye, target, up, width: int, height: int, fov_y_deg: float,
                   near: float = DEFAULT_NEAR) -> Camera:
        """A centred camera at `eye` looking at `target`, world `up` appearing up in the image (+y down)."""
        eye, target, up = (_matrix(name, v, (3,)) for name, v in (("eye", eye), ("target", target), ("up", up)))
        fov = _real("fov_y_deg", fov_y_deg)
        if not 0.0 < fov < 180.0:
            raise CameraError(f"camera fov_y_deg must be in (0, 180) degrees, got {fov_y_deg!r}")
        forward = target - eye
        if not np.linalg.norm(forward) > 0:
            raise CameraError(f"camera eye and target must differ (and be finite), got eye {_numbers(eye)}, "
                              f"target {_numbers(target)}")
        forward /= np.linalg.norm(forward)
        right = np.cross(forward, up)
        if not np.linalg.norm(right) > 1e-9 * np.linalg.norm(up):
            raise CameraError(f"camera up {_numbers(up)} must not be parallel to the view direction "
                              f"{_numbers(forward)} (nor zero or non-finite)")
        right /= np.linalg.norm(right)
        down = np.cross(forward, right)
        R = np.stack([right, down, forward])  # rows: camera x, y, z axes in world coordinates
        t = -R @ eye
        fy = 0.5 * height / np.tan(np.radians(fov) / 2.0)
        return cls(width, height, fy, fy, width / 2.0, height / 2.0, R, t, near)
