"""TalkingHead's settings in groups, as onnxruntime takes SessionOptions: `OutputSettings` (what the frames look
like), `BackendSettings` (what runs the graphs and shaders) and `RenderSettings` (speed/accuracy knobs, from
gaussiantalker.sdk.render_settings); and how the old keyword shortcuts combine with them (docs/embedding.md).

In a group, None is "not set": the bundle's default. A shortcut keyword fills the group's field; a shortcut and a
group field that are both set to different values are one setting given twice, refused with SettingsError.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from numbers import Integral
from typing import Any

import numpy as np

from gaussiantalker.sdk.camera import Camera
from gaussiantalker.sdk.errors import SettingsError
from gaussiantalker.sdk.render_settings import RenderSettings
from gaussiantalker.shaders import check_target

from .backend import GRAPH_BACKENDS, check_backend_name


def _size(value: Any) -> tuple[int, int]:
    """(width, height) as two whole numbers >= 1, or SettingsError naming `resolution`."""
    try:
        width, height = value
    except (TypeError, ValueError):
        width = height = None
    if not all(isinstance(v, Integral) and not isinstance(v, bool) and v >= 1 for v in (width, height)):
        raise SettingsError(f"output resolution must be (width, height), two whole numbers >= 1, got {value!r}")
    return int(width), int(height)


def _rgb(value: Any) -> tuple[float, float, float]:
    """Three finite numbers, or SettingsError naming `background`."""
    try:
        values = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        values = np.zeros(0)
    if values.shape != (3,) or not np.all(np.isfinite(values)):
        raise SettingsError(f"output background must be 3 finite numbers (r, g, b), got {value!r}")
    return float(values[0]), float(values[1]), float(values[2])


@dataclass(frozen=True)
class OutputSettings:
    """What a TalkingHead's frames are: `resolution` (width, height) (None: the camera's own size, the reference
    clip's when compositing), `camera` (None: the bundle's; not with compositing), `background` r, g, b (None: the
    bundle's, else white) and `composite` into the reference clip (None: whether the bundle has one)."""

    resolution: tuple[int, int] | None = None
    camera: Camera | None = None
    background: tuple[float, float, float] | None = None
    composite: bool | None = None

    def __post_init__(self) -> None:
        if self.resolution is not None:
            object.__setattr__(self, "resolution", _size(self.resolution))
        if self.camera is not None and not isinstance(self.camera, Camera):
            raise SettingsError(f"output camera must be a gaussiantalker.sdk.camera.Camera, got "
                                f"{type(self.camera).__name__}")
        if self.background is not None:
            object.__setattr__(self, "background", _rgb(self.background))
        if self.composite is not None:
            if not isinstance(self.composite, bool | np.bool_):
                raise SettingsError(f"output composite must be True, False or None, got {self.composite!r}")
            object.__setattr__(self, "composite", bool(self.composite))

    def _key(self) -> tuple:
        camera = None if self.camera is None else json.dumps(self.camera.to_dict(), sort_keys=True)
        return self.resolution, camera, self.background, self.composite

    def __eq__(self, other: object) -> bool:  # a Camera holds arrays: compared by value through its dict
        return isinstance(other, OutputSettings) and self._key() == other._key()

    def __hash__(self) -> int:
        return hash(self._key())


# What splats the frames (docs/embedding.md, "Renderer"): the OpenGL splatter, the CPU tile splatter, or "auto".
RENDERERS = ("auto", "gl", "cpu")


@dataclass(frozen=True)
class BackendSettings:
    """What runs a TalkingHead: the graph backend `name` ("onnxruntime" or "mnn", docs/mnn.md), its `threads`
    (None: the bundle's preset, else one where the CPU splatter draws, every core
    for onnxruntime otherwise, one for MNN), the GLSL variant compiled, `shader_target`
    ("330", "410", "300es"; the same pixels, docs/shaders.md), the `renderer` that splats: "gl",
    "cpu" (the numba tile splatter, the `cpu` extra) or "auto", the default (cpu where the GL is a software
    rasterizer or none starts, and numba is installed; gl in an app's GL context or on a GPU), and whether the frame
    loops `pipeline` their stages across frames on worker threads (runtime/pipeline.py; the same frames either way;
    None: on, False: one stage after another on the caller's thread)."""

    name: str = "onnxruntime"
    threads: int | None = None
    shader_target: str = "330"
    renderer: str = "auto"
    pipeline: bool | None = None

    def __post_init__(self) -> None:
        try:
            check_backend_name(self.name)
        except ValueError as exc:
            raise SettingsError(str(exc)) from None
        threads = self.threads
        if threads is not None and (isinstance(threads, bool) or not isinstance(threads, Integral) or threads < 1):
            raise SettingsError(f"backend threads must be a whole number >= 1 or None, got {threads!r}")
        if threads is not None:
            object.__setattr__(self, "threads", int(threads))
        try:
            check_target(self.shader_target)
        except ValueError as exc:
            raise SettingsError(str(exc)) from None
        if self.renderer not in RENDERERS:
            raise SettingsError(f"renderer must be one of {', '.join(map(repr, RENDERERS))}, got {self.renderer!r}")
        if self.pipeline is not None:
            if not isinstance(self.pipeline, bool | np.bool_):
                raise SettingsError(f"backend pipeline must be True, False or None, got {self.pipeline!r}")
            object.__setattr__(self, "pipeline", bool(self.pipeline))


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, Camera) and isinstance(b, Camera):
        return a is b or a.to_dict() == b.to_dict()
    return a == b


