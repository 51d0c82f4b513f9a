"""Which splatter draws a TalkingHead's frames: the OpenGL one or the CPU tile splatter (docs/embedding.md,
"Renderer").

"auto" (TalkingHead's default) draws with GL in a GL context the app gives (`gl_context=`: a window's). Otherwise
it tries GL first. Where no GL context can be made, or its shaders cannot be built (no libEGL, a sandbox, a
driver below OpenGL 3.3), it draws on the CPU splatter if numba (the `cpu` extra) is installed, and otherwise
raises one RenderError naming both problems. Where GL starts on a software rasterizer (SOFTWARE_RASTERIZERS), which
the CPU splatter outdraws (docs/bench/renderers.md), it releases GL for the CPU splatter when numba is installed.
Otherwise GL draws. Each choice is logged with its reason, once per process (logger "gaussiantalker.runtime").
"""

from __future__ import annotations

import importlib.util
import logging
from dataclasses import dataclass

from gaussiantalker.sdk.errors import RenderError, SettingsError
from gaussiantalker.sdk.render_settings import RenderSettings

from .common import Splatter
from .gl import GLSplatter

# GL_RENDERER substrings (lower case) of rasterizers that run on the CPU: Mesa's llvmpipe and softpipe, Google's
# SwiftShader, Apple's "Apple Software Renderer", and Microsoft's WARP ("Microsoft Basic Render Driver", e.g.
# "D3D12 (Microsoft Basic Render Driver)" under WSL's Mesa).
SOFTWARE_RASTERIZERS = ("llvmpipe", "softpipe", "swiftshader", "apple software renderer",
                        "microsoft basic render driver")
CPU_EXTRA_HINT = "pip install 'gaussiantalker-sdk[cpu]'"

logger = logging.getLogger("gaussiantalker.runtime")
_reported: set[tuple[str, str, str]] = set()


def is_software_renderer(gl_renderer: str) -> bool:
    """Whether a GL_RENDERER string names a CPU rasterizer (SOFTWARE_RASTERIZERS)."""
    name = gl_renderer.lower()
    return any(kind in name for kind in SOFTWARE_RASTERIZERS)


def cpu_splatter_available() -> bool:
    """Whether the CPU splatter can run here (numba importable)."""
    return importlib.util.find_spec("numba") is not None


def _report(requested: str, chosen: str, why: str) -> None:
    """Log the choice and its reason (INFO), once per process for each distinct one."""
    if (requested, chosen, why) not in _reported:
        _reported.add((requested, chosen, why))
        logger.info("renderer %r: drawing with the %s splatter (%s)", requested, chosen, why)


def _cpu_splatter(settings: RenderSettings | None):
    """The CPU tile splatter (imported here: numba is an optional extra)."""
    from .cpu import CPUSplatter

    return CPUSplatter(settings=settings)


@dataclass
class SplatterChoice:
    """A renderer chosen, before the CPU splatter is built: "gl" with its GLSplatter (made to choose it), or "cpu".
    Knowing the kind first lets the graphs be set up for it; `build` then gives the splatter (the CPU one's kernels
    load there), `release` frees a GL splatter that will not be used."""

    renderer: str  # "gl" or "cpu"
    gl: GLSplatter | None
    settings: RenderSettings | None

    def build(self) -> Splatter:
        """The chosen splatter: the GL one made when choosing, or a new CPU splatter."""
        return self.gl if self.gl is not None else _cpu_splatter(self.settings)

    def release(self) -> None:
        """Free the GL splatter made while choosing (nothing for "cpu")."""
        if self.gl is not None:
            self.gl.release()


def choose_splatter(renderer: str, *, gl_context=None, settings: RenderSettings | None = None,
                    shader_target: str = "330", cpu_settings: RenderSettings | None = None) -> SplatterChoice:
    """The choice `make_splatter` makes (the module's docstring), with the CPU splatter not yet built. `settings`
    are the GL splatter's and, unless `cpu_settings` are given, the CPU splatter's too."""
    cpu_settings = settings if cpu_settings is None else cpu_settings
    for given in (settings, cpu_settings):  # a wrong call, not a GL that cannot run
        if given is not None and not isinstance(given, RenderSettings):
            raise SettingsError(f"settings must be a RenderSettings, got {type(given).__name__}")
    if renderer == "cpu":
        if not cpu_splatter_available():
            raise SettingsError(f"renderer='cpu' needs numba, the cpu extra: {CPU_EXTRA_HINT}")
        _report(renderer, "cpu", "asked for")
        return SplatterChoice("cpu", None, cpu_settings)
    if renderer == "gl" or gl_context is not None:
        splatter = GLSplatter(gl_context, settings=settings, shader_target=shader_target)
        _report(renderer, "gl", "asked for" if renderer == "gl" else "the app gave a GL context to draw in")
        return SplatterChoice("gl", splatter, settings)
    try:
        splatter = GLSplatter(gl_context, settings=settings, shader_target=shader_target)
    except SettingsError:
        raise  # a bad setting, not a GL that cannot start
    except RenderError as exc:
        if not cpu_splatter_available():
            raise RenderError(f"renderer='auto' has nothing to draw with: OpenGL cannot run here ({exc}), and the "
                              f"CPU splatter needs numba, which is not installed: {CPU_EXTRA_HINT}") from exc
        _report(renderer, "cpu", f"OpenGL cannot run here: {exc}")
        return SplatterChoice("cpu", None, cpu_settings)
    gl_renderer = str(splatter.ctx.info.get("GL_RENDERER", ""))
    if not is_software_renderer(gl_renderer):
        _report(renderer, "gl", f"the GL renderer {gl_renderer!r} is not a software rasterizer")
        return SplatterChoice("gl", splatter, settings)
    if not cpu_splatter_available():
        _report(renderer, "gl", f"the GL renderer {gl_renderer!r} is a software rasterizer, but numba is not "
                                f"installed for the CPU splatter: {CPU_EXTRA_HINT}")
        return SplatterChoice("gl", splatter, settings)
    splatter.release()
    _report(renderer, "cpu", f"the GL renderer {gl_renderer!r} is a software rasterizer")
    return SplatterChoice("cpu", None, cpu_settings)


def make_splatter(renderer: str, *, gl_context=None, settings: RenderSettings | None = None,
                  shader_target: str = "330") -> tuple[Splatter, str]:
    """(splatter, "gl" or "cpu") for a `BackendSettings.renderer` choice: "gl", "cpu" or "auto" (the module's
    docstring). SettingsError for "cpu" without numba; RenderError where GL cannot start ("gl"), or where neither
    GL nor the CPU splatter can run ("auto")."""
    choice = choose_splatter(renderer, gl_context=gl_context, settings=settings, shader_target=shader_target)
    return choice.build(), choice.renderer


__all__ = ["CPU_EXTRA_HINT", "SOFTWARE_RASTERIZERS", "SplatterChoice", "choose_splatter", "cpu_splatter_available",
           "is_software_renderer", "make_splatter"]
