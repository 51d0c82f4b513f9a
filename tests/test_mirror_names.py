"""One name per contract step: the GLSL shaders and the torch reference (exporter/model/splat_math.py) mirror each
other.

The GLSL function definitions are parsed out of shaders/*.vert and shaders/*.frag (`<type> <name>(<params>) {` at
the start of a line; `main` is skipped), and checked against the torch module (docs/numerics.md, "Mirror names"):

(a) every GLSL function that is not on the non-contract allow-list
    (`gaussiantalker.runtime.splat.gl.NON_CONTRACT_GLSL_FUNCTIONS`) has a public torch function of the same name
    whose parameters are the GLSL parameters, same names in the same order, followed by the uniforms the GLSL
    function reads (itself or through the functions it calls), mapped as `UNIFORM_ARGUMENTS` says and in
    `UNIFORM_ORDER`; the torch docstring names the GLSL twin and its file, and the GLSL comment block above the
    definition names the torch twin;
(b) every public torch function (splat_math.__all__) either names a GLSL twin, which must exist under the same
    name in the file it names, or says "No GLSL twin" (and then no GLSL function has its name).

The allow-listed GLSL functions must say "Not a contract step" and must not exist in splat_math. The #defines the
shaders get are split into contract constants (sdk.numerics) and the renderer's own settings, and each splat
shader's header names the ones it uses under the right group. `test_the_mirror_check_can_fail` feeds the checks
broken sources (a renamed function, swapped parameters, a missing comment) and expects each to be reported.
"""

from __future__ import annotations

import inspect
import re
from importlib import resources
from types import ModuleType

import pytest

from gaussiantalker.exporter.model import splat_math
from gaussiantalker.runtime.splat import gl as splatter
from gaussiantalker.runtime.splat import programs
from gaussiantalker.sdk import numerics

# GLSL has no 6-vector: the packed world covariance is two vec3 there and one [N, 6] tensor in torch.
PARAMETER_RENAMES = {("cov_a", "cov_b"): "cov3d"}
# Uniform (and swizzle component) -> torch argument; an unswizzled use takes every listed argument.
UNIFORM_ARGUMENTS = {
    "u_R": ("R",),
    "u_t": ("t",),
    "u_intrinsics": ("fx", "fy", "cx", "cy"),
    "u_fov_limits": ("limits",),
    "u_image_size": ("width", "height"),
}
UNIFORM_ORDER = ("R", "t", "fx", "fy", "cx", "cy", "limits", "width", "height")
_COMPONENT = {"x": 0, "y": 1, "z": 2, "w": 3}

_DEFINITION = re.compile(r"^(?P<type>\w+)[ \t]+(?P<name>\w+)[ \t]*\((?P<params>[^)]*)\)\s*\{", re.MULTILINE)
_UNIFORM_USE = re.compile(r"\b(?P<uniform>u_\w+)\b(?:\.(?P<swizzle>[xyzw]+)\b)?")
_CALL = re.compile(r"\b(\w+)\s*\(")
_TWIN_CLAIM = re.compile(r"GLSL twin: `(?P<name>\w+)` in shaders/(?P<file>\w+\.(?:vert|frag))")


class GlslFunction:
    """One GLSL function definition: its file, name, parameter names, body and the comment block above it."""

    def __init__(self, file: str, source: str, match: re.Match) -> None:
        self.file = file
        self.name = match["name"]
        params = [p.strip() for p in match["params"].split(",") if p.strip() and p.strip() != "void"]
        self.params = [p.split()[-1] for p in params]
        self.body = source[match.end() - 1 : _matching_brace(source, match.end() - 1) + 1]
        lines = source[: match.start()].split("\n")[:-1]
        comment = []
        while lines and lines[-1].lstrip().startswith("//"):
            comment.insert(0, lines.pop().strip())
        self.comment = "\n".join(comment)


def _matching_brace(source: str, open_at: int) -> int:
    """Index of the '}' closing the '{' at open_at."""
    depth = 0
    for i in range(open_at, len(source)):
        depth += {"{": 1, "}": -1}.get(source[i], 0)
        if depth == 0:
            return i
    raise AssertionError(f"unbalanced braces after offset {open_at}")


def shader_sources() -> dict[str, str]:
    """Every shipped .vert and .frag shader, by file name."""
    files = resources.files("gaussiantalker.shaders").iterdir()
    return {f.name: f.read_text(encoding="utf-8") for f in files if f.name.endswith((".vert", ".frag"))}