def _one_value(setting: str, given: dict[str, Any]) -> Any:
    """The one value of a setting given under several names (label -> value, None: not given), else SettingsError
    naming two that disagree."""
    values = [(label, value) for label, value in given.items() if value is not None]
    for label, value in values[1:]:
        first_label, first = values[0]
        if not _same(first, value):
            raise SettingsError(f"{setting} given twice: {first_label}={first!r} and {label}={value!r}; give it once")
    return values[0][1] if values else None


def _check_group(value: Any, kind: type, keyword: str) -> None:
    if value is not None and not isinstance(value, kind):
        raise SettingsError(f"{keyword}= must be a {kind.__name__} (or None), got {type(value).__name__}")


def merged_output(output: OutputSettings | None, **shortcuts: Any) -> OutputSettings:
    """`output` (None: all defaults) with the shortcut keywords resolution, camera, background, composite."""
    _check_group(output, OutputSettings, "output_settings")
    output = output or OutputSettings()
    fields = {}
    for name, value in shortcuts.items():
        given = None if value is None else getattr(OutputSettings(**{name: value}), name)  # checked, normalised
        fields[name] = _one_value(f"output {name}", {name: given, f"output.{name}": getattr(output, name)})
    return dataclasses.replace(output, **fields)


def merged_backend(backend: str | BackendSettings, threads: int | None = None,
                   shader_target: str | None = None, renderer: str | None = None,
                   pipeline: bool | None = None) -> BackendSettings:
    """The backend group from `backend=` (a name or a BackendSettings) and the threads, shader_target, renderer,
    pipeline shortcuts."""
    if isinstance(backend, str):
        return BackendSettings(backend, threads, "330" if shader_target is None else shader_target,
                               BackendSettings.renderer if renderer is None else renderer, pipeline)
    if not isinstance(backend, BackendSettings):
        raise SettingsError(f"backend= must be a backend name ({', '.join(GRAPH_BACKENDS)}) or a BackendSettings, "
                            f"got {type(backend).__name__}")
    return dataclasses.replace(
        backend, threads=_one_value("threads", {"threads": threads, "backend.threads": backend.threads}),
        shader_target=_one_value("shader_target", {"shader_target": shader_target,
                                                   "backend.shader_target": backend.shader_target}),
        renderer=_one_value("renderer", {"renderer": renderer, "backend.renderer": backend.renderer}),
        pipeline=_one_value("pipeline", {"pipeline": None if pipeline is None else BackendSettings(
            pipeline=pipeline).pipeline, "backend.pipeline": backend.pipeline}))


def merged_render(preset: RenderSettings, render: RenderSettings | None, threads: int | None,
                  threads_label: str = "threads", **shortcuts: Any) -> RenderSettings:
    """The render settings a head runs with: `render` (None: the bundle's `preset`) with the shortcut keywords
    render_scale, render_target, sort_interval, sort_key_bits, alpha_min, max_draw_pixels, transmittance_min, and the
    graph `threads`
    (given as `threads_label`; None: the render group's graph_threads, else the preset's)."""
    _check_group(render, RenderSettings, "render_settings")
    try:
        if render is None:
            return preset.with_overrides(graph_threads=threads, **shortcuts)
        fields = {name: _one_value(name, {name: value, f"render.{name}": getattr(render, name)})
                  for name, value in shortcuts.items()}
        threads = _one_value("graph threads", {threads_label: threads, "render.graph_threads": render.graph_threads})
        # (a field given nowhere is None here, and render's own None is what with_overrides then keeps)
        return render.with_overrides(graph_threads=preset.graph_threads if threads is None else threads, **fields)
    except SettingsError:
        raise
    except (TypeError, ValueError) as exc:
        raise SettingsError(str(exc)) from None


__all__ = ["RENDERERS", "BackendSettings", "OutputSettings", "RenderSettings", "merged_backend", "merged_output",
           "merged_render"]
