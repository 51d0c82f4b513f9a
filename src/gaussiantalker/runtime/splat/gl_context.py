"""Offscreen OpenGL context for the runtime: picks a backend per platform and explains what to install if none works."""

from __future__ import annotations

import os
import sys
from collections.abc import Iterable

import moderngl

from gaussiantalker.sdk.errors import RenderError
from gaussiantalker.shaders import check_target

# The shaders use only what OpenGL 3.3/4.1 core and OpenGL ES 3.0 / WebGL 2 share, in one variant per target
# (docs/shaders.md); the runtime's own context is desktop core, at least 3.3.
REQUIRED_GL_VERSION = 330

# What a desktop context needs to compile each shader target's variant (shaders.SHADER_TARGETS): the core version,
# and for GLSL ES 3.00 either OpenGL 4.3 (ES 3.0 compatibility is core there) or ARB_ES3_compatibility.
_TARGET_GL_VERSION = {"330": 330, "410": 410, "300es": 430}
_ES3_ON_DESKTOP = "GL_ARB_ES3_compatibility"

# Colour-buffer extensions of OpenGL ES 3.0 / WebGL 2 that make RGBA16F renderable and blendable (docs/shaders.md,
# "Render targets on OpenGL ES 3.0"); RGBA32F blending needs EXT_float_blend on top, so the rule never picks it.
_HALF_FLOAT_TARGET_EXTENSIONS = ("GL_EXT_color_buffer_half_float", "GL_EXT_color_buffer_float")

_INSTALL_HINTS = {
    "linux": "on Debian/Ubuntu install the Mesa EGL/GL drivers: apt-get install libegl1 libgl1-mesa-dri",
    "darwin": "macOS needs nothing extra (OpenGL 4.1 core is built in); check that the process may use the GPU",
    "win32": "install a GPU driver with OpenGL 3.3+ support (from the GPU vendor, not the Windows default)",
}


def _platform_key() -> str:
    """'darwin', 'win32' or 'linux' (every other Unix is treated like Linux: EGL or GLX through Mesa)."""
    if sys.platform == "darwin":
        return "darwin"
    if sys.platform.startswith(("win32", "cygwin")):
        return "win32"
    return "linux"


def default_backends() -> list[str | None]:
    """Backends to try in order (None = moderngl's platform default: GLX, CGL or WGL)."""
    if _platform_key() != "linux":
        return [None]
    if not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        return ["egl"]  # headless: GLX needs an X server, EGL does not
    return [None, "egl"]


def _try_backend(backend: str | None) -> moderngl.Context:
    """A standalone context on one backend with at least GL 3.3 core; raises on failure."""
    kwargs = {} if backend is None else {"backend": backend}
    ctx = moderngl.create_standalone_context(require=REQUIRED_GL_VERSION, **kwargs)
    if ctx.version_code < REQUIRED_GL_VERSION:
        version = ctx.version_code
        ctx.release()
        raise RuntimeError(f"OpenGL {version // 100}.{version % 100 // 10} is below the required 3.3 core")
    return ctx


def create_context(backend: str | None = None) -> moderngl.Context:
    """Create a standalone (offscreen) GL >= 3.3 core context; `backend` forces one (e.g. "egl")."""
    candidates = [backend] if backend is not None else default_backends()
    failures = []
    for candidate in candidates:
        try:
            return _try_backend(candidate)
        except Exception as exc:  # moderngl/glcontext raise several types (Exception, ValueError, OSError)
            failures.append(f"{candidate or 'default'}: {type(exc).__name__}: {exc}")
    hint = _INSTALL_HINTS[_platform_key()]
    raise RenderError(
        f"could not create an OpenGL {REQUIRED_GL_VERSION // 100}.{REQUIRED_GL_VERSION % 100 // 10} core context "
        f"({'; '.join(failures)}); {hint}"
    )


def shader_target_problem(ctx: moderngl.Context, target: str) -> str | None:
    """Why `ctx` cannot compile shader `target`'s variant (None when it can), so a splatter fails before compiling."""
    try:
        required = _TARGET_GL_VERSION[check_target(target)]
    except ValueError as exc:  # not a target at all: the one message every caller gives
        return str(exc)
    if ctx.version_code >= required:
        return None
    if target == "300es" and _ES3_ON_DESKTOP in ctx.extensions:
        return None
    version = f"OpenGL {ctx.version_code // 100}.{ctx.version_code % 100 // 10}"
    if target == "300es":
        return f"shader target '300es' needs OpenGL 4.3 or {_ES3_ON_DESKTOP}; this context is {version} without it"
    return f"shader target {target!r} needs OpenGL {required // 100}.{required % 100 // 10}; this context is {version}"


def check_shader_target(ctx: moderngl.Context, target: str) -> None:
    """RenderError naming what is missing when `ctx` cannot compile shader `target`'s variant."""
    problem = shader_target_problem(ctx, target)
    if problem is not None:
        raise RenderError(problem)


def gles_render_target(extensions: Iterable[str]) -> str:
    """The render target (sdk.render_settings.RENDER_TARGETS name) an OpenGL ES 3.0 / WebGL 2 port blends into,
    given its extension names (with or without the GL_ prefix): "float16" (RGBA16F) where a colour-buffer
    extension makes it renderable, else "uint8" (RGBA8, renderable everywhere). docs/shaders.md measures both."""
    names = {name if name.startswith("GL_") else f"GL_{name}" for name in extensions}
    return "float16" if names.intersection(_HALF_FLOAT_TARGET_EXTENSIONS) else "uint8"


def describe_context(ctx: moderngl.Context) -> str:
    """One line naming the GL renderer and version, for logs and benchmark reports."""
    info = ctx.info
    return f"{info.get('GL_RENDERER', '?')} / OpenGL {info.get('GL_VERSION', ctx.version_code)}"
