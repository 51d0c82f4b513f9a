"""Shader variants (docs/shaders.md): every program the splatter builds, in every target of SHADER_TARGETS (GLSL
3.30 core, 4.10 core, ES 3.00), is text glslangValidator accepts, exactly as the runtime compiles it (#defines
included); the sources use only what OpenGL 4.1 core, OpenGL ES 3.0 and WebGL 2 share; and every variant draws
the same pixels, bit for bit, through points, quads, the background and the render-scale pass.

glslangValidator (Debian package glslang-tools) is optional on a developer's machine: without it the validator
tests skip, except where the environment variable CI is set (non-empty): .ci/install installs it there, so its
absence fails.

`python tests/test_shader_variants.py` prints the render-target accuracy table of docs/shaders.md (float16 and
uint8 frames drawn with the GLSL ES shaders against float32 frames).
"""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from ci_tools import need
from test_splatter import BACKGROUND, make_camera, random_scene

from gaussiantalker.runtime.splat import programs as programs_module
from gaussiantalker.runtime.splat.gl import GLSplatter
from gaussiantalker.runtime.splat.gl_context import (
    _TARGET_GL_VERSION,
    check_shader_target,
    gles_render_target,
    shader_target_problem,
)
from gaussiantalker.runtime.splat.programs import PROGRAMS, program_sources, shader_defines, with_defines
from gaussiantalker.sdk.errors import RenderError
from gaussiantalker.sdk.render_settings import RenderSettings
from gaussiantalker.shaders import (
    SHADER_TARGETS,
    SOURCE_VERSION_LINE,
    available_shaders,
    load_shader,
    shader_header,
    shader_source,
    shader_variant,
)

VALIDATOR = "glslangValidator"
STAGES = ("vert", "frag")  # glslangValidator picks the stage from the file suffix, the profile from #version
VALIDATOR_TIMEOUT_S = 60


@pytest.fixture(scope="module")
def validator() -> str:
    """Path of glslangValidator; skip without it, fail without it where CI is set (CI installs it)."""
    path = shutil.which(VALIDATOR)
    need(None if path else f"{VALIDATOR} is not on PATH (Debian: apt-get install glslang-tools)", ".ci/install")
    return path


def validate(validator: str, *paths: Path, link: bool = False) -> subprocess.CompletedProcess:
    """Run glslangValidator on `paths` (-l: link them into one program); the result keeps its output."""
    command = [validator, *(["-l"] if link else []), *map(str, paths)]
    return subprocess.run(command, capture_output=True, text=True, timeout=VALIDATOR_TIMEOUT_S, check=False)


def write_program(folder: Path, program: str, target: str) -> list[Path]:
    """Write `program`'s sources for `target`, as the runtime compiles them, to `<program>_<target>.vert/.frag`."""
    paths = []
    for stage, source in zip(STAGES, program_sources(program, target), strict=True):
        path = folder / f"{program}_{target}.{stage}"
        path.write_text(source, encoding="utf-8")
        paths.append(path)
    return paths


def failure_report(result: subprocess.CompletedProcess, paths: list[Path]) -> str:
    """The validator's command, exit code and output, then the numbered text it was given."""
    listings = "\n".join(f"--- {path.name}\n" + "\n".join(f"{i + 1:4d} {line}" for i, line in
                                                      enumerate(path.read_text().split("\n"))) for path in paths)
    return (f"{' '.join(result.args)} exited with {result.returncode}:\n{result.stdout}{result.stderr}\n"
            f"{listings}")


# -- glslangValidator: what the runtime compiles, every program, stage and target ----------------------------


@pytest.mark.parametrize("target", SHADER_TARGETS)
@pytest.mark.parametrize("stage", STAGES)
@pytest.mark.parametrize("program", list(PROGRAMS))
def test_validator_accepts_every_variant(validator, tmp_path, program, stage, target):
    path = write_program(tmp_path, program, target)[STAGES.index(stage)]
    result = validate(validator, path)
    assert result.returncode == 0, failure_report(result, [path])


