"""What every splatter shares (docs/numerics.md): the `Splatter` protocol the frame renderer draws through, the
packed and depth-sorted frame both kinds prepare alike (`PreparedSplats`, `sorted_rows`), and the frame kinds they
return. The GL splatter (splat/gl.py) and the CPU tile splatter (splat/cpu.py) implement it side by side.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from gaussiantalker.sdk.camera import Camera
from gaussiantalker.sdk.errors import RenderError
from gaussiantalker.sdk.render_settings import RenderSettings

from .depth_sort import DepthSorter

STAGES = ("sort", "upload", "draw", "readback")

# What `draw`/`render` return: "uint8" or "float" [H, W, 3] over the background; "rgba" uint8 [H, W, 4] straight
# colour and alpha; "rgba_float" float32 [H, W, 4] premultiplied (C, 1 - T), no background.
FRAME_OUTPUTS = ("uint8", "float", "rgba", "rgba_float")
ALPHA_OUTPUTS = ("rgba", "rgba_float")

FLOATS_PER_SPLAT = 13  # mean 3, covariance 6, rgb 3, opacity 1


def checked_gaussians(means, cov3d, rgb, opacity) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The four arrays as C-contiguous float32 means [N, 3], cov3d [N, 6], rgb [N, 3], opacity [N], or
    RenderError naming the one whose shape does not match."""
    means = np.ascontiguousarray(means, dtype=np.float32)
    if means.ndim != 2 or means.shape[1] != 3:
        raise RenderError(f"means must have shape [N, 3], got {list(means.shape)}")
    n = means.shape[0]
    arrays = {
        "cov3d": (np.ascontiguousarray(cov3d, dtype=np.float32), (n, 6)),
        "rgb": (np.ascontiguousarray(rgb, dtype=np.float32), (n, 3)),
        "opacity": (np.ascontiguousarray(opacity, dtype=np.float32), (n,)),
    }
    for name, (array, shape) in arrays.items():
        if array.shape != shape and not (name == "opacity" and array.shape == (n, 1)):
            raise RenderError(f"{name} must have shape {list(shape)} to match means {list(means.shape)}, "
                              f"got {list(array.shape)}")
    return means, arrays["cov3d"][0], arrays["rgb"][0], arrays["opacity"][0].reshape(n)


def pack_gaussians(means, cov3d, rgb, opacity) -> np.ndarray:
    """Validate shapes and pack [N, 13] float32 rows: mean xyz, cov xx xy xz yy yz zz, rgb, opacity."""
    means, cov3d, rgb, opacity = checked_gaussians(means, cov3d, rgb, opacity)
    packed = np.empty((means.shape[0], FLOATS_PER_SPLAT), dtype=np.float32)
    packed[:, 0:3] = means
    packed[:, 3:9] = cov3d
    packed[:, 9:12] = rgb
    packed[:, 12] = opacity
    return packed


def background_rgb(background) -> tuple[float, float, float]:
    """Three finite floats, or RenderError."""
    values = np.asarray(background, dtype=np.float64).reshape(-1)
    if values.shape != (3,) or not np.all(np.isfinite(values)):
        raise RenderError(f"background must be 3 finite floats, got {background!r}")
    return tuple(float(v) for v in values)


@dataclass(frozen=True)
class PreparedSplats:
    """A frame's Gaussians packed and sorted front to back, with their draw runs: ready for `GLSplatter.draw`."""

    rows: np.ndarray  # [n, 13] float32, culled and depth-sorted
    runs: list[tuple[int, int, bool]]  # (start, stop, as_quads)
    camera: Camera  # the camera drawn with (at the render scale's size)
    seconds: float  # time spent preparing (reported as the "sort" stage)
    output_size: tuple[int, int] | None = None  # (width, height) returned, when it differs from the drawn size


def draw_camera(settings: RenderSettings, camera: Camera) -> tuple[Camera, tuple[int, int] | None]:
    """The camera to draw with at the render scale's draw size, and the output size to upscale to (None: none)."""
    if not isinstance(camera, Camera):
        raise RenderError(f"camera must be a gaussiantalker.sdk.camera.Camera, got {type(camera).__name__}")
    output_size = (int(camera.width), int(camera.height))
    draw_size = settings.draw_size(*output_size)
    if draw_size == output_size:
        return camera, None
    return camera.resized(*draw_size), output_size  # the same view, fewer pixels: upscaled after drawing


def sorted_rows(sorter: DepthSorter, settings: RenderSettings, means, cov3d, rgb, opacity, camera: Camera
                ) -> tuple[np.ndarray, Camera, tuple[int, int] | None]:
    """What both splatters prepare alike: the Gaussians validated, packed and sorted front to back ([n, 13]) for the
    camera at the render scale's draw size, that camera, and the output size to upscale to (None: no upscale)."""
    camera, output_size = draw_camera(settings, camera)
    packed = pack_gaussians(means, cov3d, rgb, opacity)
    return packed[sorter.order(packed, camera)], camera, output_size


@runtime_checkable
class Splatter(Protocol):
    """A frame's Gaussians in, pixels out, on the numerics contract: `prepare` needs no GL and is safe on a worker
    thread, `draw` runs on the thread that owns the splatter (or, where `frames_at_once` > 1, on that many worker
    threads at once); `last_timings` holds the last draw's STAGES seconds (the calling thread's last draw)."""

    settings: RenderSettings
    last_timings: dict[str, float]

    def prepare(self, means, cov3d, rgb, opacity, camera: Camera) -> PreparedSplats:
        """Validate, pack and depth-sort one frame's Gaussians for `camera`."""

    def draw(self, prepared: PreparedSplats, background, *, output: str = "uint8") -> np.ndarray:
        """Splat a prepared frame over `background` -> a frame of kind `output` (FRAME_OUTPUTS)."""

    def render(self, means, cov3d, rgb, opacity, camera: Camera, background, *, output: str = "uint8"
               ) -> np.ndarray:
        """`prepare` then `draw`."""

    def release(self) -> None:
        """Free what the splatter holds; later draws raise RenderError."""

    def frames_at_once(self) -> int:
        """How many frames a frame loop may draw at once, each prepared and drawn whole on its own worker thread
        (1: draws stay on the owning thread, as a GL context's must)."""

    def begin_worker(self) -> None:
        """Set up the calling worker thread to draw one of `frames_at_once` frames (run once per thread)."""


__all__ = ["ALPHA_OUTPUTS", "FLOATS_PER_SPLAT", "FRAME_OUTPUTS", "STAGES", "PreparedSplats", "Splatter",
           "background_rgb", "checked_gaussians", "draw_camera", "pack_gaussians", "sorted_rows"]
