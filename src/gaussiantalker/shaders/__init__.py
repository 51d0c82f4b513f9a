"""GLSL sources of the runtime's splatter, shipped as package data (`*.vert`, `*.frag`, `*.glsl`).

Each shader has one source, written as GLSL 3.30 core; `shader_variant` makes the text for every target in
`SHADER_TARGETS` by swapping its first line (`#version 330 core`) for that target's header (version line, and for
GLSL ES the precision statements). Nothing else differs between variants (docs/shaders.md).
"""

from __future__ import annotations

from importlib import resources

_SUFFIXES = (".vert", ".frag", ".glsl")

# The targets every shader is generated for: GLSL 3.30 core (OpenGL 3.3), 4.10 core (OpenGL 4.1, macOS), and
# GLSL ES 3.00 (OpenGL ES 3.0 and WebGL 2).
SHADER_TARGETS = ("330", "410", "300es")

# The first line of every source in this package: the source is the "330" variant itself.
SOURCE_VERSION_LINE = "#version 330 core"

# The header that replaces SOURCE_VERSION_LINE in each target's variant. GLSL ES has no default float precision in
# fragment shaders and only lowp samplers by default, so the ES header asks for highp everywhere: the same
# float32 maths and sampling as desktop GL.
_HEADERS = {
    "330": ("#version 330 core",),
    "410": ("#version 410 core",),
    "300es": ("#version 300 es", "precision highp float;", "precision highp int;", "precision highp sampler2D;"),
}


def available_shaders() -> list[str]:
    """Names of the shader files shipped in this package, sorted (used in error messages)."""
    files = resources.files(__name__).iterdir()
    return sorted(f.name for f in files if f.name.endswith(_SUFFIXES))


def load_shader(name: str) -> str:
    """Source text of shader `name` (e.g. "splat.vert"), read through importlib.resources so zips work too."""
    if not name.endswith(_SUFFIXES) or "/" in name or "\\" in name:
        raise FileNotFoundError(f"unknown shader {name!r}; available: {', '.join(available_shaders())}")
    resource = resources.files(__name__).joinpath(name)
    if not resource.is_file():
        raise FileNotFoundError(f"unknown shader {name!r}; available: {', '.join(available_shaders())}")
    return resource.read_text(encoding="utf-8")


def check_target(target: str) -> str:
    """`target` itself if it is one of SHADER_TARGETS, else ValueError listing them (a typo fails early)."""
    if target not in SHADER_TARGETS:
        raise ValueError(f"unknown shader target {target!r}; allowed: {', '.join(map(repr, SHADER_TARGETS))}")
    return target


def shader_header(target: str) -> list[str]:
    """The lines that open every shader of `target`'s variant: the #version line, then any precision statements."""
    return list(_HEADERS[check_target(target)])


def shader_variant(source: str, target: str) -> str:
    """`source` (a shader of this package, first line SOURCE_VERSION_LINE) as GLSL for `target`: only its first
    line changes, to the target's header, so line k >= 2 of the source is the body's (k - 1)-th line."""
    first, newline, body = source.partition("\n")
    if first.strip() != SOURCE_VERSION_LINE:
        raise ValueError(f"a shader source must start with {SOURCE_VERSION_LINE!r}, got {first[:40]!r}")
    return "\n".join(shader_header(target)) + newline + body


def shader_source(name: str, target: str = "330") -> str:
    """Shader `name` (e.g. "splat.vert") as GLSL for `target` (one of SHADER_TARGETS), without #defines."""
    return shader_variant(load_shader(name), target)