@pytest.mark.parametrize("target", SHADER_TARGETS)
@pytest.mark.parametrize("program", list(PROGRAMS))
def test_validator_links_every_program(validator, tmp_path, program, target):
    """The two stages of each program agree on their interface (outputs to inputs, shared uniforms)."""
    paths = write_program(tmp_path, program, target)
    result = validate(validator, *paths, link=True)
    assert result.returncode == 0, failure_report(result, paths)


def test_the_validator_can_fail(validator, tmp_path):
    """The checks above are not vacuous: glslangValidator takes its profile from the #version line, so an ES
    fragment shader without a default float precision, or an int-to-float conversion that only desktop GLSL has,
    fails in the ES variant (and the conversion passes in the 330 one)."""
    fragment = program_sources("points", "300es")[1]
    no_precision = tmp_path / "no_precision.frag"
    no_precision.write_text("\n".join(line for line in fragment.split("\n") if not line.startswith("precision")))
    assert validate(validator, no_precision).returncode != 0
    for target, accepted in (("330", True), ("300es", False)):
        path = tmp_path / f"conversion_{target}.frag"
        path.write_text(program_sources("points", target)[1].replace(
            "void main() {\n", "void main() {\n    float probe = 1;\n"))
        assert (validate(validator, path).returncode == 0) == accepted, target


@pytest.mark.parametrize("target", SHADER_TARGETS)
def test_driver_logs_number_the_lines_of_the_source(validator, tmp_path, target):
    """After the header and the #defines, `#line 2` restores the numbering of the file in shaders/, so an error
    at line k of shaders/splat.frag is reported at line k in every variant."""
    lines = load_shader("splat.frag").split("\n")
    at = lines.index("void main() {") + 1
    broken = "\n".join([*lines[:at], "    undeclared_probe;", *lines[at:]])  # source line at + 1
    path = tmp_path / f"broken_{target}.frag"
    path.write_text(with_defines(shader_variant(broken, target), shader_defines()))
    result = validate(validator, path)
    assert result.returncode != 0
    assert f"ERROR: 0:{at + 1}: 'undeclared_probe'" in result.stdout, result.stdout


# -- the variants: one source, only the header differs -------------------------------------------------------


@pytest.mark.parametrize("target", SHADER_TARGETS)
@pytest.mark.parametrize("name", available_shaders())
def test_variants_differ_from_the_source_only_in_their_header(name, target):
    source = load_shader(name)
    variant = shader_source(name, target)
    header = shader_header(target)
    assert source.split("\n")[0] == SOURCE_VERSION_LINE
    assert variant.split("\n")[: len(header)] == header
    assert variant.split("\n")[len(header):] == source.split("\n")[1:]
    assert header[0].startswith("#version ") and all(line.startswith("precision highp ") for line in header[1:])


def test_headers_of_the_targets():
    assert shader_header("330") == ["#version 330 core"]
    assert shader_header("410") == ["#version 410 core"]
    assert shader_header("300es") == ["#version 300 es", "precision highp float;", "precision highp int;",
                                      "precision highp sampler2D;"]
    for call in (lambda: shader_source("splat.vert", "450"), lambda: shader_variant("#version 450\n", "330")):
        with pytest.raises(ValueError, match="330"):
            call()


@pytest.mark.parametrize("target", SHADER_TARGETS)
def test_defines_follow_the_whole_header(target):
    """The #defines go after the version line and the precision statements, then `#line 2` and the body."""
    vertex, _ = program_sources("points", target)
    lines = vertex.split("\n")
    header = shader_header(target)
    assert lines[: len(header)] == header
    defines = {**shader_defines(), **PROGRAMS["points"].defines}
    after = lines[len(header): len(header) + len(defines) + 1]
    assert after == [f"#define {name} {value}" for name, value in defines.items()] + ["#line 2"]
    assert lines[len(header) + len(defines) + 1:] == load_shader("splat.vert").split("\n")[1:]


