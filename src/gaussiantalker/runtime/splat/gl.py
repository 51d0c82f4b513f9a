"""OpenGL EWA splatter of the torch-free runtime: depth-sorted Gaussians -> [H, W, 3] frame.

It follows the numerics contract of docs/numerics.md. The per-Gaussian maths lives in shaders/splat.vert
(`world_to_camera`, `camera_to_pixel`, `clamped_ratios`, `sigma_matrix`, `covariance_2d`, `cov2d_scale`,
`reliable`, `rounding_products`, `determinant_and_noise`, `covariance_2d_determinant`, `reliability_fade`,
`conic_from_cov2d`, `alpha_shape`, `radius_of`, `extent_radius`, `extent_power_bound`, `screen_bounded`) and
shaders/splat.frag (`splat_color`, `splat_alpha`); each of these GLSL functions has a torch twin of the same name
and arguments in exporter/model/splat_math.py. The shaders' other functions only decide where to rasterise
(`NON_CONTRACT_GLSL_FUNCTIONS`). Numpy does the rest: the near-plane and non-finite-input culling with the depth
order (runtime/splat/depth_sort.py: `view_depth`, `depth_order`), and the final 8-bit conversion (`to_uint8`).

Primitives
----------
Each Gaussian is drawn as a box of whole pixels (shaders/splat.vert, `pixel_box`) that holds every pixel that
can pass the exact per-pixel tests of the fragment shader; the rasteriser only decides which fragments are
tried, never which pixels a Gaussian touches. On llvmpipe a point sprite costs far less than two triangles, so
Gaussians whose box provably fits the largest point size are drawn as points, the others as instanced quads, in
sorted runs (a frame whose runs would cost more than points save is drawn as quads only). Both give identical pixels.

A point is a square whose side is the box's longer side. llvmpipe shades 4x4 pixel blocks (and runs the shader
on the 4x2 halves of a block that have a covered pixel), so along the box's shorter side the square is placed to
touch the fewest blocks (`point_start`), usually starting on a multiple of 4 pixels, instead of being centred.
The oriented quads, axis-aligned quads and tighter fragment-shader early-outs tried instead were all slower on
llvmpipe (measured: docs/numerics.md, "Rasterisation in the GL renderer").

The GL programs themselves (GLSL sources with the runtime's #defines, the shader-target variants, compiling,
uniforms) are assembled by runtime/splat/programs.py (docs/shaders.md).

Compositing and the contract's early termination
------------------------------------------------
Gaussians are drawn front to back into an RGBA32F framebuffer cleared to 0 with the premultiplied "under"
blend (src factor ONE_MINUS_DST_ALPHA, dst factor ONE, for colour and alpha alike), each fragment writing
(rgb * alpha, alpha). The framebuffer then holds (C, 1 - T), and a last full-screen pass of (background, 1)
under the same blend turns it into (C + T * background, 1), the contract's final colour.

Fixed-function blending cannot read T, so it cannot stop a pixel "before a Gaussian that would take T below
1e-4" as 3DGS does: every later Gaussian is still added, weighted by the (tiny) remaining T. The difference from
the 3DGS rule at a pixel that would have stopped with transmittance T_stop is
    sum_{later i} T_i * alpha_i * (c_i - background)  (the later weights sum to at most T_stop),
so it is bounded by T_stop * max|c_i - background|. The stop happens before a Gaussian with
T_stop * (1 - alpha) < 1e-4 and alpha <= 0.99, hence T_stop < 1e-4 / 0.01 = 0.01: the worst case is
0.01 * max colour difference, and typically (T_stop ~ 1e-4..1e-3) it is ~1e-4..1e-3, below half an 8-bit
level. tests/test_splatter.py measures it against a literal numpy implementation of the rule.

The experimental `RenderSettings.early_stop` (off by default; slower on llvmpipe) skips pixels whose T is already
below TRANSMITTANCE_MIN after given fractions of the sorted Gaussians, with a depth mark (`_draw_segments`;
docs/numerics.md, "Early stop of saturated pixels").
"""

from __future__ import annotations

import logging
import time
from collections import OrderedDict

import moderngl
import numpy as np

from gaussiantalker.sdk import numerics
from gaussiantalker.sdk.camera import Camera
from gaussiantalker.sdk.errors import RenderError
from gaussiantalker.sdk.image import straight_rgba, to_uint8
from gaussiantalker.sdk.render_settings import RENDER_TARGETS, RenderSettings
from gaussiantalker.shaders import check_target

