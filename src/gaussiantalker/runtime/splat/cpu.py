"""CPU tile splatter of the runtime: the numerics contract (docs/numerics.md) on the CPU cores, with numba.

Where the only OpenGL is a software rasterizer (Mesa's llvmpipe, softpipe, SwiftShader), most of a frame is that
rasterizer's generic triangle/point set-up, 4x4-block shading and RGBA32F blending. This splatter does what the
3DGS rasterizer does on GPUs instead, specialised to Gaussians:

1. `_project` (parallel over Gaussians): each depth-sorted Gaussian's contract steps in float32, step for step as
   the torch reference computes them (exporter/model/splat_math.py): world -> camera -> pixel, the FOV-clamped 2D
   covariance with the low-pass filter, the least-cancelling determinant, the conic's `alpha_shape`, the extent
   radius and the culling rules; plus the whole-pixel box where it can reach alpha >= ALPHA_MIN.
2. `_bin` (parallel over slices of the sorted list): the kept Gaussians binned to the 32x32 tiles their box
   overlaps, every tile's list kept front to back.
3. `_blend_tiles` (parallel over tiles): each tile's 1,024 pixels accumulated front to back in a small array that
   stays in L1 cache, with the contract's per-pixel extent test, alpha bound, 0.99 clamp and the T_MIN stop, in
   blocks of 4 x 2 pixels; a block whose pixels have all stopped is skipped, and a tile whose pixels have all
   stopped skips the rest of its list. The next Gaussians' rows are fetched ahead (`prefetch`: a tile's list is
   scattered over the parameter array, where no cache holds it). The per-block loop is written branch-free (float
   selects, a polynomial exp: `_exp`, no integer sums) so LLVM turns it into 8-wide vector code. Its counting twin
   (`splat_frame(..., counts)`) reports the work; docs/speed.md, "The blend against the machine".

Every per-pixel decision is made exactly as the contract says; the boxes and tiles only choose which pixels are
tried (a superset of those that can pass), as in the torch reference and the GL renderer.

It is hand-written because no library does it: the CPU 3DGS rasterizers that exist are the torch reference's kind
(tensor-batched, autograd) or CUDA kernels; numba's parallel loops give per-tile register/cache accumulation
without a C extension to build. Kernels are compiled once, at construction, and cached on disk (`cache_dir`), so
a warm start loads machine code instead of compiling; a render loop never compiles. The kernels release the GIL
(`nogil`), so a pipelined frame loop's other threads (the next frame's deformation and sort, the compositing, the
encoder: runtime/pipeline.py) run their Python while a frame is drawn instead of waiting for the draw to end.
Each parallel loop's threads claim their items as they finish (`jit.claim`: chunks of Gaussians, slices, tiles
longest list first, rows), not a fixed share each, so a thread whose core the pipeline's worker also needs takes
fewer and the others do not wait for it (docs/speed.md, "Work shared as it finishes").
"""

from __future__ import annotations

import logging
import math
import threading
import time
from pathlib import Path

import numpy as np

from gaussiantalker.sdk import numerics
from gaussiantalker.sdk.camera import Camera
from gaussiantalker.sdk.errors import RenderError
from gaussiantalker.sdk.image import straight_rgba
from gaussiantalker.sdk.render_settings import RenderSettings

from ..jit import cache_dir, claim, njit, numba, prange, prefetch
from . import cpu_sort
from .common import FRAME_OUTPUTS, STAGES, PreparedSplats, background_rgb, checked_gaussians, draw_camera, sorted_rows
from .depth_sort import DepthSorter

logger = logging.getLogger("gaussiantalker.runtime")

TILE = 32  # tile side in pixels: twice the 3DGS rasterizer's 16, fewer (Gaussian, tile) set-ups (docs/speed.md)
_TILE_PIXELS = TILE * TILE
# Pixels per vectorised step: a block of 4 columns x 2 rows, one 256-bit register of float32 (contiguous in the
# tile's accumulator: `_slot`). Runs of 8 columns of one row measured slower (more lanes outside the ellipse);
# docs/bench/renderers.md, "What made the blend faster".
_BLOCK = 8
_PAIRS = TILE // 2  # pixel-row pairs per tile
_LANE_COLUMN = np.array([0, 1, 2, 3, 0, 1, 2, 3], dtype=np.float32)  # a block lane's column and row in the block
_LANE_ROW = np.array([0, 0, 0, 0, 1, 1, 1, 1], dtype=np.float32)
_LANE_INDEX = np.arange(_BLOCK, dtype=np.float32)  # a lane's place in a run of 8 rows
_HI = np.uint64(TILE)  # offset of the last columns in the blend's `span`
_BLOCKS_PER_PAIR = TILE // 4
# Gaussians ahead in a tile's list whose parameter row the blend asks the CPU to fetch (`prefetch`) while it draws
# the current one: the rows of a tile's list lie far apart in `params`, so each first read missed the caches.
# docs/speed.md, "Rows fetched ahead".
_AHEAD = 2
_LIVE_EVERY = 8  # Gaussians between the checks of which blocks and row pairs of a tile still blend
# Offsets of the planes in a tile's accumulator (red at 0), unsigned like the pixel index added to them.
_G, _B, _T = (np.uint64(k * _TILE_PIXELS) for k in range(1, 4))
# Per kept Gaussian: u, v, A, k, q, opacity, radius, r, g, b, alpha level (see `_project`), and its pixel box x0, x1,
# y0, y1 as floats (exact: image sizes are far below 2^24), so the blend reads one Gaussian from one row; padded to
# 16 floats, and the array aligned (`_aligned_rows`), so that a row is one 64-byte cache line.
_PARAMS = 16
_CACHE_LINE = 64

_F = np.float32
_HALF = _F(numerics.PIXEL_CENTER_OFFSET)
_NEG_HALF = _F(-0.5)
_ZERO = _F(0.0)
_ONE = _F(1.0)
_LOW_PASS = _F(numerics.LOW_PASS_PX2)
_EXTENT = _F(numerics.EXTENT_SIGMAS)
_ALPHA_MAX = _F(numerics.ALPHA_MAX)
_ALPHA_MIN = _F(numerics.ALPHA_MIN)
_T_MIN = _F(numerics.TRANSMITTANCE_MIN)
_FINITE = _F(numerics.FINITE_LIMIT)
_COLOR = _F(numerics.COLOR_LIMIT)
_DET_REL = _F(numerics.DET_MIN_RELATIVE)
_HUGE = _F(numerics.COV2D_HUGE_PX2)
_NO_SPAN = _F(np.inf)  # span start of a row no pixel of which can reach ALPHA_MIN