# GLSL ES 3.00 literals (section 4.1.3-4.1.4): decimal integers, and floats with a fraction and/or an exponent, no
# suffix (WebGL 2 compilers vary on `f`), no hex floats, no `inf`/`nan`.
_ES_INT = re.compile(r"[0-9]+")
_ES_FLOAT = re.compile(r"(?:[0-9]+\.[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?|[0-9]+[eE][+-]?[0-9]+")


def test_every_define_is_a_glsl_es_literal():
    """Every #define value the runtime injects parses as a GLSL ES 3.00 float (or, for the per-program switches
    used by `#if`, integer) literal, and as float32 to the value sdk.numerics gives."""
    for name, value in shader_defines().items():
        assert _ES_FLOAT.fullmatch(value), (name, value)
        assert np.isfinite(np.float32(float(value))), (name, value)
    for spec in PROGRAMS.values():
        for name, value in spec.defines.items():
            assert _ES_INT.fullmatch(value), (name, value)
    for bad in (float("inf"), float("nan"), 1e39):
        with pytest.raises(ValueError, match="no GLSL float32 literal"):
            programs_module._glsl_float(bad)


# -- the feature subset: what OpenGL 4.1 core, OpenGL ES 3.0 and WebGL 2 share ----------------------------------

# Features outside that subset, each with a pattern that finds it in GLSL with comments removed (docs/shaders.md
# says why the splatter needs none of them).
FORBIDDEN_FEATURES = {
    "#extension directive": r"^[ \t]*#[ \t]*extension\b",
    "compute shader": r"\blocal_size_[xyz]\b|\bgl_(?:GlobalInvocationID|LocalInvocationID|LocalInvocationIndex|"
                      r"WorkGroupID|NumWorkGroups|WorkGroupSize)\b|\bshared\b|\b\w*[bB]arrier\s*\(",
    "buffer block (SSBO)": r"\bbuffer\b|\bstd430\b",
    "image load/store": r"\bimage(?:Load|Store|Atomic\w*|Size|Samples)\b|\b[iu]?image(?:1D|2D|3D|Cube|Buffer)\w*\b"
                        r"|\b(?:coherent|volatile|restrict|readonly|writeonly)\b",
    "atomic counter": r"\batomic_uint\b|\batomicCounter\w*\b",
    "geometry shader": r"\bEmit(?:Stream)?Vertex\b|\bEnd(?:Stream)?Primitive\b|\bgl_in\b|\bgl_PrimitiveIDIn\b|"
                       r"\bgl_(?:Layer|ViewportIndex|InvocationID)\b|\bmax_vertices\b|\b(?:triangle|line)_strip\b",
    "tessellation shader": r"\bgl_(?:TessLevelOuter|TessLevelInner|TessCoord|PatchVerticesIn)\b|\bpatch\b",
}
_SHADER_FILE_SUFFIXES = (".vert", ".frag", ".glsl")  # never .comp, .geom, .tesc, .tese


def without_comments(source: str) -> str:
    """GLSL with // and /* */ comments blanked (prose may say "buffer"), newlines kept for line numbers."""
    source = re.sub(r"/\*.*?\*/", lambda m: re.sub(r"[^\n]", " ", m.group()), source, flags=re.S)
    return re.sub(r"//[^\n]*", "", source)


def forbidden_features(source: str) -> list[str]:
    """'feature (line k: text)' for every use of a FORBIDDEN_FEATURES feature in `source`."""
    code = without_comments(source)
    found = []
    for feature, pattern in FORBIDDEN_FEATURES.items():
        for match in re.finditer(pattern, code, flags=re.M):
            line = code.count("\n", 0, match.start()) + 1
            found.append(f"{feature} (line {line}: {match.group().strip()!r})")
    return found