from .common import ALPHA_OUTPUTS, FLOATS_PER_SPLAT, FRAME_OUTPUTS, STAGES, PreparedSplats, background_rgb, sorted_rows
from .depth_sort import DepthSorter
from .gl_context import check_shader_target, create_context
from .programs import QUAD_SLACK_PX, build_programs, set_camera_uniforms

logger = logging.getLogger("gaussiantalker.runtime")

# GLSL functions in shaders/ that are rasterisation, not contract maths: they choose which fragments are tried
# (the pixel box, where a point sprite goes, the primitive of a culled Gaussian) and never what a pixel gets, so
# they have no torch twin in exporter/model/splat_math.py. Every other GLSL function except main has one
# (tests/test_mirror_names.py).
NON_CONTRACT_GLSL_FUNCTIONS = ("pixel_box", "block_cost", "point_start", "cull")

# Point sprites and quads are drawn in sorted runs, one draw call each. One extra run costs about as much as drawing
# this many Gaussians as quads instead of points (measured: docs/numerics.md, "Rasterisation in the GL renderer"), so
# a frame is drawn in mixed runs only while runs * RUN_COST_IN_SPLATS < number of point Gaussians, else all quads.
RUN_COST_IN_SPLATS = 12

# A Gaussian is drawn as a point when this factor times its conservative radius bound still fits (float margin).
POINT_BOUND_SAFETY = 1.01

# Framebuffers kept alive for this many recent resolutions.
MAX_CACHED_TARGETS = 4

_STRIDE = FLOATS_PER_SPLAT * 4
_ATTRIBUTES = (("in_mean", 3, 0), ("in_cov_a", 3, 3), ("in_cov_b", 3, 6), ("in_rgba", 4, 9))  # name, size, offset


# -- numpy side of the contract ------------------------------------------------------------------------------


def extent_radius_bound(packed: np.ndarray, camera: Camera) -> np.ndarray:
    """An upper bound of each Gaussian's extent radius in px (cheap, float64), to pick point or quad. # [N]

    lambda_max(J W S W^T J^T) <= |J|_F^2 * rho(S) and rho(S) <= |S|_F for any symmetric S, with J formed from
    the clamped x/z, y/z exactly as in `covariance_2d`; the low-pass term adds LOW_PASS_PX2.
    """
    p = packed[:, 0:3].astype(np.float64) @ camera.R.T + camera.t  # [N, 3] camera space
    x_lo, x_hi, y_lo, y_hi = camera.fov_clamp_limits()
    with np.errstate(all="ignore"):
        xz = np.clip(p[:, 0] / p[:, 2], x_lo, x_hi)
        yz = np.clip(p[:, 1] / p[:, 2], y_lo, y_hi)
        jac_sq = (camera.fx**2 * (1.0 + xz * xz) + camera.fy**2 * (1.0 + yz * yz)) / (p[:, 2] * p[:, 2])
        cov = packed[:, 3:9].astype(np.float64)
        cov_frobenius = np.sqrt((cov * cov) @ np.array([1.0, 2.0, 2.0, 1.0, 2.0, 1.0]))
        bound = numerics.EXTENT_SIGMAS * np.sqrt(jac_sq * cov_frobenius + numerics.LOW_PASS_PX2)
    return np.where(np.isfinite(bound), bound, np.inf)


def draw_runs(needs_quad: np.ndarray) -> list[tuple[int, int, bool]]:
    """Split the sorted Gaussians into maximal (start, stop, as_quads) runs of one primitive kind."""
    n = len(needs_quad)
    if n == 0:
        return []
    edges = np.concatenate(([0], np.flatnonzero(needs_quad[1:] != needs_quad[:-1]) + 1, [n]))
    return [(int(a), int(b), bool(needs_quad[a])) for a, b in zip(edges[:-1], edges[1:], strict=True)]


def early_stop_segments(runs: list[tuple[int, int, bool]], fractions: tuple[float, ...]
                        ) -> list[list[tuple[int, int, bool]]]:
    """The draw runs cut into segments at each fraction of the sorted Gaussians (RenderSettings.early_stop);
    empty segments are dropped, so () or a frame too small to cut gives one segment, the runs themselves."""
    n = runs[-1][1] if runs else 0
    cuts = sorted({round(f * n) for f in fractions} - {0, n})
    if not cuts:
        return [runs]
    segments: list[list[tuple[int, int, bool]]] = []
    bounds = [0, *cuts, n]
    for lo, hi in zip(bounds[:-1], bounds[1:], strict=True):
        segments.append([(max(a, lo), min(b, hi), q) for a, b, q in runs if a < hi and b > lo])
    return segments


