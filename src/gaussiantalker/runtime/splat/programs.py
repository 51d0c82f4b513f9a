"""The splatter's GL programs: GLSL sources assembled from shaders/ with the runtime's #defines, compiled per
shader target, and their camera uniforms set.

Shader variants
---------------
Every program (`PROGRAMS`) is compiled from the one source of each shader in shaders/, in the variant that
`GLSplatter(shader_target=...)` picks: GLSL 3.30 core (the default), 4.10 core or ES 3.00. Variants differ only in
their header, so all draw the same pixels; `program_sources` gives the exact text compiled, which CI validates
(docs/shaders.md).
"""

from __future__ import annotations

from typing import NamedTuple

import moderngl
import numpy as np

from gaussiantalker.sdk import numerics
from gaussiantalker.sdk.camera import Camera
from gaussiantalker.sdk.errors import RenderError
from gaussiantalker.shaders import load_shader, shader_variant

# A Gaussian's pixel box is widened by this much (pixels) so that float rounding in the vertex shader never
# drops a pixel the fragment shader would accept. 1/64 px is several float32 ulps even at 16384 px and adds an
# extra row/column with probability ~1/32 per side.
QUAD_SLACK_PX = 1.0 / 64.0

# Relative (and absolute) widening of the alpha >= ALPHA_MIN ellipse used to shrink the pixel box, far above
# the float32 error of exp/log/the conic (~1e-6), so the shrink never removes a pixel that passes.
BOX_SLACK_REL = 1e-3

# Largest finite float32: a #define beyond it is not a float32 (GLSL ES highp float is float32 at most).
_FLOAT32_MAX = float(np.finfo(np.float32).max)


def _glsl_float(value: float) -> str:
    """A float literal valid in GLSL 3.30/4.10 core and GLSL ES 3.00 that parses to float32(value) (repr is the
    shortest round-tripping decimal, e.g. `0.3`, `1e+30`, `9.5367431640625e-07`; never `inf` or `nan`)."""
    value = float(value)
    if not abs(value) <= _FLOAT32_MAX:
        raise ValueError(f"{value!r} has no GLSL float32 literal")
    text = repr(value)
    return text if any(ch in text for ch in ".eE") else text + ".0"


# Contract constants the shaders get as #defines: read from gaussiantalker.sdk.numerics under the same names, so
# GLSL and the torch reference use one value each (docs/numerics.md).
CONTRACT_DEFINES = (
    "LOW_PASS_PX2",
    "EXTENT_SIGMAS",
    "ALPHA_MAX",
    "ALPHA_MIN",
    "FINITE_LIMIT",
    "COLOR_LIMIT",
    "DET_MIN_RELATIVE",
    "COV2D_HUGE_PX2",
    "TRANSMITTANCE_MIN",
)


def renderer_defines() -> dict[str, float]:
    """The GL renderer's own rasterisation settings injected as #defines (not contract maths, no torch twin).

    SPLAT_POINTS (1: point sprites, 0: instanced quads) is the renderer's too; it differs per program and is added
    where each program is built.
    """
    return {"QUAD_SLACK_PX": QUAD_SLACK_PX, "BOX_SLACK_REL": BOX_SLACK_REL}


def shader_defines() -> dict[str, str]:
    """Every #define injected into the shaders (never re-typed in GLSL): the contract constants from
    sdk.numerics (`CONTRACT_DEFINES`), then the renderer's own settings (`renderer_defines`)."""
    contract = {name: getattr(numerics, name) for name in CONTRACT_DEFINES}
    return {name: _glsl_float(value) for name, value in {**contract, **renderer_defines()}.items()}


