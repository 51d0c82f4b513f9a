"""Our OpenCV pinhole `Camera` as the three.js PerspectiveCamera the LAM web renderer draws with, and back.

three.js cameras look down their local -z with +y up; ours look down +z with +y down, so the camera-to-world
rotation is R^T diag(1, -1, -1). A PerspectiveCamera has one vertical field of view and a centred principal
point, so only centred cameras with fx == fy convert exactly; anything else is refused (docs/lam-web.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from gaussiantalker.sdk.camera import Camera

NEAR = 0.1     # the LAM web renderer's PerspectiveCamera near and far planes
FAR = 1000.0
# Its fixed camera (charactorConfig): position, then rotateX by -10 degrees, vertical field of view 50 degrees.
LAM_CAM_POSITION = (0.0, 1.8, 1.0)
LAM_CAM_ROTATE_X_DEG = -10.0
LAM_FOV_Y_DEG = 50.0
# How far the principal point may sit from the image centre (px) and fx from fy (relative) and still convert.
CENTRE_TOL_PX = 1e-6
FOCAL_TOL = 1e-9
FLIP_YZ = np.diag([1.0, -1.0, -1.0])


@dataclass(frozen=True)
class ThreeCamera:
    """A three.js PerspectiveCamera: world position, world quaternion (x, y, z, w), vertical fov, aspect, planes."""

    position: tuple[float, float, float]
    quaternion: tuple[float, float, float, float]
    fov: float
    aspect: float
    near: float = NEAR
    far: float = FAR

    def to_page(self) -> dict:
        """The camera as the harness page takes it (lam_web/lam_web.js, setCamera)."""
        return {"position": list(self.position), "quaternion": list(self.quaternion), "fov": self.fov,
                "aspect": self.aspect, "near": self.near, "far": self.far}


def quaternion_from_matrix(m: np.ndarray) -> tuple[float, float, float, float]:
    """Unit quaternion (x, y, z, w) of a rotation matrix, w >= 0 (the branch three.js setFromRotationMatrix takes)."""
    m = np.asarray(m, dtype=np.float64)
    trace = m[0, 0] + m[1, 1] + m[2, 2]
    if trace > 0:
        s = 0.5 / math.sqrt(trace + 1.0)
        q = (m[2, 1] - m[1, 2]) * s, (m[0, 2] - m[2, 0]) * s, (m[1, 0] - m[0, 1]) * s, 0.25 / s
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s
    else:
        s = 2.0 * math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s, (m[1, 0] - m[0, 1]) / s
    q = np.array(q) / np.linalg.norm(q)
    if q[3] < 0:
        q = -q
    return tuple(float(v) for v in q)


def matrix_from_quaternion(q) -> np.ndarray:
    """Rotation matrix of a unit quaternion (x, y, z, w), as three.js Matrix4.compose builds it."""
    x, y, z, w = (float(v) for v in q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def check_convertible(camera: Camera) -> None:
    """ValueError unless the camera is one a three.js PerspectiveCamera can be: centred principal point, fx == fy."""
    if abs(camera.cx - camera.width / 2.0) > CENTRE_TOL_PX or abs(camera.cy - camera.height / 2.0) > CENTRE_TOL_PX:
        raise ValueError(f"the LAM web renderer's camera has its principal point at the image centre "
                         f"({camera.width / 2.0}, {camera.height / 2.0}); this camera has ({camera.cx}, {camera.cy}): "
                         "crop or re-centre it instead of comparing against a different view")
    if abs(camera.fx - camera.fy) > FOCAL_TOL * max(camera.fx, camera.fy):
        raise ValueError(f"the LAM web renderer's camera has square pixels (one vertical field of view); this "
                         f"camera has fx={camera.fx} != fy={camera.fy}")


def to_three(camera: Camera) -> ThreeCamera:
    """The PerspectiveCamera that draws exactly what `camera` sees (ValueError where none can, see module doc)."""
    check_convertible(camera)
    position = -camera.R.T @ camera.t
    rotation = camera.R.T @ FLIP_YZ
    fov = math.degrees(2.0 * math.atan(camera.height / (2.0 * camera.fy)))
    return ThreeCamera(tuple(float(v) for v in position), quaternion_from_matrix(rotation), fov,
                       camera.width / camera.height)


def from_three(three: ThreeCamera, width: int, height: int) -> Camera:
    """Our Camera for a PerspectiveCamera drawn at width x height (its aspect is taken as width / height)."""
    rotation = matrix_from_quaternion(three.quaternion)
    R = (rotation @ FLIP_YZ).T
    t = -R @ np.asarray(three.position, dtype=np.float64)
    focal = height / (2.0 * math.tan(math.radians(three.fov) / 2.0))
    return Camera(width, height, focal, focal, width / 2.0, height / 2.0, R, t, three.near)


def lam_default_three(width: int, height: int) -> ThreeCamera:
    """The renderer's own fixed camera: position (0, 1.8, 1), rotateX(-10 deg), vertical fov 50, near 0.1."""
    half = math.radians(LAM_CAM_ROTATE_X_DEG) / 2.0
    return ThreeCamera(LAM_CAM_POSITION, (math.sin(half), 0.0, 0.0, math.cos(half)), LAM_FOV_Y_DEG, width / height)


def lam_default_camera(width: int, height: int) -> Camera:
    """The LAM web renderer's fixed camera at width x height, as our Camera."""
    return from_three(lam_default_three(width, height), width, height)


def three_matrices(three: ThreeCamera) -> tuple[np.ndarray, np.ndarray]:
    """(view, projection) 4x4 matrices as three.js computes them: matrixWorldInverse and projectionMatrix."""
    world = np.eye(4)
    world[:3, :3] = matrix_from_quaternion(three.quaternion)
    world[:3, 3] = three.position
    top = three.near * math.tan(math.radians(three.fov) / 2.0)
    bottom, right = -top, top * three.aspect
    left = -right
    n, f = three.near, three.far
    projection = np.array([
        [2 * n / (right - left), 0, (right + left) / (right - left), 0],
        [0, 2 * n / (top - bottom), (top + bottom) / (top - bottom), 0],
        [0, 0, -(f + n) / (f - n), -2 * f * n / (f - n)],
        [0, 0, -1, 0],
    ])
    return np.linalg.inv(world), projection


def project_three(three: ThreeCamera, points: np.ndarray, width: int, height: int) -> np.ndarray:
    """Pixel coordinates (x right, y down, pixel centres at +0.5) of world points through the three.js camera."""
    view, projection = three_matrices(three)
    homogeneous = np.concatenate([np.asarray(points, np.float64), np.ones((len(points), 1))], axis=1)
    clip = homogeneous @ (projection @ view).T
    ndc = clip[:, :3] / clip[:, 3:4]
    return np.stack([(ndc[:, 0] + 1.0) * 0.5 * width, (1.0 - ndc[:, 1]) * 0.5 * height], axis=1)