# exp(x) = exp(x / 16)^16: x / 16 lies in [-0.625, 0] once x is clamped to [_EXP_LO, 0], where a degree-8 Taylor
# polynomial (Estrin form) is within 1.3e-7 relatively; four squarings follow. Only float multiply-adds and
# selects, so the per-pixel loop vectorises (numba's np.exp calls libm per lane, and a 2^n exponent split needs
# int64 -> float conversions that AVX2 lacks; both measured ~2x slower per frame). alpha >= 1/255 needs
# x >= ln(1/255) = -5.55, so below _EXP_LO the value only has to stay small. Max relative error against float64
# exp: docs/numerics.md.
_EXP_LO = _F(-10.0)
_EXP_SPLIT = _F(1.0 / 16.0)
_TAYLOR = tuple(_F(1.0 / math.factorial(k)) for k in range(9))  # 1/k!, k = 0..8
# exp(x) < 2.1e-9 for x < -20, far under 2^-25 (half the spacing of float32 just below 1): 1 - exp(x) rounds to 1.
_FADE_SKIP = _F(-20.0)
# Relative widening of the alpha >= ALPHA_MIN ellipse's box and extra pixels, so float32 rounding of a pixel's
# power can never pass a pixel outside the box (the box only selects pixels; each still tests itself).
_BOX_SLACK_REL = 1e-3
_BOX_SLACK_PX = 1.0


@njit(inline="always", cache=True, error_model="numpy", fastmath={"contract"})
def _exp(x):
    """exp(x) for float32 x <= 0 (x > 0 is taken as 0): branch-free, vectorisable (see the constants above)."""
    y = min(max(x, _EXP_LO), _ZERO) * _EXP_SPLIT
    y2 = y * y  # Estrin's scheme: the same polynomial in a shorter dependency chain than Horner's
    y4 = y2 * y2
    low = (_TAYLOR[0] + _TAYLOR[1] * y) + (_TAYLOR[2] + _TAYLOR[3] * y) * y2
    high = (_TAYLOR[4] + _TAYLOR[5] * y) + (_TAYLOR[6] + _TAYLOR[7] * y) * y2
    p = low + (high + _TAYLOR[8] * y4) * y4
    p = p * p
    p = p * p
    p = p * p
    return p * p


@njit(cache=True, error_model="numpy")
def exp_approx(x: np.ndarray) -> np.ndarray:
    """`_exp` over a float32 array (for tests and docs/numerics.md's error figure)."""
    out = np.empty_like(x)
    for i in range(x.shape[0]):
        out[i] = _exp(x[i])
    return out


@njit(inline="always", cache=True, error_model="numpy")
def _safe_div(x):
    """x where x > 0, else 1 (the torch reference's `_safe_divisor`: culled anyway, kept finite)."""
    return x if x > _ZERO else _ONE


@njit(inline="always", cache=True, error_model="numpy")
def _safe_sqrt(x):
    return np.sqrt(x) if x > _ZERO else _ZERO


@njit(inline="always", cache=True, error_model="numpy")
def _radius_of(a, b, c):
    mid = _HALF * (a + c)
    return _EXTENT * _safe_sqrt(mid + _safe_sqrt(mid * mid - (a * c - b * b)))


@njit(inline="always", cache=True, error_model="numpy")
def _times_sym(r0, r1, r2, xx, xy, xz, yy, yz, zz):
    """The row (r0, r1, r2) times the symmetric 3x3 [[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]]."""
    return r0 * xx + r1 * xy + r2 * xz, r0 * xy + r1 * yy + r2 * yz, r0 * xz + r1 * yz + r2 * zz


@njit(inline="always", cache=True, error_model="numpy")
def _bounded(x):
    return abs(x) < _FINITE  # NaN fails


@njit(inline="always", cache=True, error_model="numpy")
def _pixel_span(center, reach, size):
    """Pixel index range [lo, hi] (clipped) whose centres lie within `reach` (float64), widened by one pixel."""
    lo = math.ceil(center - reach - 0.5) - 1.0
    hi = math.floor(center + reach - 0.5) + 1.0
    ok = hi >= 0.0 and lo <= size - 1.0
    return int(min(max(lo, 0.0), size - 1.0)), int(min(max(hi, 0.0), size - 1.0)), ok


_PROJECT_CHUNK = 512  # sorted rows a thread of `_project` claims at a time (`claim`)
_ROWS_CHUNK = 16  # image rows a thread of `_over_background` claims at a time


