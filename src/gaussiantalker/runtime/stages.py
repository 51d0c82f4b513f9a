"""A bundle's frame path built from its manifest and the app's settings (docs/embedding.md, "Stages"): the Driver of
its rig, the FrameRenderer (graph backend + splatter) and, when compositing, the Compositor. Everything a frame may
need is read and checked here, at load, so a damaged bundle fails before the first frame, not mid-video.
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass

import numpy as np

from gaussiantalker.sdk.bundle import Bundle
from gaussiantalker.sdk.config import SpeakerConfig
from gaussiantalker.sdk.errors import BundleError
from gaussiantalker.sdk.reference_clip import ReferenceClip
from gaussiantalker.sdk.render_settings import SPLATTERS, RenderSettings, stored_defaults
from gaussiantalker.sdk.rig import ARKIT_RIG, ArkitRig, rig_kind
from gaussiantalker.sdk.scene import Scene, SceneError, SceneGuard

from .backend import GraphBackend, open_backend
from .compositor import Compositor
from .driver import ArkitDriver, FlameDriver
from .frame_renderer import FrameRenderer
from .output import output_view
from .semantic import Regions
from .settings import BackendSettings, OutputSettings, merged_render
from .splat.choice import SplatterChoice, choose_splatter
from .timings import Timings
from .translate import SILENCE_GATE_DBFS


@dataclass
class Stages:
    """The stages of one head, sharing one Timings: `compositor` is None for bare frames; `renderer` names the
    splatter that draws ("gl" or "cpu"); `reference` is the bundle's clip (None if it has none)."""

    driver: FlameDriver | ArkitDriver
    frame_renderer: FrameRenderer
    compositor: Compositor | None
    renderer: str
    reference: ReferenceClip | None
    timings: Timings
    render: RenderSettings  # the settings of the splatter that draws
    backend: BackendSettings  # with the graph threads of `render`


def bundle_render_settings(bundle: Bundle, render: RenderSettings | None = None, threads: int | None = None,
                           threads_label: str = "threads", splatter: str = "gl", **shortcuts) -> RenderSettings:
    """The render settings for `splatter` ("gl" or "cpu"): `render` (None: the runtime defaults the bundle stores for
    that splatter, BundleError if damaged) with the app's shortcut keywords (None: keep the value; SettingsError if
    bad or given twice)."""
    try:
        preset = stored_defaults(bundle.manifest, splatter)
    except (TypeError, ValueError) as exc:
        raise BundleError(f"{bundle.path}: manifest 'runtime_defaults' is invalid: {exc}") from None
    return merged_render(preset, render, threads, threads_label, **shortcuts)


def render_settings_by_splatter(bundle: Bundle, render: RenderSettings | None = None, threads: int | None = None,
                                threads_label: str = "threads", **shortcuts) -> dict[str, RenderSettings]:
    """`bundle_render_settings` for each splatter a head may draw with (`SPLATTERS`): the renderer is chosen after
    the settings are checked, and the bundle's defaults may differ between the two."""
    return {splatter: bundle_render_settings(bundle, render, threads, threads_label, splatter, **shortcuts)
            for splatter in SPLATTERS}


def read_rig(bundle: Bundle) -> SpeakerConfig | ArkitRig:
    """The FLAME speaker config or the ARKit rig of the manifest, checked (BundleError names what is wrong)."""
    manifest = bundle.manifest
    try:
        if rig_kind(manifest) == ARKIT_RIG:
            return ArkitRig.from_dict(manifest["rig"])
    except (TypeError, ValueError) as exc:
        raise BundleError(f"{bundle.path}: manifest has no valid rig: {exc}") from exc
    try:
        config = SpeakerConfig.from_dict(manifest["speaker"])
        config.check_timing()
    except (TypeError, ValueError, AttributeError) as exc:
        raise BundleError(f"{bundle.path}: manifest has no valid speaker config: {exc}") from exc
    return config


def read_background(bundle: Bundle, background=None) -> np.ndarray:
    """The app's background or the bundle's: 3 numbers finite in float32 (docs/untrusted-input.md, "Bundles")."""
    if background is None:
        background = bundle.manifest.get("background", (1, 1, 1))
        if not (isinstance(background, list | tuple) and len(background) == 3 and all(
                isinstance(c, int | float) and not isinstance(c, bool) and abs(c) <= float(np.finfo(np.float32).max)
                for c in background)):
            raise BundleError(f"{bundle.path}: manifest 'background' must be 3 finite numbers (RGB), got "
                              f"{repr(background)[:80]}")
    return np.asarray(background, dtype=np.float32).reshape(3)


