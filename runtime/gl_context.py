"""Offscreen OpenGL context for the runtime: picks a backend per platform and explains what to install if none works."""

from __future__ import annotations

import os
import sys

import moderngl

from gaussiantalker.sdk.errors import RenderError

# The shaders are GLSL 3.30 core; macOS (OpenGL 4.1 core) and GLES 3.0 devices offer the same feature set.
REQUIRED_GL_VERSION = 330

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


def describe_context(ctx: moderngl.Context) -> str:
    """One line naming the GL renderer and version, for logs and benchmark reports."""
    info = ctx.info
    return f"{info.get('GL_RENDERER', '?')} / OpenGL {info.get('GL_VERSION', ctx.version_code)}"