@njit(parallel=True, nogil=True, cache=True, error_model="numpy")
def _project(rows, R, t, intr, limits, width, height, params, boxes, workers, alpha_min):
    """Contract steps of each sorted Gaussian (float32, as exporter/model/splat_math.py computes them):
    params [n, _PARAMS] as `_PARAMS` lists, boxes [n, 4] (x0, x1, y0, y1) of pixels that can reach `alpha_min`
    (the contract's ALPHA_MIN unless a setting raises it),
    x0 = -1 where the Gaussian is culled or misses the image. Rows are finite with z >= near (`depth_order`)."""
    fx, fy, cx, cy = intr[0], intr[1], intr[2], intr[3]
    x_min, x_max, y_min, y_max = limits[0], limits[1], limits[2], limits[3]
    n = rows.shape[0]
    taken = np.zeros(1, dtype=np.int64)  # chunks of _PROJECT_CHUNK rows claimed so far
    for _worker in prange(workers):
        while True:
            first = claim(taken) * _PROJECT_CHUNK
            if first >= n:
                break
            for i in range(first, min(first + _PROJECT_CHUNK, n)):
                boxes[i, 0] = -1
                mx, my, mz = rows[i, 0], rows[i, 1], rows[i, 2]
                # world_to_camera: (mean * R_row).sum() + t, summed left to right
                px = mx * R[0, 0] + my * R[0, 1] + mz * R[0, 2] + t[0]
                py = mx * R[1, 0] + my * R[1, 1] + mz * R[1, 2] + t[1]
                pz = mx * R[2, 0] + my * R[2, 1] + mz * R[2, 2] + t[2]
                z = _safe_div(pz)
                u = fx * px / z + cx  # camera_to_pixel
                v = fy * py / z + cy
                xz = min(max(px / z, x_min), x_max)  # clamped_ratios
                yz = min(max(py / z, y_min), y_max)
                s_xx, s_xy, s_xz = rows[i, 3], rows[i, 4], rows[i, 5]
                s_yy, s_yz, s_zz = rows[i, 6], rows[i, 7], rows[i, 8]
                # covariance_2d: m = J R, cov = (m Sigma) m^T + low-pass
                j00, j02 = fx / z, -fx * xz / z
                j11, j12 = fy / z, -fy * yz / z
                m00, m01 = j00 * R[0, 0] + j02 * R[2, 0], j00 * R[0, 1] + j02 * R[2, 1]
                m02 = j00 * R[0, 2] + j02 * R[2, 2]
                m10, m11 = j11 * R[1, 0] + j12 * R[2, 0], j11 * R[1, 1] + j12 * R[2, 1]
                m12 = j11 * R[1, 2] + j12 * R[2, 2]
                w00, w01, w02 = _times_sym(m00, m01, m02, s_xx, s_xy, s_xz, s_yy, s_yz, s_zz)
                w10, w11, w12 = _times_sym(m10, m11, m12, s_xx, s_xy, s_xz, s_yy, s_yz, s_zz)
                a = w00 * m00 + w01 * m01 + w02 * m02 + _LOW_PASS
                b = w00 * m10 + w01 * m11 + w02 * m12
                c = w10 * m10 + w11 * m11 + w12 * m12 + _LOW_PASS
                # covariance_2d_determinant: J's second row sheared orthogonal to the first
                g = _ONE / (_ONE + xz * xz)
                f = fy / z
                k0, k1, k2 = f * (-(xz * g) * yz), f * _ONE, f * (-yz * g)
                # row 0 is J R's own (m0, and m0 Sigma = w0); row 1 is the sheared one
                n10 = k0 * R[0, 0] + k1 * R[1, 0] + k2 * R[2, 0]
                n11 = k0 * R[0, 1] + k1 * R[1, 1] + k2 * R[2, 1]
                n12 = k0 * R[0, 2] + k1 * R[1, 2] + k2 * R[2, 2]
                e10, e11, e12 = _times_sym(n10, n11, n12, s_xx, s_xy, s_xz, s_yy, s_yz, s_zz)
                c00 = w00 * m00 + w01 * m01 + w02 * m02
                c01 = w00 * n10 + w01 * n11 + w02 * n12
                c11 = e10 * n10 + e11 * n11 + e12 * n12
                use_sheared = c11 + _LOW_PASS < c
                s = max(abs(a), abs(c))  # cov2d_scale
                an, bn, cn = a / s, b / s, c / s
                s00, s01, s11 = c00 / s, c01 / s, c11 / s
                low = _LOW_PASS / s
                # reliable(det, rounding_products): the entries' magnitudes are the same quadratic forms over |rows| and
                # |Sigma|; row 0 is the same in both forms, the plain form's entries carry the low-pass
                a_xx, a_xy, a_xz, a_yy, a_yz, a_zz = abs(s_xx), abs(s_xy), abs(s_xz), abs(s_yy), abs(s_yz), abs(s_zz)
                r00, r01, r02 = abs(m00), abs(m01), abs(m02)
                t00, t01, t02 = _times_sym(r00, r01, r02, a_xx, a_xy, a_xz, a_yy, a_yz, a_zz)
                if use_sheared:
                    r10, r11, r12 = abs(n10), abs(n11), abs(n12)
                    x, y, z_entry, low_mag = s00, s01, s11, _ZERO
                    det = (s00 * s11 - s01 * s01) + low * (an + cn - low)
                else:
                    r10, r11, r12 = abs(m10), abs(m11), abs(m12)
                    x, y, z_entry, low_mag = an, bn, cn, _LOW_PASS
                    det = an * cn - bn * bn
                t10, t11, t12 = _times_sym(r10, r11, r12, a_xx, a_xy, a_xz, a_yy, a_yz, a_zz)
                x_mag = (t00 * r00 + t01 * r01 + t02 * r02 + low_mag) / s
                y_mag = (t10 * r00 + t11 * r01 + t12 * r02) / s
                z_mag = (t10 * r10 + t11 * r11 + t12 * r12 + low_mag) / s
                noise = _HALF * (x_mag * abs(z_entry) + abs(x) * z_mag) + abs(y) * y_mag
                threshold = _DET_REL * noise
                if not det > threshold:  # reliable: rounding noise, culled (NaN too)
                    continue
                # reliability_fade: 1 - exp(-ALPHA_MIN (rho - 1)), rho = det / threshold; 1 where the threshold
                # underflowed. Below _FADE_SKIP, exp is under a quarter of float32's spacing below 1, so 1 - exp rounds
                # to 1 exactly: exp (a libm call, a fifth of this loop's time) is skipped for the well-conditioned
                # Gaussians, nearly all.
                fade_power = -_ALPHA_MIN * ((det - threshold) / threshold) if threshold > _ZERO else _FADE_SKIP
                fade = _ONE - np.exp(fade_power) if fade_power > _FADE_SKIP else _ONE
                # conic_from_cov2d, alpha_shape
                det_s = _safe_div(det) * s
                con_a, con_b, con_c = cn / det_s, -bn / det_s, an / det_s
                c_div = c if c != _ZERO else _ONE
                shape_k, shape_q = b / c_div, _ONE / c_div
                # extent_radius
                if _HALF * (a + c) > _HUGE:
                    radius = _radius_of(an, bn, cn) * _safe_sqrt(s)
                else:
                    radius = _radius_of(a, b, c)
                bound = (abs(con_a) + _F(2.0) * abs(con_b) + abs(con_c)) * radius * radius  # extent_power_bound
                # screen_bounded, and keep_mask's finite 2D covariance
                if not (_bounded(u) and _bounded(v) and _bounded(con_a) and _bounded(con_b) and _bounded(con_c)
                        and _bounded(shape_k) and _bounded(shape_q) and _bounded(radius) and _bounded(bound)
                        and math.isfinite(a) and math.isfinite(b) and math.isfinite(c)):
                    continue
                opacity = rows[i, 12] * fade  # the opacity as composited
                if opacity < alpha_min:  # alpha <= opacity (exp <= 1): no pixel can pass
                    continue
                # Box: the extent square intersected with the alpha >= alpha_min ellipse of this quadratic form,
                # |dx| <= sqrt(2 L (det' + b^2) / c), |dy| <= sqrt(2 L c), L = ln(opacity / alpha_min); in float64,
                # widened.
                level = 2.0 * math.log(float(opacity) / float(alpha_min))
                det_abs = float(det) * float(s) * float(s)  # det(cov2d) as the conic uses it
                reach_x = math.sqrt(max(level * (det_abs + float(b) * float(b)) / float(c), 0.0))
                reach_y = math.sqrt(max(level * float(c), 0.0))
                reach_x = min(float(radius), reach_x * (1.0 + _BOX_SLACK_REL) + _BOX_SLACK_PX)
                reach_y = min(float(radius), reach_y * (1.0 + _BOX_SLACK_REL) + _BOX_SLACK_PX)
                x0, x1, ok_x = _pixel_span(float(u), reach_x, width)
                y0, y1, ok_y = _pixel_span(float(v), reach_y, height)
                if not (ok_x and ok_y):
                    continue
                params[i, 0], params[i, 1], params[i, 2], params[i, 3], params[i, 4] = u, v, con_a, shape_k, shape_q
                params[i, 5], params[i, 6] = opacity, radius
                params[i, 10] = level * (1.0 + _BOX_SLACK_REL)  # A t^2 + q dy^2 <= this where alpha can reach ALPHA_MIN
                for ch in range(3):  # splat_color
                    params[i, 7 + ch] = min(max(rows[i, 9 + ch], -_COLOR), _COLOR)
                boxes[i, 0], boxes[i, 1], boxes[i, 2], boxes[i, 3] = x0, x1, y0, y1
                params[i, 11], params[i, 12], params[i, 13], params[i, 14] = x0, x1, y0, y1


_BIN_CHUNKS = 8  # contiguous slices of the sorted list that `_bin` counts and fills in parallel