def parse_functions(sources: dict[str, str]) -> dict[str, GlslFunction]:
    """Every GLSL function except main, by name (a name defined twice, in any files, is an error)."""
    functions: dict[str, GlslFunction] = {}
    for file, source in sorted(sources.items()):
        for match in _DEFINITION.finditer(source):
            function = GlslFunction(file, source, match)
            if function.name == "main":
                continue
            assert function.name not in functions, f"GLSL function {function.name} is defined twice"
            functions[function.name] = function
    return functions


def uniform_arguments(function: GlslFunction, functions: dict[str, GlslFunction], seen=()) -> set[str]:
    """Torch arguments standing for the uniforms `function` reads, itself or through the functions it calls."""
    arguments: set[str] = set()
    for use in _UNIFORM_USE.finditer(function.body):
        names = UNIFORM_ARGUMENTS[use["uniform"]]
        if use["swizzle"] and len(names) > 1:
            names = tuple(names[_COMPONENT[c]] for c in use["swizzle"])
        arguments.update(names)
    for called in _CALL.findall(function.body):
        if called in functions and called != function.name and called not in seen:
            arguments |= uniform_arguments(functions[called], functions, (*seen, function.name))
    return arguments


def expected_torch_parameters(function: GlslFunction, functions: dict[str, GlslFunction]) -> list[str]:
    """The GLSL parameters (packed covariance mapped), then the uniforms' arguments in UNIFORM_ORDER."""
    params = list(function.params)
    for pair, torch_name in PARAMETER_RENAMES.items():
        for i in range(len(params) - 1):
            if tuple(params[i : i + 2]) == pair:
                params[i : i + 2] = [torch_name]
                break
    uniforms = uniform_arguments(function, functions)
    return params + [name for name in UNIFORM_ORDER if name in uniforms]


def mirror_problems(sources: dict[str, str], module: ModuleType, allow_list: tuple[str, ...]) -> list[str]:
    """Every way the GLSL sources and the torch module fail to mirror each other (empty: they mirror)."""
    problems = []
    functions = parse_functions(sources)
    public = set(module.__all__)
    for name in allow_list:
        function = functions.get(name)
        if function is None:
            problems.append(f"allow-listed {name} is not a GLSL function")
            continue
        if "Not a contract step" not in function.comment:
            problems.append(f"{function.file}: allow-listed {name} has no 'Not a contract step' comment")
        if hasattr(module, name):
            problems.append(f"allow-listed GLSL function {name} also exists in splat_math")
    for name, function in functions.items():
        if name in allow_list:
            continue
        where = f"{function.file}: {name}"
        if f"Torch twin: `{name}`" not in function.comment:
            problems.append(f"{where}: the comment above it does not name its torch twin `{name}`")
        twin = getattr(module, name, None)
        if twin is None or name not in public:
            problems.append(f"{where} has no public torch twin of the same name in splat_math")
            continue
        parameters = list(inspect.signature(twin).parameters)
        expected = expected_torch_parameters(function, functions)
        if parameters != expected:
            problems.append(f"{where}: torch parameters {parameters}, GLSL gives {expected}")
        if f"GLSL twin: `{name}` in shaders/{function.file}" not in (twin.__doc__ or ""):
            problems.append(f"{where}: the torch docstring does not say 'GLSL twin: `{name}` in "
                            f"shaders/{function.file}'")
    for name in module.__all__:
        doc = getattr(module, name).__doc__ or ""
        claims = list(_TWIN_CLAIM.finditer(doc))
        if not claims:
            if "No GLSL twin" not in doc:
                problems.append(f"torch {name}: docstring says neither 'GLSL twin: ...' nor 'No GLSL twin'")
            elif name in functions:
                problems.append(f"torch {name} says 'No GLSL twin' but {functions[name].file} defines {name}")
            continue
        for claim in claims:
            function = functions.get(claim["name"])
            if claim["name"] != name:
                problems.append(f"torch {name} claims a GLSL twin of another name, {claim['name']}")
            elif function is None or function.file != claim["file"]:
                problems.append(f"torch {name} claims GLSL twin {claim['name']} in shaders/{claim['file']}, "
                                "which does not define it")
    return problems


def test_glsl_and_torch_mirror_each_other():
    sources = shader_sources()
    assert {"splat.vert", "splat.frag", "background.vert", "background.frag"} <= set(sources)
    assert all(re.search(r"^void\s+main\s*\(", source, re.MULTILINE) for source in sources.values())
    functions = parse_functions(sources)
    contract = set(functions) - set(splatter.NON_CONTRACT_GLSL_FUNCTIONS)
    # The parser really sees the functions (a broken regex would make every check vacuous).
    assert {"world_to_camera", "camera_to_pixel", "covariance_2d", "extent_radius", "splat_alpha"} <= contract
    assert len(contract) >= 15
    assert mirror_problems(sources, splat_math, splatter.NON_CONTRACT_GLSL_FUNCTIONS) == []