def with_defines(source: str, defines: dict[str, str]) -> str:
    """Insert `#define NAME VALUE` lines after a shader variant's header (its #version line, which GLSL requires
    first, and the precision statements of GLSL ES), then `#line 2`: the body of every variant is its source from
    line 2 on, so a driver log's line numbers are those of the file in shaders/ (docs/shaders.md)."""
    lines = source.split("\n")
    if not lines[0].startswith("#version"):
        raise RenderError("shader source must start with a #version line")
    end = 1
    while end < len(lines) and lines[end].startswith("precision "):
        end += 1
    block = [f"#define {name} {value}" for name, value in defines.items()]
    return "\n".join([*lines[:end], *block, "#line 2", *lines[end:]])


class ProgramSpec(NamedTuple):
    """One GL program the splatter builds: its vertex and fragment shader files and its own #defines."""

    vertex: str
    fragment: str
    defines: dict[str, str]  # added to shader_defines()


# Every program GLSplatter compiles: point and quad splats (one source, SPLAT_POINTS set per program), the
# background pass, the render-scale pass and the early stop's saturation mark (full-screen triangles without a
# vertex buffer).
PROGRAMS = {
    "points": ProgramSpec("splat.vert", "splat.frag", {"SPLAT_POINTS": "1"}),
    "quads": ProgramSpec("splat.vert", "splat.frag", {"SPLAT_POINTS": "0"}),
    "background": ProgramSpec("background.vert", "background.frag", {}),
    "upscale": ProgramSpec("background.vert", "upscale.frag", {}),
    "saturation": ProgramSpec("background.vert", "saturation.frag", {}),
}


def program_sources(program: str, target: str = "330") -> tuple[str, str]:
    """(vertex, fragment) GLSL of `program` (a PROGRAMS key) for shader `target`, exactly as GLSplatter compiles
    it: each shader's variant with shader_defines() and the program's own #defines (what CI validates)."""
    spec = PROGRAMS[program]
    defines = {**shader_defines(), **spec.defines}
    vertex, fragment = (with_defines(shader_variant(load_shader(name), target), defines)
                        for name in (spec.vertex, spec.fragment))
    return vertex, fragment


def compile_program(ctx: moderngl.Context, name: str, target: str) -> moderngl.Program:
    """Compile and link program `name` of PROGRAMS in shader `target` (`program_sources`); RenderError with the
    driver log."""
    vertex, fragment = program_sources(name, target)
    try:
        return ctx.program(vertex_shader=vertex, fragment_shader=fragment)
    except moderngl.Error as exc:
        spec = PROGRAMS[name]
        raise RenderError(f"shader {spec.vertex}/{spec.fragment} ({name}, target {target}) failed "
                          f"to compile or link: {exc}") from exc


def build_programs(ctx: moderngl.Context, target: str) -> dict[str, moderngl.Program]:
    """Every program of PROGRAMS compiled for shader `target`; on a failure the ones already built are released."""
    programs: dict[str, moderngl.Program] = {}
    try:
        for name in PROGRAMS:
            programs[name] = compile_program(ctx, name, target)
    except Exception:
        for program in programs.values():
            program.release()
        raise
    return programs


def set_camera_uniforms(programs: dict[str, moderngl.Program], camera: Camera) -> None:
    """Camera uniforms of both splat programs (GLSL mat3 is column-major, hence R^T's bytes)."""
    rotation = np.ascontiguousarray(camera.R.T, dtype=np.float32).tobytes()
    for key in ("points", "quads"):
        program = programs[key]
        program["u_R"].write(rotation)
        program["u_t"].value = tuple(float(v) for v in camera.t)
        program["u_intrinsics"].value = (camera.fx, camera.fy, camera.cx, camera.cy)
        program["u_image_size"].value = (float(camera.width), float(camera.height))
        program["u_fov_limits"].value = camera.fov_clamp_limits()


__all__ = ["BOX_SLACK_REL", "CONTRACT_DEFINES", "PROGRAMS", "QUAD_SLACK_PX", "ProgramSpec", "build_programs",
           "compile_program", "program_sources", "renderer_defines", "set_camera_uniforms", "shader_defines",
           "with_defines"]