def read_scene(bundle: Bundle, config: SpeakerConfig | ArkitRig) -> tuple[Scene | None, SceneGuard | None]:
    """The scene the bundle was specialised for (docs/scene.md) and its range checks; (None, None) if none."""
    data = bundle.manifest.get("scene")
    if data is None:
        return None, None
    try:
        scene = Scene.from_dict(data)
        if not isinstance(config, SpeakerConfig):
            raise SceneError("scenes are for FLAME speakers")
        return scene, SceneGuard(scene, config.n_expr)
    except (SceneError, TypeError, ValueError, AttributeError) as exc:
        raise BundleError(f"{bundle.path}: manifest 'scene' is invalid: {exc}") from None


def build_stages(bundle: Bundle, render: RenderSettings | dict[str, RenderSettings], output: OutputSettings,
                 backend: BackendSettings, *, gl_context=None, silence_gate_dbfs: float | None) -> Stages:
    """The stages of a head playing `bundle` with these (merged) settings; `render` may hold one RenderSettings per
    splatter (`render_settings_by_splatter`), the chosen splatter's are used, and the backend's graph threads are
    theirs."""
    by_splatter = render if isinstance(render, dict) else dict.fromkeys(SPLATTERS, render)
    # The renderer is chosen first (a GL splatter made to choose it is released if anything below fails): the
    # graphs' threads depend on it, and the CPU splatter's kernels load last, after the bundle is checked.
    choice = choose_splatter(backend.renderer, gl_context=gl_context, settings=by_splatter["gl"],
                             shader_target=backend.shader_target, cpu_settings=by_splatter["cpu"])
    backend = dataclasses.replace(backend, threads=choice.settings.graph_threads)
    try:
        return _build_stages(bundle, render, output, backend, choice, silence_gate_dbfs)
    except BaseException:
        choice.release()
        raise


def graph_threads(backend: BackendSettings, renderer: str) -> int | None:
    """Threads each graph runs on: the settings' own, else one where the CPU splatter draws (the pipelined loops
    make whole frames at once, one per core, and onnxruntime's results depend on its thread count, so the serial
    loop takes one too and makes the same bits: docs/speed.md, "Whole frames at once"), else the backend's
    default."""
    if backend.threads is None and renderer == "cpu":
        return 1
    return backend.threads


def _build_stages(bundle: Bundle, render: RenderSettings, output: OutputSettings, backend: BackendSettings,
                  choice: SplatterChoice, silence_gate_dbfs: float | None) -> Stages:
    manifest, timings = bundle.manifest, Timings()
    rig = read_rig(bundle)
    graphs: GraphBackend = open_backend(bundle, backend.name, threads=graph_threads(backend, choice.renderer))
    driver = _driver(bundle, graphs, rig, timings, silence_gate_dbfs)
    view = output_view(bundle, output)
    background = read_background(bundle, output.background)
    reference = ReferenceClip(bundle, output.resolution) if "reference" in manifest else None
    compositor = (Compositor.from_bundle(bundle, reference, driver.pose_track, graphs, timings=timings)
                  if view.composite else None)
    scene, scene_guard = read_scene(bundle, rig)
    if scene_guard is not None:
        scene_guard.check_camera(view.camera)
    splatter = choice.build()
    regions = Regions(bundle) if "regions" in manifest else None
    frame_renderer = FrameRenderer(graphs, splatter, view.camera, background, rig=driver.rig, scene=scene,
                                   scene_guard=scene_guard, regions=regions, timings=timings, where=str(bundle.path))
    return Stages(driver, frame_renderer, compositor, choice.renderer, reference, timings, choice.settings, backend)


def _driver(bundle: Bundle, graphs: GraphBackend, rig, timings: Timings,
            silence_gate_dbfs: float | None) -> FlameDriver | ArkitDriver:
    options = {"timings": timings, "silence_gate_dbfs": silence_gate_dbfs}
    return (ArkitDriver(bundle, graphs, rig, **options) if isinstance(rig, ArkitRig) else
            FlameDriver(bundle, graphs, rig, specialised="scene" in bundle.manifest, **options))


def open_driver(bundle: str | os.PathLike | Bundle, *, backend: str = "onnxruntime", threads: int | None = None,
                silence_gate_dbfs: float | None = SILENCE_GATE_DBFS) -> FlameDriver | ArkitDriver:
    """A bundle's Driver alone: its graphs and rig, no splatter and no GL. What a server runs that streams drives
    to clients that render them (`LiveSession(driver, output=None)`)."""
    bundle = bundle if isinstance(bundle, Bundle) else Bundle(bundle)
    return _driver(bundle, open_backend(bundle, backend, threads=threads), read_rig(bundle), Timings(),
                   silence_gate_dbfs)


__all__ = ["Stages", "build_stages", "graph_threads", "open_driver", "bundle_render_settings",
           "render_settings_by_splatter", "read_background",
           "read_rig", "read_scene"]
