"""3D Gaussian Splatting point clouds in PLY (the INRIA layout: x, y, z, f_dc_0..2, f_rest_*, opacity, scale_*,
rot_*), read with plyfile into checked float32 arrays."""

from __future__ import annotations

import io
from dataclasses import dataclass

import numpy as np
from plyfile import PlyData

from gaussiantalker.sdk.errors import ImportFormatError

REQUIRED_FIELDS = ("x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
                   "rot_0", "rot_1", "rot_2", "rot_3")


@dataclass
class GaussianCloud:
    """One PLY's Gaussians: xyz [N, 3], f_dc [N, 3], f_rest [N, R, 3] (R = 0 without higher SH), opacity logit [N],
    log-scale [N, 3], quaternion (w, x, y, z) [N, 4], and any extra scalar fields by name."""

    xyz: np.ndarray
    f_dc: np.ndarray
    f_rest: np.ndarray
    opacity: np.ndarray
    log_scale: np.ndarray
    rotation: np.ndarray
    extra: dict

    @property
    def count(self) -> int:
        return int(self.xyz.shape[0])


def read_gaussian_ply(data: bytes, member: str) -> GaussianCloud:
    """Parse a Gaussian PLY; ImportFormatError naming `member` and the field that is missing or not finite."""
    try:
        ply = PlyData.read(io.BytesIO(data))
    except Exception as exc:  # plyfile raises assorted errors on damaged headers and bodies
        raise ImportFormatError(f"{member}: not a readable PLY file: {exc}") from exc
    if "vertex" not in [element.name for element in ply.elements]:
        raise ImportFormatError(f"{member}: the PLY has no 'vertex' element")
    vertex = ply["vertex"].data
    names = vertex.dtype.names or ()
    missing = [name for name in REQUIRED_FIELDS if name not in names]
    if missing:
        raise ImportFormatError(f"{member}: the PLY's vertex element lacks field(s) {', '.join(missing)} "
                                f"(a Gaussian PLY has {', '.join(REQUIRED_FIELDS)})")
    if len(vertex) == 0:
        raise ImportFormatError(f"{member}: the PLY holds no Gaussians")

    def stack(fields: list[str]) -> np.ndarray:
        out = np.stack([np.asarray(vertex[name], np.float64) for name in fields], axis=-1)
        bad = ~np.isfinite(out)
        if bad.any():
            row, column = np.argwhere(bad)[0]
            raise ImportFormatError(f"{member}: field {fields[column]} of Gaussian {row} is {out[row, column]} "
                                    f"({int(bad.any(axis=1).sum())} Gaussians have non-finite values)")
        return out.astype(np.float32)

    rest_names = sorted((n for n in names if n.startswith("f_rest_")), key=lambda n: int(n.rsplit("_", 1)[1]))
    if len(rest_names) % 3:
        raise ImportFormatError(f"{member}: {len(rest_names)} f_rest fields is not a multiple of 3")
    f_rest = stack(rest_names) if rest_names else np.zeros((len(vertex), 0), np.float32)
    # The INRIA layout stores f_rest channel-major: all of red's coefficients, then green's, then blue's.
    f_rest = f_rest.reshape(len(vertex), 3, -1).transpose(0, 2, 1)
    known = set(REQUIRED_FIELDS) | set(rest_names) | {"nx", "ny", "nz"}
    return GaussianCloud(
        xyz=stack(["x", "y", "z"]), f_dc=stack(["f_dc_0", "f_dc_1", "f_dc_2"]), f_rest=np.ascontiguousarray(f_rest),
        opacity=stack(["opacity"])[:, 0], log_scale=stack(["scale_0", "scale_1", "scale_2"]),
        rotation=stack(["rot_0", "rot_1", "rot_2", "rot_3"]),
        extra={n: np.asarray(vertex[n]) for n in names if n not in known})


__all__ = ["GaussianCloud", "REQUIRED_FIELDS", "read_gaussian_ply"]