# -- GL side -------------------------------------------------------------------------------------------------


class _Target:
    """A framebuffer of one resolution and precision (moderngl dtype f4, f2 or f1) plus its read-back scratch."""

    def __init__(self, ctx: moderngl.Context, width: int, height: int, dtype: str = "f4") -> None:
        self.texture = ctx.texture((width, height), 4, dtype=dtype)
        self.texture.filter = (moderngl.LINEAR, moderngl.LINEAR)  # sampled by the render-scale pass
        self.texture.repeat_x = self.texture.repeat_y = False
        self.dtype = dtype
        try:
            self.fbo = ctx.framebuffer(color_attachments=[self.texture])
        except Exception:
            self.texture.release()
            raise
        self.scratch = np.empty((height, width, 3), dtype=np.float32)
        self._early_stop: tuple | None = None  # (depth renderbuffer, splat fbo, mark fbo), see early_stop_fbos

    def early_stop_fbos(self, ctx: moderngl.Context) -> tuple[moderngl.Framebuffer, moderngl.Framebuffer]:
        """(splat, mark) framebuffers sharing one depth buffer, made on first use: the splats blend into the colour
        texture, depth-tested but never writing depth; the saturation mark writes only depth, while it samples the
        colour texture (which is why it is a framebuffer of its own: no texture is read while attached)."""
        if self._early_stop is None:
            depth = ctx.depth_renderbuffer(self.texture.size)
            splat = ctx.framebuffer(color_attachments=[self.texture], depth_attachment=depth)
            splat.depth_mask = False
            mark = ctx.framebuffer(depth_attachment=depth)
            mark.depth_mask = True
            self._early_stop = (depth, splat, mark)
        return self._early_stop[1], self._early_stop[2]

    def release(self) -> None:
        """Free the GL objects."""
        if self._early_stop is not None:
            for obj in reversed(self._early_stop):
                obj.release()
            self._early_stop = None
        self.fbo.release()
        self.texture.release()