@pytest.mark.parametrize("name", available_shaders())
def test_sources_use_only_the_shared_feature_set(name):
    assert name.endswith(_SHADER_FILE_SUFFIXES)
    assert forbidden_features(load_shader(name)) == []


@pytest.mark.parametrize("target", SHADER_TARGETS)
def test_compiled_programs_use_only_the_shared_feature_set(target):
    for program in PROGRAMS:
        for source in program_sources(program, target):
            assert forbidden_features(source) == [], (program, target)


@pytest.mark.parametrize(("snippet", "feature"), [
    ("#extension GL_ARB_shader_storage_buffer_object : require\n", "#extension directive"),
    ("  #  extension GL_OES_standard_derivatives : enable\n", "#extension directive"),
    ("layout(local_size_x = 64) in;\n", "compute shader"),
    ("uvec3 id = gl_GlobalInvocationID;\n", "compute shader"),
    ("layout(std430, binding = 0) buffer Splats { vec4 data[]; };\n", "buffer block (SSBO)"),
    ("vec4 c = imageLoad(u_image, ivec2(0));\n", "image load/store"),
    ("imageStore(u_image, ivec2(0), vec4(1.0));\n", "image load/store"),
    ("layout(rgba32f) uniform image2D u_image;\n", "image load/store"),
    ("layout(binding = 0) uniform atomic_uint u_count;\n", "atomic counter"),
    ("layout(points) in;\nlayout(triangle_strip, max_vertices = 4) out;\n", "geometry shader"),
    ("EmitVertex();\nEndPrimitive();\n", "geometry shader"),
    ("vec4 p = gl_in[0].gl_Position;\n", "geometry shader"),
    ("gl_TessLevelOuter[0] = 1.0;\n", "tessellation shader"),
])
def test_the_feature_check_can_fail(snippet, feature):
    source = load_shader("splat.vert").replace("void main() {", snippet + "void main() {", 1)
    assert any(found.startswith(feature) for found in forbidden_features(source)), forbidden_features(source)


def test_comments_may_name_forbidden_features():
    assert forbidden_features("// no SSBO: a vertex buffer, no imageStore\n/* EmitVertex\n buffer */\n") == []


# -- every target runs here and draws the same pixels ------------------------------------------------------------
# Mesa's desktop OpenGL 4.5 context compiles GLSL ES 3.00 (ARB_ES3_compatibility), so all three variants run on
# the test machine. They differ only in their header, and highp is float32 as desktop float is, so every frame
# must be identical bit for bit, for every primitive path and render target.


@pytest.fixture(scope="module")
def context_splatter():
    """A splatter whose context the variant splatters share (no GL context is a failure: the install has one)."""
    instance = GLSplatter()
    yield instance
    instance.release()


def draw_with_targets(ctx, scene, camera, *, output: str = "float", **kwargs) -> dict[str, np.ndarray]:
    """The frame of `scene` drawn by a fresh splatter per shader target (`kwargs` go to GLSplatter)."""
    frames = {}
    for target in SHADER_TARGETS:
        splatter = GLSplatter(ctx, shader_target=target, **kwargs)
        try:
            frames[target] = splatter.render(*scene, camera, BACKGROUND, output=output)
        finally:
            splatter.release()
    return frames


@pytest.mark.parametrize("point_sprites", [True, False], ids=["points", "quads"])
def test_every_target_draws_identical_frames(context_splatter, point_sprites):
    camera = make_camera(40, 30)
    scene = random_scene(21, n=80)
    probe = GLSplatter(context_splatter.ctx, shader_target="300es", point_sprites=point_sprites)
    try:
        runs = probe.prepare(*scene, camera).runs
    finally:
        probe.release()
    assert runs and all(as_quads != point_sprites for _, _, as_quads in runs)  # the path under test draws all
    for output in ("float", "rgba_float"):  # with and without the background pass
        frames = draw_with_targets(context_splatter.ctx, scene, camera, output=output, point_sprites=point_sprites)
        assert np.abs(frames["330"][..., :3] - np.asarray(BACKGROUND, np.float32)).max() > 0.1  # something drawn
        for target in SHADER_TARGETS:
            np.testing.assert_array_equal(frames[target], frames["330"], err_msg=f"{target} {output}")