@njit(parallel=True, nogil=True, cache=True, error_model="numpy")
def _bin(boxes, tiles_x, tiles_y, workers):
    """Per-tile lists of Gaussian indices (each front to back): (start [tiles + 1], list [pairs]). The sorted list
    is cut into _BIN_CHUNKS contiguous slices, each counted and then written by whichever thread claims it; a
    tile's entries from slice k go after those of slices < k, so every tile's list keeps the depth order. The two
    passes are written out, not one helper with a count-or-fill flag: the flag's test in the innermost loop measured
    6-9% slower at 100k Gaussians."""
    n, tiles = boxes.shape[0], tiles_x * tiles_y
    per_chunk = -(-n // _BIN_CHUNKS)
    count = np.zeros((_BIN_CHUNKS, tiles), dtype=np.int64)
    counted = np.zeros(1, dtype=np.int64)  # slices claimed so far
    for _worker in prange(workers):
        while True:
            chunk = claim(counted)
            if chunk >= _BIN_CHUNKS:
                break
            for i in range(chunk * per_chunk, min(n, (chunk + 1) * per_chunk)):
                if boxes[i, 0] < 0:
                    continue
                for ty in range(boxes[i, 2] // TILE, boxes[i, 3] // TILE + 1):
                    for tx in range(boxes[i, 0] // TILE, boxes[i, 1] // TILE + 1):
                        count[chunk, ty * tiles_x + tx] += 1
    start = np.zeros(tiles + 1, dtype=np.int64)
    cursor = np.empty((_BIN_CHUNKS, tiles), dtype=np.int64)  # where each slice writes next in each tile
    total = 0
    for tile in range(tiles):
        start[tile] = total
        for chunk in range(_BIN_CHUNKS):
            cursor[chunk, tile] = total
            total += count[chunk, tile]
    start[tiles] = total
    lists = np.empty(total, dtype=np.int32)
    filled = np.zeros(1, dtype=np.int64)
    for _worker in prange(workers):
        while True:
            chunk = claim(filled)
            if chunk >= _BIN_CHUNKS:
                break
            for i in range(chunk * per_chunk, min(n, (chunk + 1) * per_chunk)):
                if boxes[i, 0] < 0:
                    continue
                for ty in range(boxes[i, 2] // TILE, boxes[i, 3] // TILE + 1):
                    for tx in range(boxes[i, 0] // TILE, boxes[i, 1] // TILE + 1):
                        tile = ty * tiles_x + tx
                        lists[cursor[chunk, tile]] = i
                        cursor[chunk, tile] += 1
    return start, lists


@njit(inline="always", cache=True)
def _slot(py, px):
    """Index of tile pixel (px, py) in a plane of the accumulator: blocks of 4 columns x 2 rows are contiguous."""
    return (py >> 1) * (2 * TILE) + (px >> 2) * _BLOCK + (py & 1) * 4 + (px & 3)


@njit(inline="always", cache=True)
def _row_slot(row):
    """`_slot(row, 0)` for an unsigned row: a row's column c lies at it + (c >> 2) * _BLOCK + (c & 3)."""
    return (row >> np.uint64(1)) * np.uint64(2 * TILE) + (row & np.uint64(1)) * np.uint64(4)


# A function of its own, like `_over_pixel`: compiled without the blend's fastmath flags, so each value is
# `_over_background`'s byte. Converting the tile's planes in one pass, then scattering the bytes, measured 2.3x
# faster than a call per pixel and channel in the blend (an empty 512x512 frame: 0.82 -> 0.35 ms on 2 cores).
@njit(cache=True, error_model="numpy")
def _tile_bytes(acc, bytes_out, y0, x0, rows, columns, background):
    """A tile's accumulator (C, T planes) over `background` into bytes_out [y0 : y0 + rows, x0 : x0 + columns]."""
    levels = np.empty(3 * _TILE_PIXELS, dtype=np.uint8)
    for i in range(np.uint64(_TILE_PIXELS)):
        transmittance = abs(acc[_T + i])
        levels[i] = _over_pixel(acc[i], transmittance, background[0])
        levels[_G + i] = _over_pixel(acc[_G + i], transmittance, background[1])
        levels[_B + i] = _over_pixel(acc[_B + i], transmittance, background[2])
    for row in range(np.uint64(rows)):
        py, first = np.uint64(y0) + row, _row_slot(row)
        for column in range(np.uint64(columns)):
            px = np.uint64(x0) + column
            k = first + (column >> np.uint64(2)) * np.uint64(_BLOCK) + (column & np.uint64(3))
            bytes_out[py, px, 0] = levels[k]
            bytes_out[py, px, 1] = levels[_G + k]
            bytes_out[py, px, 2] = levels[_B + k]


def _blend_source(counting: bool):
    """The tile blend, with the work counts of BLEND_COUNTS when `counting` (a compile-time constant: the kernel
    that draws frames has no counting code; the counts would need integer sums inside the block loop, which keep
    it from 8-wide vectors)."""

    def blend_tiles(params, start, lists, tiles_x, width, height, out, counts, order, workers, background, bytes_out,
                    alpha_min, t_stop):
        """Composite each tile front to back into out [H, W, 4] = (C, T): per pixel the extent test, alpha (0.99
        clamp, skipped below `alpha_min` or for a positive power), the stop before T would fall below T_MIN and the
        one after a contribution leaves T below `t_stop` (RenderSettings.transmittance_min; T_MIN: never). With
        a non-empty bytes_out [H, W, 3] (uint8), that receives C + T background in 8 bits instead (`_over_pixel`), and
        `out` is not written."""
        n_tiles = start.shape[0] - 1
        taken = np.zeros(1, dtype=np.int64)  # tiles claimed so far, in `order`
        for _worker in prange(workers):
            while True:
                claimed = claim(taken)
                if claimed >= n_tiles:
                    break
                tile = order[claimed]
                ty, tx = tile // tiles_x, tile % tiles_x
                x0, y0 = tx * TILE, ty * TILE
                x1, y1 = min(x0 + TILE, width), min(y0 + TILE, height)
                # One array holds the tile's red, green, blue and T planes at constant offsets, so the compiler sees
                # that the planes do not overlap and vectorises. A pixel that has stopped keeps -T (and one outside
                # the image -1): T > 0 is "still blending".
                # A whole tile (most of them) sets its planes in one pass; an edge tile marks its pixels in the image.
                acc = np.empty(4 * _TILE_PIXELS, dtype=np.float32)
                whole = y1 - y0 == TILE and x1 - x0 == TILE
                for i in range(np.uint64(_TILE_PIXELS)):
                    acc[i] = _ZERO
                    acc[_G + i] = _ZERO
                    acc[_B + i] = _ZERO
                    acc[_T + i] = _ONE if whole else -_ONE
                if not whole:
                    for py in range(y1 - y0):
                        for px in range(x1 - x0):
                            acc[_T + _slot(py, px)] = _ONE
                # Which blocks of 4 x 2 pixels, and which pixel-row pairs, still hold a pixel that blends: set again
                # every _LIVE_EVERY Gaussians (a per-pixel count would need integer sums in the block loop), so a block
                # that has just stopped may still be computed a few times, changing nothing.
                block_live = np.ones(_TILE_PIXELS // _BLOCK, dtype=np.bool_)
                pair_live = np.zeros(_PAIRS, dtype=np.bool_)
                pair_live[: (y1 - y0 + 1) >> 1] = True
                # The current Gaussian's first and last columns per row of the tile, in one array (the last at _HI) so
                # that the compiler sees the two do not overlap and vectorises the loop that sets them.
                span = np.empty(2 * TILE, dtype=np.float32)
                span_lo, span_hi = span[:TILE], span[TILE:]
                visited = row_pairs = blocks_tried = blocks_blended = fragments = 0
                for j in range(start[tile], start[tile + 1]):
                    if (j - start[tile]) % _LIVE_EVERY == _LIVE_EVERY - 1:
                        any_live = False
                        for pair in range(_PAIRS):
                            if pair_live[pair]:
                                live = False
                                for block in range(pair * _BLOCKS_PER_PAIR, (pair + 1) * _BLOCKS_PER_PAIR):
                                    if block_live[block]:
                                        most = acc[_T + np.uint64(block * _BLOCK)]
                                        for lane in range(1, _BLOCK):
                                            most = max(most, acc[_T + np.uint64(block * _BLOCK + lane)])
                                        block_live[block] = most > _ZERO
                                        live |= block_live[block]
                                pair_live[pair] = live
                                any_live |= live
                        if not any_live:  # every pixel of the tile has stopped
                            break
                    if counting:
                        visited += 1
                    if j + _AHEAD < start[tile + 1]:
                        prefetch(params, lists[j + _AHEAD])
                    p = params[lists[j]]
                    u, v, sa, sk, sq = p[0], p[1], p[2], p[3], p[4]
                    opacity, radius = p[5], p[6]
                    red, green, blue = p[7], p[8], p[9]
                    level = p[10]
                    bx0, bx1 = max(p[11], _F(x0)), min(p[12], _F(x1 - 1))
                    by0, by1 = max(np.int64(p[13]), y0) - y0, min(np.int64(p[14]), y1 - 1) - y0  # tile rows
                    ry0, ry1 = by0 & ~1, by1 | 1  # whole row pairs
                    # Each row's columns where A t^2 <= level - q dy^2 (t = dx - k dy), widened by a pixel, for every
                    # row of the pairs at once (runs of 8 rows without branches: 8-wide vector code); none in a row
                    # beyond the radius or outside the box. They only choose the pixels tried: each pixel still tests
                    # itself.
                    inv_sa = _ONE / sa
                    first_row = _F(y0 + ry0)
                    box_top, box_bottom = _F(by0 - ry0), _F(by1 - ry0)
                    for eight in range(0, ry1 - ry0 + 1, _BLOCK):  # whole runs of 8 rows: vector code, no remainder
                        for lane in range(_BLOCK):
                            row = _F(eight) + _LANE_INDEX[lane]  # the row within the pairs, as a float (exact)
                            dy = (first_row + row) + _HALF - v  # first_row + row is the row's own float: dy exactly
                            rest = level - sq * dy * dy
                            half = np.sqrt(max(rest, _ZERO) * inv_sa) + _ONE
                            mid = u + sk * dy - _HALF
                            lo, hi = np.floor(mid - half), np.ceil(mid + half)
                            # selects, not min/max: a NaN (0 * inf where A underflowed) keeps the whole box row
                            lo = lo if lo > bx0 else bx0
                            hi = hi if hi < bx1 else bx1
                            lo = lo if rest >= _ZERO else _NO_SPAN
                            lo = lo if abs(dy) <= radius else _NO_SPAN
                            lo = lo if row >= box_top else _NO_SPAN
                            lo = lo if row <= box_bottom else _NO_SPAN
                            k = np.uint64(eight) + np.uint64(lane)  # unsigned: no wraparound checks
                            span[k] = lo
                            span[_HI + k] = hi if lo != _NO_SPAN else -_NO_SPAN
                    for pair in range(ry0 >> 1, (ry1 >> 1) + 1):
                        r = 2 * pair - ry0
                        lo, hi = min(span_lo[r], span_lo[r + 1]), max(span_hi[r], span_hi[r + 1])
                        if not pair_live[pair] or lo > hi:
                            continue
                        if counting:
                            row_pairs += 1
                        dy0 = _F(y0 + 2 * pair) + _HALF - v
                        dy1 = _F(y0 + 2 * pair + 1) + _HALF - v
                        qdy0, qdy1 = sq * dy0 * dy0, sq * dy1 * dy1
                        skdy0, skdy1 = sk * dy0, sk * dy1
                        # the extent test's dy half, per row: a row without columns passes no pixel (as a skipped row)
                        reach0 = radius if span_lo[r] <= span_hi[r] else -_ONE
                        reach1 = radius if span_lo[r + 1] <= span_hi[r + 1] else -_ONE
                        for column in range((np.int64(lo) - x0) >> 2, ((np.int64(hi) - x0) >> 2) + 1):
                            first = np.uint64(pair * 2 * TILE + column * _BLOCK)  # unsigned: no wraparound checks
                            if counting:
                                blocks_tried += 1
                            # A block whose pixels have all stopped (or lie outside the image) changes nothing: skip it.
                            # On an opaque head most blocks behind the first few layers are such.
                            if not block_live[pair * _BLOCKS_PER_PAIR + column]:
                                continue
                            if counting:
                                blocks_blended += 1
                            # plus small whole floats: exact, and no int -> float per lane
                            block_x = _F(x0 + 4 * column)
                            for lane in range(_BLOCK):  # branch-free, fixed width, no integer sums: 8-wide vectors
                                i = first + np.uint64(lane)
                                lower = _LANE_ROW[lane] > _HALF
                                dx = (block_x + _LANE_COLUMN[lane]) + _HALF - u
                                tt = dx - (skdy1 if lower else skdy0)
                                power = _NEG_HALF * (sa * tt * tt + (qdy1 if lower else qdy0))
                                alpha = min(_ALPHA_MAX, opacity * _exp(power))
                                t_old = acc[_T + i]
                                # The tests as float selects (boolean ands of 8 lanes cost packing): a = alpha
                                # where the pixel is inside the extent, the power is not positive and the pixel
                                # blends, else 0; it is used where a >= ALPHA_MIN (> 0).
                                a = alpha if abs(dx) <= (reach1 if lower else reach0) else _ZERO
                                a = a if power <= _ZERO else _ZERO
                                a = a if t_old > _ZERO else _ZERO
                                used = a >= alpha_min
                                t_new = t_old * (_ONE - a)
                                added = (a if t_new >= _T_MIN else _ZERO) if used else _ZERO
                                stop_probe = t_new if used else _ONE  # below T_MIN: used, and T would fall under it
                                # Stores of computed values only (T * (1 - 0) is exact): a select between a new and the
                                # loaded value would become a masked store, slow on AMD CPUs.
                                w = added * t_old
                                acc[i] += red * w
                                acc[_G + i] += green * w
                                acc[_B + i] += blue * w
                                t_after = t_old * (_ONE - added)
                                after_probe = t_after if used else _ONE  # a live pixel's T is >= t_stop already
                                t_keep = -t_after if after_probe < t_stop else t_after
                                acc[_T + i] = -t_old if stop_probe < _T_MIN else t_keep
                                if counting:
                                    fragments += 1 if added > _ZERO else 0
                if counting:
                    counts[tile, 0], counts[tile, 1] = start[tile + 1] - start[tile], visited
                    counts[tile, 2] = row_pairs
                    counts[tile, 3], counts[tile, 4], counts[tile, 5] = blocks_tried, blocks_blended, fragments
                if bytes_out.shape[0]:
                    _tile_bytes(acc, bytes_out, y0, x0, y1 - y0, x1 - x0, background)
                else:
                    for row in range(np.uint64(y1 - y0)):  # unsigned: no wraparound checks
                        py, first = np.uint64(y0) + row, _row_slot(row)
                        for column in range(np.uint64(x1 - x0)):
                            px = np.uint64(x0) + column
                            k = first + (column >> np.uint64(2)) * np.uint64(_BLOCK) + (column & np.uint64(3))
                            out[py, px, 0] = acc[k]
                            out[py, px, 1] = acc[_G + k]
                            out[py, px, 2] = acc[_B + k]
                            out[py, px, 3] = abs(acc[_T + k])

    return blend_tiles


_blend_tiles = njit(parallel=True, nogil=True, cache=True, error_model="numpy",
                    fastmath={"contract"})(_blend_source(False))
_blend_counting = None  # the counting twin, compiled on first use (benchmarks only; not cached: it would share the
#                         cache's name with _blend_tiles)


def _counting_kernel():
    """The blend with its work counts (`_blend_source(True)`), compiled once per process on first use."""
    global _blend_counting
    if _blend_counting is None:
        _blend_counting = njit(parallel=True, nogil=True, error_model="numpy",
                               fastmath={"contract"})(_blend_source(True))
    return _blend_counting


# What the counting blend counts: (Gaussian, tile) pairs binned and visited (a tile stops soon after its last
# pixel stops), pixel-row pairs and blocks of 4 x 2 pixels tried, blocks blended (computed: not skipped as stopped
# at the last check), and fragments blended (pixels whose colour a Gaussian changed).
BLEND_COUNTS = ("pairs_binned", "pairs_visited", "row_pairs", "blocks_tried", "blocks_blended", "fragments")


def _aligned_rows(n: int) -> np.ndarray:
    """An uninitialised float32 [n, _PARAMS] array whose rows start on cache-line boundaries (numpy aligns to 16
    bytes only)."""
    spare = _CACHE_LINE // 4
    raw = np.empty(n * _PARAMS + spare, dtype=np.float32)
    skip = (-raw.ctypes.data % _CACHE_LINE) // 4
    return raw[skip: skip + n * _PARAMS].reshape(n, _PARAMS)


def splat_frame(rows: np.ndarray, camera: Camera, counts: np.ndarray | None = None, *,
                background: np.ndarray | None = None, alpha_min: float = numerics.ALPHA_MIN,
                t_stop: float = numerics.TRANSMITTANCE_MIN) -> tuple[np.ndarray, float, float]:
    """(C, T) [H, W, 4] float32 of depth-sorted, culled rows [n, 13]; also the set-up and blend seconds. `counts`
    (int64 [len(BLEND_COUNTS)]), when given, receives the blend's work totals from the counting twin of the blend
    (the same pixels; compiled on first use, about 20 s). With `background` (float32 [3]) the frame is the 8-bit
    [H, W, 3] over that background instead, written by the blend as each tile ends: `_convert(..., "uint8")`'s
    bytes without the float frame between. `alpha_min` replaces the contract's ALPHA_MIN in the alpha test and in
    the boxes (`RenderSettings.alpha_min`; the reliability fade keeps the contract's); a pixel also stops once a
    contribution leaves its T below `t_stop` (`RenderSettings.transmittance_min`, docs/numerics.md, "Transmittance
    stop")."""
    start = time.perf_counter()
    width, height = int(camera.width), int(camera.height)
    n = len(rows)
    params = _aligned_rows(n)
    boxes = np.empty((n, 4), dtype=np.int32)
    intrinsics = np.array([camera.fx, camera.fy, camera.cx, camera.cy], dtype=np.float32)
    limits = np.array(camera.fov_clamp_limits(), dtype=np.float32)
    workers = numba.get_num_threads()  # one per thread; each claims its work as it goes (`claim`)
    if n:
        _project(rows, camera.R.astype(np.float32), camera.t.astype(np.float32), intrinsics, limits, width, height,
                 params, boxes, workers, _F(alpha_min))
    tiles_x, tiles_y = -(-width // TILE), -(-height // TILE)
    tile_start, lists = _bin(boxes, tiles_x, tiles_y, workers)
    setup = time.perf_counter() - start
    start = time.perf_counter()
    as_bytes = background is not None
    out = np.empty((0 if as_bytes else height, width, 4), dtype=np.float32)
    bytes_out = np.empty((height if as_bytes else 0, width, 3), dtype=np.uint8)
    background = np.zeros(3, dtype=np.float32) if background is None else background
    per_tile = np.zeros((tiles_x * tiles_y if counts is not None else 0, len(BLEND_COUNTS)), dtype=np.int64)
    kernel = _blend_tiles if counts is None else _counting_kernel()
    order = np.argsort(tile_start[:-1] - tile_start[1:], kind="stable")  # the longest lists first
    kernel(params, tile_start, lists, tiles_x, width, height, out, per_tile, order, workers, background, bytes_out,
           _F(alpha_min), _F(t_stop))
    seconds = time.perf_counter() - start
    if counts is not None:
        counts[:] = per_tile.sum(axis=0)
    return (bytes_out if as_bytes else out), setup, seconds


def upscale_bilinear(image: np.ndarray, width: int, height: int) -> np.ndarray:
    """image [h, w, C] sampled bilinearly at the centres of a (width, height) grid, edges clamped: what the GL
    render-scale pass (shaders/upscale.frag, a LINEAR texture) computes."""

    def axis(size_out: int, size_in: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        pos = (np.arange(size_out, dtype=np.float64) + 0.5) * size_in / size_out - 0.5
        lo = np.floor(pos)
        frac = (pos - lo).astype(np.float32)
        return (np.clip(lo, 0, size_in - 1).astype(np.intp), np.clip(lo + 1, 0, size_in - 1).astype(np.intp),
                1 - frac, frac)

    if image.dtype == np.uint8:
        out = np.empty((height, width, image.shape[2]), dtype=np.uint8)
        _upscale_bytes(np.ascontiguousarray(image), *axis(height, image.shape[0]), *axis(width, image.shape[1]), out,
                       numba.get_num_threads())
        return out
    image = np.ascontiguousarray(image, dtype=np.float32)
    out = np.empty((height, width, image.shape[2]), dtype=np.float32)
    _upscale(image, *axis(height, image.shape[0]), *axis(width, image.shape[1]), out)
    return out


# A kernel rather than numpy's gathers: the gathered [H, W, C] temporaries cost ~20 ms a frame at 480x600 on
# 2 cores, more than a 3/4 render scale saves in the blending (docs/bench/renderers.md).
@njit(parallel=True, nogil=True, cache=True, error_model="numpy")
def _upscale(image, y0, y1, wy0, wy1, x0, x1, wx0, wx1, out):
    """out[y, x] = the vertical blend of rows y0/y1, then the horizontal blend of columns x0/x1 (float32)."""
    for y in prange(out.shape[0]):
        top, bottom, w_top, w_bottom = y0[y], y1[y], wy0[y], wy1[y]
        for x in range(out.shape[1]):
            left, right = x0[x], x1[x]
            for c in range(out.shape[2]):
                at_left = image[top, left, c] * w_top + image[bottom, left, c] * w_bottom
                at_right = image[top, right, c] * w_top + image[bottom, right, c] * w_bottom
                out[y, x, c] = at_left * wx0[x] + at_right * wx1[x]


@njit(inline="always", cache=True, error_model="numpy")
def _byte_row(image, row, x0, x1, wx0, wx1, into):
    """into[x * C + c] = row `row` of the 8-bit image blended horizontally at output column x (float32)."""
    channels = image.shape[2]
    for x in range(x0.shape[0]):
        left, right, w_left, w_right = x0[x], x1[x], wx0[x], wx1[x]
        for c in range(channels):
            into[x * channels + c] = _F(image[row, left, c]) * w_left + _F(image[row, right, c]) * w_right


# Separable, unlike `_upscale`: each input row is blended horizontally once, and the vertical blend of two such rows
# is contiguous (vector code); an 8-bit frame costs a third of the float frame's upscale and conversion.
@njit(parallel=True, nogil=True, cache=True, error_model="numpy")
def _upscale_bytes(image, y0, y1, wy0, wy1, x0, x1, wx0, wx1, out, workers):
    """`_upscale` of an 8-bit frame into an 8-bit frame, each value rounded to the nearest level: what GL's
    upscale pass computes from an 8-bit framebuffer (a LINEAR UNORM8 texture written to UNORM8). Threads claim
    _ROWS_CHUNK output rows at a time."""
    height, row_size = out.shape[0], out.shape[1] * out.shape[2]
    taken = np.zeros(1, dtype=np.int64)
    for _worker in prange(workers):
        rows = np.empty((2, row_size), dtype=np.float32)  # the horizontal blends of input rows held[0], held[1]
        held = np.full(2, -1, dtype=np.int64)
        flat = out.reshape(height, row_size)
        while True:
            first = claim(taken) * _ROWS_CHUNK
            if first >= height:
                break
            for y in range(first, min(first + _ROWS_CHUNK, height)):
                for k, source in enumerate((y0[y], y1[y])):
                    if held[k] != source:
                        if held[1 - k] == source:
                            rows[k, :] = rows[1 - k, :]
                        else:
                            _byte_row(image, source, x0, x1, wx0, wx1, rows[k])
                        held[k] = source
                w_top, w_bottom = wy0[y], wy1[y]
                top, bottom, target = rows[0], rows[1], flat[y]
                for i in range(row_size):
                    target[i] = np.uint8(top[i] * w_top + bottom[i] * w_bottom + _HALF)


# Most frames a loop draws at once (`CPUSplatter.frames_at_once`): each holds its sorted rows, parameters and
# pixels (about 3 MB at 20k Gaussians and 512x512), so this bounds that memory on machines with many cores.
MAX_FRAMES_AT_ONCE = 8


class CPUSplatter:
    """`GLSplatter`'s interface (prepare, draw, render, release, last_timings, the same outputs) on the CPU.

    `settings`: the render settings; render_scale, max_draw_pixels and the sort knobs work as on GL. The CPU always
    blends in float32, the contract's precision; with render_target "uint8" a frame drawn at a render scale is kept
    in 8 bits before its upscale, as GL's 8-bit framebuffer is (an 8-bit frame then skips the float frame's upscale
    and conversion). alpha_min and transmittance_min apply on this splatter only. `threads`: numba threads for the
    kernels (None: numba's default, every core). Construction compiles (first run) or loads (cached) the kernels."""

    def __init__(self, *, settings: RenderSettings | None = None, threads: int | None = None) -> None:
        if settings is not None and not isinstance(settings, RenderSettings):
            raise RenderError(f"settings must be a RenderSettings, got {type(settings).__name__}")
        self.settings = settings or RenderSettings()
        self.threads = threads
        self._sorter = DepthSorter(self.settings.sort_interval, self.settings.sort_key_bits)
        self._timings = threading.local()
        self._no_draw: dict[str, float] = dict.fromkeys(STAGES, 0.0)
        self.released = False
        if not _WARM and not kernels_cached():
            logger.warning("compiling the CPU splatter's kernels for this machine: once, about 20 s on 2 cores "
                           "(cached in %s)", cache_dir())
        start = time.perf_counter()
        warm_up()
        self.warm_up_seconds = time.perf_counter() - start

    def prepare(self, means, cov3d, rgb, opacity, camera: Camera) -> PreparedSplats:
        """Validate, pack and depth-sort (no shared state: safe on a worker thread). Sorting every frame (32-bit
        keys, the contract's, or 16-bit ones) this runs the fused numba passes of `cpu_sort`; with a sort interval,
        `DepthSorter`'s numpy path."""
        start = time.perf_counter()
        if self._sorter.interval == 1:
            camera, output_size = draw_camera(self.settings, camera)
            rows = cpu_sort.sorted_packed_rows(*checked_gaussians(means, cov3d, rgb, opacity), camera,
                                               self._sorter.key_bits)
        else:
            rows, camera, output_size = sorted_rows(self._sorter, self.settings, means, cov3d, rgb, opacity,
                                                    camera)
        return PreparedSplats(np.ascontiguousarray(rows), [], camera, time.perf_counter() - start, output_size)

    def draw(self, prepared: PreparedSplats, background, *, output: str = "uint8") -> np.ndarray:
        """Splat a prepared frame -> the `output` frame (see `GLSplatter.render`). Timings: "upload" is the
        projection and binning, "draw" the tile blending (and render-scale upscale), "readback" the conversion; an
        8-bit frame at the drawn size is written by the blend itself, so its "readback" is 0."""
        if self.released:
            raise RenderError("this CPUSplatter has been released")
        if output not in FRAME_OUTPUTS:
            raise RenderError(f"output must be one of {', '.join(map(repr, FRAME_OUTPUTS))}, got {output!r}")
        background = np.asarray(background_rgb(background), dtype=np.float32)
        timings = dict.fromkeys(STAGES, 0.0)
        timings["sort"] = prepared.seconds
        previous = numba.get_num_threads()
        if self.threads is not None:
            numba.set_num_threads(min(self.threads, numba.config.NUMBA_NUM_THREADS))
        # 8 bits at the drawn size: the blend writes them as each tile ends (timed as "draw"; "readback" is 0)
        # With an 8-bit render target a scaled frame is stored in 8 bits too, then its bytes upscaled, as GL's 8-bit
        # framebuffer is
        fused = output == "uint8" and (prepared.output_size is None or self.settings.render_target == "uint8")
        try:
            frame, timings["upload"], timings["draw"] = splat_frame(prepared.rows, prepared.camera,
                                                                    background=background if fused else None,
                                                                    alpha_min=self.settings.alpha_min,
                                                                    t_stop=self.settings.transmittance_min)
        finally:
            numba.set_num_threads(previous)
        if fused:
            if prepared.output_size is not None:
                start = time.perf_counter()
                frame = upscale_bilinear(frame, *prepared.output_size)
                timings["draw"] += time.perf_counter() - start
            self.last_timings = timings
            return frame
        if prepared.output_size is not None:
            start = time.perf_counter()
            frame = upscale_bilinear(frame, *prepared.output_size)
            timings["draw"] += time.perf_counter() - start
        start = time.perf_counter()
        result = _convert(frame, background, output)
        timings["readback"] = time.perf_counter() - start
        self.last_timings = timings
        return result

    def render(self, means, cov3d, rgb, opacity, camera: Camera, background, *, output: str = "uint8"
               ) -> np.ndarray:
        """Splat N Gaussians -> a frame, as `GLSplatter.render`."""
        return self.draw(self.prepare(means, cov3d, rgb, opacity, camera), background, output=output)

    def frames_at_once(self) -> int:
        """Frames a loop may draw at once, each whole on one core (`begin_worker`): numba's thread count for the
        calling thread, at most MAX_FRAMES_AT_ONCE, where draws share no state (the contract's sort, every frame)
        and no `threads` was set; else 1. On 2 cores two frames at once beat one frame on both cores by about 1.25x
        (no parallel loops to start and join; docs/speed.md, "Whole frames at once")."""
        if self.threads is not None or self._sorter.interval != 1:
            return 1
        return max(1, min(numba.get_num_threads(), MAX_FRAMES_AT_ONCE))

    def begin_worker(self) -> None:
        """The calling thread's kernels run on one thread (numba's thread count is per thread)."""
        numba.set_num_threads(1)

    @property
    def last_timings(self) -> dict[str, float]:
        """The STAGES seconds of the calling thread's last draw (frames drawn at once each keep their own)."""
        return getattr(self._timings, "last", self._no_draw)

    @last_timings.setter
    def last_timings(self, timings: dict[str, float]) -> None:
        self._timings.last = timings

    def release(self) -> None:
        """Nothing to free but the name; later draws raise RenderError like a released GLSplatter's."""
        self.released = True

    def __enter__(self) -> CPUSplatter:
        return self

    def __exit__(self, *exc_info) -> None:
        self.release()


@njit(cache=True, error_model="numpy")
def _over_pixel(color, transmittance, background):
    """`to_uint8` of color + transmittance x background: floor(clamp(v, 0, 1) * 255 + 0.5) in float32, NaN as 0.
    Its own function, compiled without the blend's fastmath flags, so that the multiply and add stay two rounded
    steps (no fused multiply-add) wherever it is called: the blend's 8-bit tiles are `_over_background`'s bytes."""
    value = color + transmittance * background
    value = min(max(value, _ZERO), _ONE) if value == value else _ZERO
    return np.uint8(np.floor(value * _F(255.0) + _HALF))


@njit(parallel=True, nogil=True, cache=True, error_model="numpy")
def _over_background(frame, background, out, as_bytes, workers):
    """out = C + T * background (float32 [H, W, 3]) or, for a uint8 `out`, `to_uint8` of it: floor(clamp(v, 0, 1)
    * 255 + 0.5) in float32, NaN as 0. Threads claim _ROWS_CHUNK rows at a time."""
    height = frame.shape[0]
    taken = np.zeros(1, dtype=np.int64)
    for _worker in prange(workers):
        while True:
            first = claim(taken) * _ROWS_CHUNK
            if first >= height:
                break
            for y in range(first, min(first + _ROWS_CHUNK, height)):
                for x in range(frame.shape[1]):
                    for ch in range(3):
                        if as_bytes:
                            out[y, x, ch] = _over_pixel(frame[y, x, ch], frame[y, x, 3], background[ch])
                        else:
                            out[y, x, ch] = frame[y, x, ch] + frame[y, x, 3] * background[ch]


def _convert(frame: np.ndarray, background: np.ndarray, output: str) -> np.ndarray:
    """(C, T) [H, W, 4] -> the requested output (the GL splatter's four). The alpha outputs turn T into 1 - T in
    place: `frame` is the draw's own array (a copy would cost 30x more, 4.5 ms at 480x600)."""
    if output in ("rgba", "rgba_float"):
        np.subtract(np.float32(1.0), frame[..., 3], out=frame[..., 3])
        return frame if output == "rgba_float" else straight_rgba(frame, background)
    out = np.empty((*frame.shape[:2], 3), dtype=np.uint8 if output == "uint8" else np.float32)
    _over_background(frame, background, out, output == "uint8", numba.get_num_threads())
    return out


_WARM = False


def kernels_cached() -> bool:
    """Whether the blend kernel's machine code for this source is in numba's cache, so that construction loads
    instead of compiling. It reads numba's index path, an internal attribute: where that is missing, True."""
    try:
        return Path(_blend_tiles._cache._cache_file._index_path).is_file()
    except AttributeError:
        return True


def warm_up() -> None:
    """Compile (or load from the cache) every kernel on a tiny frame, once per process."""
    global _WARM
    if _WARM:
        return
    camera = Camera(3, 2, 2.0, 2.0, 1.5, 1.0)
    rows = np.zeros((1, 13), dtype=np.float32)
    rows[0, 2], rows[0, 3], rows[0, 6], rows[0, 8], rows[0, 9:13] = 1.0, 0.1, 0.1, 0.1, 0.5
    frame, _, _ = splat_frame(rows, camera)
    for output in ("uint8", "float"):
        _convert(frame, np.ones(3, dtype=np.float32), output)
    exp_approx(np.zeros(1, dtype=np.float32))
    cpu_sort.warm_up()
    upscale_bilinear(frame, 4, 3)
    upscale_bilinear(np.zeros((2, 3, 3), dtype=np.uint8), 4, 3)
    _WARM = True


__all__ = ["BLEND_COUNTS", "MAX_FRAMES_AT_ONCE", "TILE", "CPUSplatter", "cache_dir", "exp_approx", "kernels_cached",
           "splat_frame", "upscale_bilinear", "warm_up"]