def test_twin_parameters_spelled_out():
    """A few twins written out by hand, so the uniform mapping itself is checked too."""
    functions = parse_functions(shader_sources())
    assert expected_torch_parameters(functions["world_to_camera"], functions) == ["mean", "R", "t"]
    assert expected_torch_parameters(functions["camera_to_pixel"], functions) == ["p_cam", "fx", "fy", "cx", "cy"]
    assert expected_torch_parameters(functions["covariance_2d_determinant"], functions) == [
        "p_cam", "cov3d", "cov2d", "R", "fx", "fy", "limits"]
    assert expected_torch_parameters(functions["splat_alpha"], functions) == ["d", "shape", "opacity"]


@pytest.mark.parametrize(
    ("file", "old", "new", "expected"),
    [
        ("splat.vert", "vec3 covariance_2d(", "vec3 covariance_two_d(", "covariance_two_d has no public torch twin"),
        ("splat.vert", "return vec3(dot(m0, s0) + LOW_PASS_PX2", "vec3 unused = covariance_2d(p_cam, cov_a, cov_b);\n"
         "    return vec3(dot(m0, s0) + LOW_PASS_PX2", None),  # a recursive call must not hang or break the walk
        ("splat.frag", "float splat_alpha(vec2 d, vec3 shape, float opacity)",
         "float splat_alpha(vec3 shape, vec2 d, float opacity)", "splat_alpha: torch parameters"),
        ("splat.vert", "// Torch twin: `radius_of` (exporter/model/splat_math.py).\n", "",
         "does not name its torch twin `radius_of`"),
        ("splat.vert", "float cov2d_scale(vec3 cov2d) {\n    return",
         "float cov2d_scale(vec3 cov2d) {\n    float unused = u_t.x;\n    return",
         "cov2d_scale: torch parameters ['cov2d'], GLSL gives ['cov2d', 't']"),
        ("splat.vert", "// Not a contract step (rasterisation only): drops", "// Drops",
         "allow-listed cull has no 'Not a contract step' comment"),
        ("splat.frag", "vec3 splat_color(vec3 rgb)", "vec3 keep_mask(vec3 rgb)", "says 'No GLSL twin' but"),
    ],
)
def test_the_mirror_check_can_fail(file, old, new, expected):
    sources = shader_sources()
    assert old in sources[file]
    sources[file] = sources[file].replace(old, new, 1)
    problems = mirror_problems(sources, splat_math, splatter.NON_CONTRACT_GLSL_FUNCTIONS)
    if expected is None:
        assert problems == []
    else:
        assert any(expected in problem for problem in problems), problems


def test_shader_defines_split_contract_from_renderer():
    """Contract #defines come from sdk.numerics; the renderer's own are its rasterisation settings; the headers
    of the splat shaders name the ones each uses, under the right group."""
    contract = set(programs.CONTRACT_DEFINES)
    renderer = set(programs.renderer_defines()) | {"SPLAT_POINTS"}  # SPLAT_POINTS is set per program
    assert not contract & renderer
    assert all(hasattr(numerics, name) for name in contract)
    assert not any(hasattr(numerics, name) for name in renderer)
    defines = programs.shader_defines()
    assert set(defines) == contract | set(programs.renderer_defines())
    for name in contract:
        assert float(defines[name]) == pytest.approx(float(getattr(numerics, name)), rel=1e-15)
    for file in ("splat.vert", "splat.frag"):
        source = shader_sources()[file]
        header, _, code = source.partition("\n\n")
        header = header.partition("#defines")[2]  # the define groups, not the prose above them
        code = "\n".join(line.split("//")[0] for line in code.split("\n"))
        used = set(re.findall(r"\b[A-Z][A-Z0-9_]+\b", code)) & (contract | renderer)
        contract_part, marker, renderer_part = header.partition("renderer's own")
        assert marker, f"{file}: the header has no 'renderer's own' group"
        named_contract = set(re.findall(r"\b[A-Z][A-Z0-9_]+\b", contract_part)) & (contract | renderer)
        named_renderer = set(re.findall(r"\b[A-Z][A-Z0-9_]+\b", renderer_part)) & (contract | renderer)
        assert named_contract == used & contract, file
        assert named_renderer == used & renderer, file