@pytest.mark.parametrize("render_target", ["float32", "float16", "uint8"])
def test_every_target_draws_identical_frames_per_render_target_and_scale(context_splatter, render_target):
    """The render-scale pass (upscale program, a sampled texture) too, in each framebuffer precision."""
    settings = RenderSettings(render_scale=0.5, render_target=render_target)
    frames = draw_with_targets(context_splatter.ctx, random_scene(22, n=80), make_camera(40, 30),
                               settings=settings)
    for target in SHADER_TARGETS:
        np.testing.assert_array_equal(frames[target], frames["330"], err_msg=target)


def test_the_es_variant_is_compiled_as_glsl_es(context_splatter, monkeypatch):
    """Not vacuous: the driver really compiles the "300es" text as GLSL ES (an implicit int-to-float conversion,
    legal in GLSL 3.30, fails there), and its log numbers the line of the file in shaders/."""
    source = load_shader("splat.frag")
    at = source.split("\n").index("void main() {") + 1
    probed = source.replace("void main() {\n", "void main() {\n    float probe = 1;\n", 1)
    monkeypatch.setattr(programs_module, "load_shader", lambda name: probed if name == "splat.frag" else
                        load_shader(name))
    GLSplatter(context_splatter.ctx, shader_target="330").release()
    with pytest.raises(RenderError, match=r"target 300es") as raised:
        GLSplatter(context_splatter.ctx, shader_target="300es")
    assert f"0:{at + 1}(" in str(raised.value)


# -- choosing a target -----------------------------------------------------------------------------------------


def test_unknown_target_is_a_render_error_listing_the_targets(context_splatter):
    with pytest.raises(RenderError, match=r"unknown shader target '450'; allowed: '330', '410', '300es'"):
        GLSplatter(context_splatter.ctx, shader_target="450")


def test_targets_a_context_can_compile():
    def context(version: int, *extensions: str) -> SimpleNamespace:
        return SimpleNamespace(version_code=version, extensions=set(extensions))

    assert all(shader_target_problem(context(460), target) is None for target in SHADER_TARGETS)
    assert set(_TARGET_GL_VERSION) == set(SHADER_TARGETS)  # every target has its context requirement
    assert shader_target_problem(context(460), "450") == "unknown shader target '450'; allowed: '330', '410', '300es'"
    assert shader_target_problem(context(330), "330") is None
    assert "needs OpenGL 4.1; this context is OpenGL 3.3" in shader_target_problem(context(330), "410")
    assert shader_target_problem(context(410), "410") is None
    assert "ARB_ES3_compatibility" in shader_target_problem(context(410), "300es")  # macOS: no GLSL ES
    assert shader_target_problem(context(410, "GL_ARB_ES3_compatibility"), "300es") is None
    assert shader_target_problem(context(430), "300es") is None
    with pytest.raises(RenderError, match="4.1"):
        check_shader_target(context(330), "410")


def test_gles_render_target_rule():
    """RGBA16F where EXT_color_buffer_half_float (or EXT_color_buffer_float) makes it renderable, else RGBA8."""
    assert gles_render_target(["GL_EXT_color_buffer_half_float"]) == "float16"
    assert gles_render_target({"EXT_color_buffer_float"}) == "float16"  # WebGL names have no GL_ prefix
    assert gles_render_target(["GL_OES_texture_float", "GL_EXT_float_blend"]) == "uint8"
    assert gles_render_target([]) == "uint8"


# -- render-target accuracy with the GLSL ES shaders (docs/shaders.md) -------------------------------------------

ACCURACY_SEEDS = (0, 1, 2)
ACCURACY_SIZE = (128, 96)
ACCURACY_GAUSSIANS = 1000
# Floors well below what was measured (docs/shaders.md: float16 >= 52.3 dB, uint8 >= 42.7 dB 8-bit PSNR).
MIN_PSNR_DB = {"float16": 50.0, "uint8": 40.0}