class GLSplatter:
    """Renders Gaussians with OpenGL into an offscreen float framebuffer; reusable across frames and cameras.

    `point_sprites=False` draws every Gaussian as an instanced quad (same pixels, slower on llvmpipe).
    `settings` are the speed/accuracy knobs (render scale, framebuffer precision; docs/precision.md); the default
    is the contract's full-size float32 frame.
    `shader_target` picks the shader variant compiled (`SHADER_TARGETS`: "330", "410", "300es"; docs/shaders.md):
    they differ only in their header, so every target draws the same pixels; "300es" needs a context that accepts
    GLSL ES 3.00 (OpenGL 4.3+ or ARB_ES3_compatibility, as Mesa's has).
    On a shared context, render() leaves BLEND and PROGRAM_POINT_SIZE enabled, DEPTH_TEST and CULL_FACE disabled.
    """

    def __init__(self, ctx: moderngl.Context | None = None, *, point_sprites: bool = True,
                 settings: RenderSettings | None = None, shader_target: str = "330") -> None:
        if settings is not None and not isinstance(settings, RenderSettings):
            raise RenderError(f"settings must be a RenderSettings, got {type(settings).__name__}")
        try:
            check_target(shader_target)
        except ValueError as exc:
            raise RenderError(str(exc)) from None
        self.settings = settings or RenderSettings()
        if self.settings.alpha_min != numerics.ALPHA_MIN:
            logger.warning("alpha_min=%g applies on the CPU splatter only: the OpenGL splatter's shaders skip "
                           "contributions below the contract's 1/255 (docs/precision.md, \"Alpha cut-off\")",
                           self.settings.alpha_min)
        if self.settings.transmittance_min != numerics.TRANSMITTANCE_MIN:
            logger.warning("transmittance_min=%g applies on the CPU splatter only: the OpenGL splatter draws every "
                           "contribution as before (docs/numerics.md, \"Transmittance stop\")",
                           self.settings.transmittance_min)
        self.shader_target = shader_target
        self._sorter = DepthSorter(self.settings.sort_interval, self.settings.sort_key_bits)
        self._owns_ctx = ctx is None
        self.ctx = create_context() if ctx is None else ctx
        self.last_timings: dict[str, float] = dict.fromkeys(STAGES, 0.0)
        self._targets: OrderedDict[tuple[int, int], _Target] = OrderedDict()
        self._buffer: moderngl.Buffer | None = None
        self._point_vao: moderngl.VertexArray | None = None
        self._capacity = 0
        self._quad_start: int | None = None  # first instance the quad VAO is bound at
        self._programs: dict[str, moderngl.Program] = {}
        self._quad_vao: moderngl.VertexArray | None = None
        self._background_vao: moderngl.VertexArray | None = None
        self._upscale_vao: moderngl.VertexArray | None = None
        self._saturation_vao: moderngl.VertexArray | None = None
        try:
            with self.ctx:
                check_shader_target(self.ctx, shader_target)
                self._build_programs()
                self.max_point_size = self._max_point_size() if point_sprites else 0.0
        except Exception:
            self.release()
            raise

    # -- set-up ---------------------------------------------------------------------------------------------

    def _build_programs(self) -> None:
        """Every program of PROGRAMS (runtime/splat/programs.py); the quad, background and render-scale passes get
        attribute-less VAOs."""
        self._programs = build_programs(self.ctx, self.shader_target)
        self._quad_vao = self.ctx.vertex_array(self._programs["quads"], [])
        self._background_vao = self.ctx.vertex_array(self._programs["background"], [])
        self._upscale_vao = self.ctx.vertex_array(self._programs["upscale"], [])
        self._saturation_vao = self.ctx.vertex_array(self._programs["saturation"], [])

    def _max_point_size(self) -> float:
        """Largest point sprite side the driver draws (GL_POINT_SIZE_RANGE; 0 where unknown)."""
        sizes = self.ctx.info.get("GL_POINT_SIZE_RANGE") or (0.0, 0.0)
        return float(sizes[1])

    def _ensure_capacity(self, n: int) -> None:
        """Grow the per-Gaussian buffer (and rebuild its VAOs) only when a frame has more Gaussians than before."""
        if n <= self._capacity:
            return
        capacity = max(n, int(self._capacity * 1.5), 1024)
        self._release_buffer()
        self._buffer = self.ctx.buffer(reserve=capacity * _STRIDE)
        names = [name for name, _, _ in _ATTRIBUTES]
        self._point_vao = self.ctx.vertex_array(self._programs["points"], [(self._buffer, "3f 3f 3f 4f", *names)])
        self._capacity = capacity

    def _bind_quads_at(self, start: int) -> None:
        """Point the quad VAO's per-instance attributes at Gaussian `start` (no base-instance in GL 3.3)."""
        if self._quad_start == start:
            return
        program = self._programs["quads"]
        for name, size, offset in _ATTRIBUTES:
            self._quad_vao.bind(program[name].location, "f", self._buffer, f"{size}f",
                                offset=(start * FLOATS_PER_SPLAT + offset) * 4, stride=_STRIDE, divisor=1)
        self._quad_start = start

    def _target(self, width: int, height: int) -> _Target:
        """The framebuffer for this resolution in the settings' precision (a few recent ones are kept, least
        recently used dropped)."""
        key = (width, height, RENDER_TARGETS[self.settings.render_target])
        target = self._targets.pop(key, None)
        if target is None:
            target = _Target(self.ctx, *key)
            while len(self._targets) >= MAX_CACHED_TARGETS:
                self._targets.popitem(last=False)[1].release()
        self._targets[key] = target
        return target

    # -- per frame ------------------------------------------------------------------------------------------

    def plan_runs(self, rows: np.ndarray, camera: Camera) -> list[tuple[int, int, bool]]:
        """Draw runs for the sorted rows: points where the box surely fits a point sprite, quads elsewhere."""
        n = len(rows)
        if n == 0:
            return []
        if self.max_point_size <= 0:
            return [(0, n, True)]
        side = 2.0 * POINT_BOUND_SAFETY * extent_radius_bound(rows, camera) + 2.0 + 2.0 * QUAD_SLACK_PX
        needs_quad = side > self.max_point_size  # [n]
        runs = draw_runs(needs_quad)
        points = n - int(np.count_nonzero(needs_quad))
        return runs if len(runs) * RUN_COST_IN_SPLATS < points else [(0, n, True)]

    def _draw(self, target: _Target, runs: list[tuple[int, int, bool]],
              background: tuple[float, float, float] | None) -> None:
        """Clear to (0, 0, 0, 0), blend the sorted splats front to back, then the background under them (None:
        no background pass, the framebuffer keeps (C, 1 - T))."""
        ctx = self.ctx
        target.fbo.use()
        target.fbo.clear(0.0, 0.0, 0.0, 0.0)
        ctx.disable(moderngl.DEPTH_TEST | moderngl.CULL_FACE)
        ctx.enable(moderngl.BLEND | moderngl.PROGRAM_POINT_SIZE)
        ctx.blend_equation = moderngl.FUNC_ADD
        ctx.blend_func = moderngl.ONE_MINUS_DST_ALPHA, moderngl.ONE  # "under": dst += (1 - dst.a) * src
        segments = early_stop_segments(runs, self.settings.early_stop)
        if len(segments) > 1:
            self._draw_segments(target, segments)
        else:
            self._draw_runs(runs)
        if background is not None:
            self._programs["background"]["u_background"].value = background
            self._background_vao.render(moderngl.TRIANGLES, vertices=3)

    def _draw_runs(self, runs: list[tuple[int, int, bool]]) -> None:
        """Blend these runs of sorted splats into the framebuffer in use."""
        for start, stop, as_quads in runs:
            if as_quads:
                self._bind_quads_at(start)
                self._quad_vao.render(moderngl.TRIANGLE_STRIP, vertices=4, instances=stop - start)
            else:
                self._point_vao.render(moderngl.POINTS, vertices=stop - start, first=start)

    def _draw_segments(self, target: _Target, segments: list[list[tuple[int, int, bool]]]) -> None:
        """The early stop (RenderSettings.early_stop): the first segment of runs is drawn as usual; before each
        later one the mark pass writes depth (window depth 0.5, the splats' own, so the LESS test rejects them)
        where the transmittance so far is below TRANSMITTANCE_MIN, and the segment is blended depth-tested against
        it. Leaves the target's plain framebuffer in use and DEPTH_TEST disabled."""
        ctx = self.ctx
        splat_fbo, mark_fbo = target.early_stop_fbos(ctx)
        self._draw_runs(segments[0])  # nothing is marked yet: no depth test (it costs every fragment)
        mark_fbo.clear(depth=1.0)
        ctx.depth_func = "<"
        self._programs["saturation"]["u_accumulated"].value = 0
        ctx.enable(moderngl.DEPTH_TEST)  # also needed to write depth
        for segment in segments[1:]:
            mark_fbo.use()
            ctx.disable(moderngl.BLEND)
            target.texture.use(location=0)
            self._saturation_vao.render(moderngl.TRIANGLES, vertices=3)  # a mark stays: T only falls
            ctx.enable(moderngl.BLEND)
            splat_fbo.use()
            self._draw_runs(segment)
        ctx.disable(moderngl.DEPTH_TEST)
        target.fbo.use()

    def _upscale(self, source: _Target, target: _Target) -> None:
        """Sample `source` bilinearly at every pixel centre of the larger `target` (the render-scale pass)."""
        target.fbo.use()
        self.ctx.disable(moderngl.BLEND)
        source.texture.use(location=0)
        program = self._programs["upscale"]
        program["u_source"].value = 0
        program["u_output_size"].value = (float(target.texture.width), float(target.texture.height))
        self._upscale_vao.render(moderngl.TRIANGLES, vertices=3)
        self.ctx.enable(moderngl.BLEND)

    def prepare(self, means, cov3d, rgb, opacity, camera: Camera) -> PreparedSplats:
        """Validate, pack, depth-sort and plan draw runs (numpy only, no GL: safe on a worker thread)."""
        start = time.perf_counter()
        rows, camera, output_size = sorted_rows(self._sorter, self.settings, means, cov3d, rgb, opacity, camera)
        runs = self.plan_runs(rows, camera)
        return PreparedSplats(rows, runs, camera, time.perf_counter() - start, output_size)

    def draw(self, prepared: PreparedSplats, background, *, output: str = "uint8") -> np.ndarray:
        """Upload, splat and read back a prepared frame -> [H, W, 3] (see `render`)."""
        if self.ctx is None:
            raise RenderError("this GLSplatter has been released")
        if output not in FRAME_OUTPUTS:
            raise RenderError(f"output must be one of {', '.join(map(repr, FRAME_OUTPUTS))}, got {output!r}")
        background = background_rgb(background)
        timings = dict.fromkeys(STAGES, 0.0)
        timings["sort"] = prepared.seconds
        try:
            with self.ctx:  # make this context current (restored after): an app may hold several
                frame = self._render_sorted(prepared, background, timings, output)
        except moderngl.Error as exc:
            raise RenderError(f"OpenGL error while splatting {len(prepared.rows)} Gaussians: {exc}") from exc
        self.last_timings = timings
        return frame

    def render(self, means, cov3d, rgb, opacity, camera: Camera, background, *,
               output: str = "uint8") -> np.ndarray:
        """Splat N Gaussians (world means [N,3], covariances [N,6], rgb [N,3], opacity [N]) -> [H, W, 3] frame.

        output="float": float32 C + T * background; output="uint8": floor(clamp(v, 0, 1) * 255 + 0.5);
        output="rgba": uint8 [H, W, 4], straight colour C / (1 - T) and coverage 1 - T from the same draw (no
        background pass; `sdk.image.straight_rgba`), for overlays and videos with alpha; output="rgba_float":
        float32 [H, W, 4] premultiplied (C, 1 - T) as splatted, for compositing over any image (C + T * image).
        Rows are top first (+y down). Non-finite Gaussians and those with camera z < near are culled.
        """
        if self.ctx is None:
            raise RenderError("this GLSplatter has been released")
        return self.draw(self.prepare(means, cov3d, rgb, opacity, camera), background, output=output)

    def _render_sorted(self, prepared: PreparedSplats, background, timings: dict, output: str) -> np.ndarray:
        """Upload, draw (and upscale, at a render scale below 1) and read back one prepared frame."""
        rows, camera = prepared.rows, prepared.camera
        start = time.perf_counter()
        if len(rows):
            self._ensure_capacity(len(rows))
            self._buffer.write(rows)
        set_camera_uniforms(self._programs, camera)
        target = self._target(int(camera.width), int(camera.height))
        timings["upload"] = time.perf_counter() - start

        start = time.perf_counter()
        self._draw(target, prepared.runs, None if output in ALPHA_OUTPUTS else background)
        if prepared.output_size is not None:
            source, target = target, self._target(*prepared.output_size)
            self._upscale(source, target)
        self.ctx.finish()  # so that "draw" and "readback" timings are separate
        timings["draw"] = time.perf_counter() - start

        start = time.perf_counter()
        if output in ALPHA_OUTPUTS:
            premultiplied = np.empty((*target.scratch.shape[:2], 4), dtype=np.float32)
            target.fbo.read_into(premultiplied, components=4, dtype="f4")
            frame = premultiplied if output == "rgba_float" else straight_rgba(premultiplied, background)
        elif output == "uint8" and target.dtype == "f1":  # already 8-bit: GL rounds to nearest, as to_uint8 does
            frame = np.empty(target.scratch.shape, dtype=np.uint8)
            target.fbo.read_into(frame, components=3, dtype="f1")
        else:
            frame = target.scratch if output == "uint8" else np.empty_like(target.scratch)
            target.fbo.read_into(frame, components=3, dtype="f4")
            if output == "uint8":
                frame = to_uint8(frame)
        timings["readback"] = time.perf_counter() - start
        return frame

    # -- lifetime -------------------------------------------------------------------------------------------

    def _release_buffer(self) -> None:
        """Drop the per-Gaussian buffer and the point VAO reading it (the quad VAO is re-bound on use)."""
        for obj in (self._point_vao, self._buffer):
            if obj is not None:
                obj.release()
        self._point_vao, self._buffer, self._capacity, self._quad_start = None, None, 0, None

    def release(self) -> None:
        """Free every GL object (and the context if this splatter created it); safe to call twice."""
        if self.ctx is None:
            return
        with self.ctx:  # GL names belong to this context, which need not be the current one
            self._release_buffer()
            while self._targets:
                self._targets.popitem()[1].release()
            for obj in (self._quad_vao, self._background_vao, self._upscale_vao, self._saturation_vao,
                        *self._programs.values()):
                if obj is not None:
                    obj.release()
        self._quad_vao = self._background_vao = self._upscale_vao = self._saturation_vao = None
        self._programs = {}
        if self._owns_ctx:
            self.ctx.release()
        self.ctx = None

    def frames_at_once(self) -> int:
        """1: the GL context is bound to the thread that made it, so frames are drawn there one at a time."""
        return 1

    def begin_worker(self) -> None:
        """Nothing: a GL splatter draws on no worker thread."""

    def __enter__(self) -> GLSplatter:
        return self

    def __exit__(self, *exc_info) -> None:
        self.release()
