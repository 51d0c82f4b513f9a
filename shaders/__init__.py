"""GLSL sources of the runtime's splatter, shipped as package data (`*.vert`, `*.frag`, `*.glsl`)."""

from __future__ import annotations

from importlib import resources

_SUFFIXES = (".vert", ".frag", ".glsl")


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