def psnr_db(frame: np.ndarray, reference: np.ndarray, peak: float) -> float:
    """10 log10(peak^2 / MSE) over every pixel and channel (inf where identical)."""
    mse = float(np.mean((frame.astype(np.float64) - reference.astype(np.float64)) ** 2))
    return float("inf") if mse == 0 else 10.0 * np.log10(peak * peak / mse)


def render_target_accuracy(ctx, shader_target: str = "300es") -> dict[str, list[dict]]:
    """Per reduced render target, per seed: 8-bit PSNR, float PSNR (clipped to 0..1), the largest 8-bit error and
    the share of changed 8-bit values, of frames drawn with `shader_target` against float32 frames."""
    def splatter(render_target: str) -> GLSplatter:
        return GLSplatter(ctx, shader_target=shader_target, settings=RenderSettings(render_target=render_target))

    splatters = {name: splatter(name) for name in ("float32", "float16", "uint8")}
    camera = make_camera(*ACCURACY_SIZE)
    results: dict[str, list[dict]] = {"float16": [], "uint8": []}
    try:
        for seed in ACCURACY_SEEDS:
            scene = random_scene(seed, n=ACCURACY_GAUSSIANS, scale=0.05)
            frames = {name: (s.render(*scene, camera, BACKGROUND), s.render(*scene, camera, BACKGROUND,
                                                                            output="float"))
                      for name, s in splatters.items()}
            reference8, reference = frames["float32"]
            for name, rows in results.items():
                frame8, frame = frames[name]
                error8 = np.abs(frame8.astype(int) - reference8.astype(int))
                rows.append({"seed": seed, "psnr8_db": psnr_db(frame8, reference8, 255.0),
                             "psnr_float_db": psnr_db(np.clip(frame, 0, 1), np.clip(reference, 0, 1), 1.0),
                             "max_err8": int(error8.max()), "changed8": float(np.mean(error8 > 0))})
    finally:
        for s in splatters.values():
            s.release()
    return results


def test_reduced_render_targets_accuracy_with_es_shaders(context_splatter):
    results = render_target_accuracy(context_splatter.ctx)
    for name, rows in results.items():
        assert min(row["psnr8_db"] for row in rows) >= MIN_PSNR_DB[name], (name, rows)
    assert all(h["psnr8_db"] > u["psnr8_db"] + 5 for h, u in zip(results["float16"], results["uint8"], strict=True))


def accuracy_table(results: dict[str, list[dict]]) -> str:
    """Markdown rows of docs/shaders.md: per render target, min/mean over the seeds."""
    lines = ["| render target | 8-bit PSNR min / mean | float PSNR min / mean | max 8-bit error "
             "| 8-bit values changed |", "|---|---|---|---|---|"]
    for name, rows in results.items():
        psnr8 = [row["psnr8_db"] for row in rows]
        psnr_float = [row["psnr_float_db"] for row in rows]
        lines.append(f"| {name} | {min(psnr8):.1f} / {np.mean(psnr8):.1f} dB | {min(psnr_float):.1f} / "
                     f"{np.mean(psnr_float):.1f} dB | {max(row['max_err8'] for row in rows)} levels | "
                     f"{100 * np.mean([row['changed8'] for row in rows]):.0f} % |")
    return "\n".join(lines)


if __name__ == "__main__":
    main_splatter = GLSplatter()
    try:
        print(f"{len(ACCURACY_SEEDS)} scenes of {ACCURACY_GAUSSIANS} Gaussians, {ACCURACY_SIZE[0]}x{ACCURACY_SIZE[1]}, "
              "GLSL ES 3.00 shaders, against float32 frames:")
        print(accuracy_table(render_target_accuracy(main_splatter.ctx)))
    finally:
        main_splatter.release()
