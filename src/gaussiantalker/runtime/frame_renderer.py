"""The second stage of a frame's path (docs/embedding.md, "Stages"): drives -> Gaussians through the bundle's
deformation graph (a GraphBackend), then pixels through a Splatter (runtime/splat/: GL or CPU, one contract).

`prepare` needs no GL and is safe on a worker thread; `draw` runs on the thread that made the splatter (a GL context
is bound to it), or, where the splatter says `frames_at_once` > 1 (the CPU one), whole frames run on that many
worker threads. The pipelined frame loops (runtime/frame_loops.py) overlap frames either way.
"""

from __future__ import annotations

import time

import numpy as np

from gaussiantalker.sdk.camera import Camera
from gaussiantalker.sdk.errors import BundleError
from gaussiantalker.sdk.rig import check_drive_rig
from gaussiantalker.sdk.scene import Scene, SceneGuard

from .backend import GraphBackend
from .driver import Drive
from .semantic import Regions
from .splat.common import PreparedSplats, Splatter
from .timings import Timings


class FrameRenderer:
    """One rig's drives in, frames out: the deformation graph, then the splatter, seen through `camera` over
    `background`. `scene` (None: any drive) guards the drives of a scene-specialised bundle (docs/scene.md)."""

    def __init__(self, graphs: GraphBackend, splatter: Splatter, camera: Camera, background: np.ndarray, *,
                 rig: str, scene: Scene | None = None, scene_guard: SceneGuard | None = None,
                 regions: Regions | None = None, timings: Timings | None = None, where: str = "bundle") -> None:
        self.graphs, self.splatter, self.camera = graphs, splatter, camera
        self.background = np.asarray(background, dtype=np.float32).reshape(3)
        self.rig, self.scene, self.scene_guard = rig, scene, scene_guard
        self.timings = timings if timings is not None else Timings()
        self._regions, self._where = regions, where

    def deform(self, drive: Drive) -> dict[str, np.ndarray]:
        """Run the deformation graph: world-space means, cov3d, rgb, opacity of one frame's Gaussians."""
        start = time.perf_counter()
        check_drive_rig(self.rig, drive.rig)
        inputs = drive.graph_inputs()
        if self.scene_guard is not None:
            self.scene_guard.check_drive(drive.expression, drive.flame_pose, drive.head_translation)
        inputs["camera_center"] = self.camera.center.astype(np.float32)[None]
        out = self.graphs.run("deform", inputs)
        self.timings.record("deformation", time.perf_counter() - start)
        return {"means": out["means"][0], "cov3d": out["cov3d"][0], "rgb": out["rgb"][0], "opacity": out["opacity"]}

    def prepare(self, drive: Drive) -> PreparedSplats:
        """Everything of a frame that needs no GL: deformation graph, packing, depth sort (thread-safe)."""
        g = self.deform(drive)
        return self.splatter.prepare(g["means"], g["cov3d"], g["rgb"], g["opacity"], self.camera)

    def draw(self, prepared: PreparedSplats, output: str = "uint8") -> np.ndarray:
        """The splatter's part of a frame (upload, splat, read back), its stage timings recorded."""
        frame = self.splatter.draw(prepared, self.background, output=output)
        for stage, seconds in self.splatter.last_timings.items():
            self.timings.record(stage, seconds)
        return frame

    def frame(self, drive: Drive, output: str = "uint8") -> np.ndarray:
        """`prepare` then `draw`: one whole frame, as a worker of `frames_at_once` makes it."""
        return self.draw(self.prepare(drive), output)

    def frames_at_once(self) -> int:
        """How many frames the pipelined loops may make at once, each whole on its own worker thread (the
        splatter's answer: 1 for GL, and for an app's own splatter that does not say)."""
        at_once = getattr(self.splatter, "frames_at_once", None)
        return 1 if at_once is None else int(at_once())

    def begin_worker(self) -> None:
        """Set up a worker thread of `frames_at_once` (the splatter's kernels on one core there)."""
        begin = getattr(self.splatter, "begin_worker", None)
        if begin is not None:
            begin()

    def render(self, drive: Drive, output: str = "uint8") -> np.ndarray:
        """One frame of `drive`: any of the splatter's outputs, or "semantic" (each Gaussian in its region's
        colour over black, uint8)."""
        if output == "semantic":
            g = self.deform(drive)
            return self._draw_in_colors(g, self.regions.gaussian_colors(g["opacity"].shape[0]), "uint8")
        return self.frame(drive, output)

    @property
    def regions(self) -> Regions:
        """The bundle's semantic regions: `names`, `colors` [R, 3] (the semantic pass's), per-Gaussian `ids`."""
        if self._regions is None:
            raise BundleError(f"{self._where}: bundle has no semantic regions (manifest 'regions'); re-export a "
                              "speaker whose FLAME model labels its triangles")
        return self._regions

    def region_weights(self, drive: Drive) -> np.ndarray:
        """Per-region coverage float32 [H, W, R]: the summed blend weight of each region's Gaussians at every
        pixel (the regions sum to the frame's coverage 1 - T), a soft mask per region. Costs ceil(R / 3) draws."""
        g = self.deform(drive)
        count, names = g["opacity"].shape[0], self.regions.names
        passes = [self._draw_in_colors(g, self.regions.one_hot(count, first), "float")
                  for first in range(0, len(names), 3)]
        return np.concatenate(passes, axis=-1)[..., : len(names)]

    def _draw_in_colors(self, g: dict[str, np.ndarray], colors: np.ndarray, output: str) -> np.ndarray:
        """A frame's Gaussians `g` drawn with these colours [N, 3] instead of their own, over black."""
        prepared = self.splatter.prepare(g["means"], g["cov3d"], colors, g["opacity"], self.camera)
        return self.splatter.draw(prepared, (0.0, 0.0, 0.0), output=output)

    def release(self) -> None:
        """Free the splatter (its GL objects); later draws raise RenderError."""
        self.splatter.release()


__all__ = ["FrameRenderer"]
