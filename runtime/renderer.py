"""Which splatter draws a TalkingHead's frames: the OpenGL one or the CPU tile splatter (docs/embedding.md).

"auto" picks the CPU splatter where the GL context is a software rasterizer (Mesa's llvmpipe or softpipe,
SwiftShader), which the CPU splatter outdraws (docs/bench/renderers.md), and where numba (the `cpu` extra) is
installed; otherwise GL. The choice is logged once per process and kind (logger "gaussiantalker.runtime").
"""

from __future__ import annotations

import importlib.util
import logging

from gaussiantalker.sdk.errors import SettingsError
from gaussiantalker.sdk.render_settings import RenderSettings

from .splatter import GLSplatter

SOFTWARE_RASTERIZERS = ("llvmpipe", "softpipe", "swiftshader")
CPU_EXTRA_HINT = "pip install 'gaussiantalker-sdk[cpu]'"

logger = logging.getLogger("gaussiantalker.runtime")
_reported: set[tuple[str, str]] = set()


def is_software_renderer(gl_renderer: str) -> bool:
    """Whether a GL_RENDERER string names a CPU rasterizer (llvmpipe, softpipe, SwiftShader)."""
    name = gl_renderer.lower()
    return any(kind in name for kind in SOFTWARE_RASTERIZERS)


def cpu_splatter_available() -> bool:
    """Whether the CPU splatter can run here (numba importable)."""
    return importlib.util.find_spec("numba") is not None


def _report(requested: str, chosen: str, why: str) -> None:
    if (requested, chosen) not in _reported:
        _reported.add((requested, chosen))
        logger.info("renderer %r: drawing with the %s splatter (%s)", requested, chosen, why)


def make_splatter(renderer: str, *, gl_context=None, settings: RenderSettings | None = None,
                  shader_target: str = "330") -> tuple[GLSplatter, str]:
    """(splatter, "gl" or "cpu") for a `BackendSettings.renderer` choice; SettingsError for "cpu" without numba."""
    if renderer == "cpu":
        if not cpu_splatter_available():
            raise SettingsError(f"renderer='cpu' needs numba, the cpu extra: {CPU_EXTRA_HINT}")
        from .cpu_splatter import CPUSplatter

        _report(renderer, "cpu", "asked for")
        return CPUSplatter(settings=settings), "cpu"
    splatter = GLSplatter(gl_context, settings=settings, shader_target=shader_target)
    if renderer == "gl":
        _report(renderer, "gl", "asked for")
        return splatter, "gl"
    gl_renderer = str(splatter.ctx.info.get("GL_RENDERER", ""))
    if not is_software_renderer(gl_renderer):
        _report(renderer, "gl", f"GL renderer {gl_renderer!r}")
        return splatter, "gl"
    if not cpu_splatter_available():
        _report(renderer, "gl", f"software GL {gl_renderer!r}, but numba is not installed: {CPU_EXTRA_HINT}")
        return splatter, "gl"
    from .cpu_splatter import CPUSplatter

    splatter.release()
    _report(renderer, "cpu", f"the GL renderer {gl_renderer!r} is a software rasterizer")
    return CPUSplatter(settings=settings), "cpu"


__all__ = ["CPU_EXTRA_HINT", "SOFTWARE_RASTERIZERS", "cpu_splatter_available", "is_software_renderer",
           "make_splatter"]
