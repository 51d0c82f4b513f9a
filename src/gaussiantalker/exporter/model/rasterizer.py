"""Pure-torch reference Gaussian rasterizer: the numerics contract (docs/numerics.md) made executable.

It is the ground truth the OpenGL runtime is compared against, and differentiable so a speaker can be fitted
through it. Per pixel it does exactly what the 3DGS forward loop does: walk the kept Gaussians front to back
(stable sort on camera-space z), skip those whose box |dx|, |dy| <= r misses the pixel centre or whose alpha is
below ALPHA_MIN, and stop before the first one whose blend would take transmittance below TRANSMITTANCE_MIN.

Speed and memory come from tiles, which never change a result (each pixel still tests its own centre):
Gaussians are binned to the tiles their [xy - r, xy + r] box overlaps (band of tile rows by band, so the
(splat, tile) lists stay under budget even when every splat covers the screen), tiles with similar list lengths
are batched into padded [tiles, pixels, K] tensors, and K is walked in chunks carrying transmittance, so no
per-pixel tensor grows past a fixed element count whatever the scene. When gradients are needed and the frame's
saved intermediates would exceed the memory budget, each batch is checkpointed (recomputed during backward).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor
from torch.utils.checkpoint import checkpoint

from gaussiantalker.sdk.camera import Camera
from gaussiantalker.sdk.numerics import ALPHA_MIN, PIXEL_CENTER_OFFSET, TRANSMITTANCE_MIN

from .splat_math import (
    alpha_from_components,
    alpha_shape,
    camera_to_pixel,
    conic_from_cov2d,
    covariance_2d,
    covariance_2d_determinant,
    extent_radius,
    keep_mask,
    reliability_fade,
    splat_color,
    world_to_camera,
)

__all__ = ["render_reference", "DEFAULT_MEMORY_BUDGET_BYTES", "DEFAULT_TILE_SIZE"]

# Bound on what one render keeps alive: chunk temporaries and tile lists, or what autograd saves for a frame.
DEFAULT_MEMORY_BUDGET_BYTES = 1 << 30
# Tile side in pixels. Results do not depend on it; 8 measured fastest on CPU (larger tiles waste per-pixel work on
# tile corners a splat's box misses; smaller ones grow binning and list overhead; docs/numerics.md).
DEFAULT_TILE_SIZE = 8
# Bytes alive per (pixel, Gaussian) element of a chunk, autograd's saved tensors included, with a margin over the
# measured value (docs/numerics.md, "The torch reference rasterizer's tiles and chunks").
_LIVE_BYTES_PER_ELEMENT = 96
# Chunk size cap (elements): 1 MiB float32 temporaries are recycled by the allocator and stay in cache, while
# multi-MiB ones are fresh pages each time (measured slower: docs/numerics.md).
_MAX_CHUNK_ELEMENTS = 1 << 18
# Bytes per (splat, tile) pair while binning (a few int64 arrays and the sort); tile lists get a quarter of
# the budget, which sets the row-band size.
_PAIR_BYTES = 64
# A batch stops taking tiles whose list is shorter than this fraction of its longest (bounds padding waste).
_MIN_FILL = 0.5


@dataclass
class _Splats:
    """Kept Gaussians in compositing order (front to back); radius is detached (it only selects pixels)."""

    xy: Tensor  # [M, 2]
    shape: Tensor  # [M, 3] alpha_shape (A, k, q)
    radius: Tensor  # [M]
    opacity: Tensor  # [M] times reliability_fade
    rgb: Tensor  # [M, 3]
    index: Tensor  # [M] each kept splat's index among the input Gaussians


@dataclass(frozen=True)
class _Grid:
    """The image cut into square tiles, row-major; edge tiles run past the image and are cropped at the end."""

    width: int
    height: int
    tile_size: int

    @property
    def tiles_x(self) -> int:
        return -(-self.width // self.tile_size)

    @property
    def tiles_y(self) -> int:
        return -(-self.height // self.tile_size)

    @property
    def tiles(self) -> int:
        return self.tiles_x * self.tiles_y

    @property
    def pixels(self) -> int:
        """Pixels per tile."""
        return self.tile_size * self.tile_size


@dataclass
class _Rects:
    """Inclusive tile-index rectangle of each splat's pixel box, clipped to the image; ok False = off screen."""

    tx0: Tensor  # [M] int64
    tx1: Tensor  # [M]
    ty0: Tensor  # [M]
    ty1: Tensor  # [M]
    ok: Tensor  # [M] bool


@dataclass
class _Bins:
    """Per-tile lists of splat indices, concatenated in tile order, each list in compositing order."""

    splat: Tensor  # [pairs] index into _Splats
    start: Tensor  # [tiles] offset of each tile's list
    count: Tensor  # [tiles] length of each tile's list


def render_reference(
    means: Tensor,
    cov3d: Tensor,
    rgb: Tensor,
    opacity: Tensor,
    camera: Camera,
    background: Tensor | Sequence[float],
    *,
    tile_size: int = DEFAULT_TILE_SIZE,
    memory_budget_bytes: int = DEFAULT_MEMORY_BUDGET_BYTES,
    max_weight: Tensor | None = None,
    blend_count: Tensor | None = None,
    alpha_min: float = ALPHA_MIN,
) -> tuple[Tensor, Tensor]:
    """Render one frame by the numerics contract: (image C + T * background [H, W, 3], transmittance T [H, W]).

    `max_weight` [N] float32, if given, is raised in place to each Gaussian's largest blend weight alpha_i T_i
    over this frame's pixels (what scene pruning measures, docs/scene.md). `blend_count` [2, H, W], if given, is set
    in place to the number of Gaussians blended into each pixel [0] before the contract stopped it and [1] while its
    T was still >= 1/255, before it was visibly saturated (how deep a surface is: without gradients only;
    docs/demo-speaker.md). `alpha_min` replaces the contract's ALPHA_MIN in the per-pixel alpha test as the CPU
    splatter's `RenderSettings.alpha_min` does (the reliability fade keeps the contract's): frames as that splatter
    draws them with an alpha cut, which a Gaussian budget's refit fits through (docs/precision.md, "Refit")."""
    _check_inputs(means, cov3d, rgb, opacity, tile_size, memory_budget_bytes)
    if not ALPHA_MIN <= alpha_min < 1.0:
        raise ValueError(f"render_reference: alpha_min must be in [{ALPHA_MIN:.6g}, 1), got {alpha_min!r}")
    bg = torch.as_tensor(background, dtype=torch.float32, device=means.device).reshape(3)
    splats = _prepare_splats(means, cov3d, rgb, opacity, camera)
    grid = _Grid(camera.width, camera.height, tile_size)
    weights = None if max_weight is None else torch.zeros(len(splats.radius) + 1, dtype=torch.float32)
    counts: list[tuple[Tensor, Tensor]] | None = None if blend_count is None else []
    if counts is not None and torch.is_grad_enabled() and (means.requires_grad or rgb.requires_grad):
        raise ValueError("render_reference: blend_count is measured without gradients (use torch.no_grad())")
    color, trans = _render_tiles(splats, _tile_rects(splats, grid), grid, memory_budget_bytes, weights, counts,
                                 alpha_min)
    if blend_count is not None:
        per_tile = torch.zeros(grid.tiles, grid.pixels, 2, dtype=torch.int64)
        for tile_ids, count in counts:
            per_tile[tile_ids] = count
        blend_count.copy_(_untile(per_tile, grid)[: camera.height, : camera.width].permute(2, 0, 1))
    if max_weight is not None:
        max_weight.scatter_reduce_(0, splats.index, weights[:-1].to(max_weight.dtype), "amax")
    color = _untile(color, grid)[: camera.height, : camera.width]  # [H, W, 3]
    trans = _untile(trans, grid)[: camera.height, : camera.width]  # [H, W]
    return color + trans.unsqueeze(-1) * bg, trans


def _check_inputs(
    means: Tensor, cov3d: Tensor, rgb: Tensor, opacity: Tensor, tile_size: int, memory_budget_bytes: int
) -> None:
    """Raise ValueError on mis-shaped or non-float32 inputs or bad settings, naming the argument."""
    n = means.shape[0] if means.dim() == 2 else -1
    expected = {"means": (means, (n, 3)), "cov3d": (cov3d, (n, 6)), "rgb": (rgb, (n, 3)), "opacity": (opacity, (n,))}
    for name, (value, shape) in expected.items():
        if tuple(value.shape) != shape or n < 0:
            raise ValueError(f"render_reference: {name} must have shape {shape} (N from means [N, 3]), "
                             f"got {tuple(value.shape)}")
        if value.dtype != torch.float32:
            raise ValueError(f"render_reference: {name} must be float32, got {value.dtype}")
    if int(tile_size) != tile_size or tile_size < 1:
        raise ValueError(f"render_reference: tile_size must be a positive integer, got {tile_size!r}")
    if int(memory_budget_bytes) != memory_budget_bytes or memory_budget_bytes < 1:
        raise ValueError(f"render_reference: memory_budget_bytes must be a positive integer, "
                         f"got {memory_budget_bytes!r}")


def _prepare_splats(means: Tensor, cov3d: Tensor, rgb: Tensor, opacity: Tensor, camera: Camera) -> _Splats:
    """Project, cull and depth-sort; recompute the kept ones with grad so culled extremes never touch autograd."""
    device = means.device
    R = torch.as_tensor(camera.R, dtype=torch.float32, device=device)  # [3, 3]
    t = torch.as_tensor(camera.t, dtype=torch.float32, device=device)  # [3]
    intrinsics = (float(camera.fx), float(camera.fy), float(camera.cx), float(camera.cy))
    limits = camera.fov_clamp_limits()

    def screen_space(m: Tensor, c3: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        points = world_to_camera(m, R, t)  # [N, 3]
        xy = camera_to_pixel(points, *intrinsics)  # [N, 2]
        cov2d = covariance_2d(points, c3, R, intrinsics[0], intrinsics[1], limits)  # [N, 3]
        det = covariance_2d_determinant(points, c3, cov2d, R, intrinsics[0], intrinsics[1], limits)  # [N]
        return xy, points, cov2d, det, alpha_shape(cov2d, det)

    with torch.no_grad():
        xy, points, cov2d, det, shape = screen_space(means, cov3d)
        radius = extent_radius(cov2d)  # [N]
        conic = conic_from_cov2d(cov2d, det)  # [N, 3], for the culling bounds
        keep = keep_mask(points, xy, cov2d, det, conic, shape, radius, float(camera.near), rgb, opacity, cov3d)
        index = torch.nonzero(keep).squeeze(1)  # [M], ascending
        index = index[torch.sort(points[index, 2], stable=True).indices]  # front to back, ties in index order
        # The opacity as composited is faded where the determinant is near its noise (docs/numerics.md,
        # "Reliability fade"). Without gradient, like the radius: the factor is exactly 1 for ordinary splats, and
        # its derivative near the cut divides by the noise.
        fade = reliability_fade(points[index], cov3d[index], cov2d[index], R, intrinsics[0], intrinsics[1], limits)
    needs_grad = torch.is_grad_enabled() and any(x.requires_grad for x in (means, cov3d, rgb, opacity))
    if needs_grad:
        xy_kept, _, _, _, shape_kept = screen_space(means[index], cov3d[index])
    else:
        xy_kept, shape_kept = xy[index], shape[index]
    return _Splats(xy_kept, shape_kept, radius[index], opacity[index] * fade, splat_color(rgb[index]), index)


def _tile_rects(splats: _Splats, grid: _Grid) -> _Rects:
    """Inclusive tile ranges of each splat's pixel box (a superset; pixels test themselves exactly)."""
    xy = splats.xy.detach().double()  # [M, 2]; float64 so u +- r never overflows or rounds inwards
    r = splats.radius.double()  # [M]
    x_lo, x_hi, x_ok = _pixel_span(xy[:, 0], r, grid.width)
    y_lo, y_hi, y_ok = _pixel_span(xy[:, 1], r, grid.height)
    ts = grid.tile_size
    return _Rects(x_lo // ts, x_hi // ts, y_lo // ts, y_hi // ts, x_ok & y_ok)


def _pixel_span(center: Tensor, radius: Tensor, size: int) -> tuple[Tensor, Tensor, Tensor]:
    """Pixel index range [lo, hi] (int64, clipped to the image) whose centres lie within radius, widened by 1."""
    lo = torch.ceil(center - radius - PIXEL_CENTER_OFFSET) - 1  # widened: float32 rounding decides per pixel
    hi = torch.floor(center + radius - PIXEL_CENTER_OFFSET) + 1
    ok = (hi >= 0) & (lo <= size - 1)
    return lo.clamp(0, size - 1).long(), hi.clamp(0, size - 1).long(), ok


def _row_bands(rects: _Rects, grid: _Grid, max_pairs: int) -> list[tuple[int, int]]:
    """Split tile rows into bands [y0, y1] holding at most max_pairs (splat, tile) pairs each (one row at least)."""
    width = torch.where(rects.ok, rects.tx1 - rects.tx0 + 1, 0)  # [M] tiles per covered row
    per_row = torch.zeros(grid.tiles_y + 1, dtype=torch.long, device=width.device)
    per_row = per_row.index_add(0, rects.ty0, width).index_add(0, rects.ty1 + 1, -width)
    per_row = torch.cumsum(per_row, 0)[:-1].tolist()  # pairs in each tile row
    bands, y0, total = [], 0, 0
    for y, pairs in enumerate(per_row):
        if total and total + pairs > max_pairs:
            bands.append((y0, y - 1))
            y0, total = y, 0
        total += pairs
    bands.append((y0, grid.tiles_y - 1))
    return bands


def _bin_band(rects: _Rects, y0: int, y1: int, grid: _Grid) -> _Bins:
    """Per-tile splat lists for the tile rows y0..y1, each list front to back (stable sort on tile id)."""
    device = rects.ok.device
    splat = torch.nonzero(rects.ok & (rects.ty0 <= y1) & (rects.ty1 >= y0)).squeeze(1)  # [S], ascending
    tx0, ty0 = rects.tx0[splat], rects.ty0[splat].clamp_min(y0)
    nx, ny = rects.tx1[splat] - tx0 + 1, rects.ty1[splat].clamp_max(y1) - ty0 + 1
    per_splat = nx * ny  # [S] tiles each splat overlaps in this band
    owner = torch.repeat_interleave(torch.arange(len(splat), device=device), per_splat)  # [pairs], ascending
    first = torch.cumsum(per_splat, 0) - per_splat  # [S]
    local = torch.arange(len(owner), device=device) - first[owner]  # [pairs] rank within the splat's rectangle
    tile = (ty0[owner] + local // nx[owner]) * grid.tiles_x + tx0[owner] + local % nx[owner]  # [pairs]
    tile, order = torch.sort(tile, stable=True)  # stable: each tile's list stays front to back
    count = torch.bincount(tile, minlength=grid.tiles)  # [tiles]
    return _Bins(splat[owner[order]], torch.cumsum(count, 0) - count, count)


def _render_tiles(splats: _Splats, rects: _Rects, grid: _Grid, budget: int, max_weight: Tensor | None = None,
                  counts: list | None = None, alpha_min: float = ALPHA_MIN) -> tuple[Tensor, Tensor]:
    """Composite every non-empty tile, band by band, in padded batches; empty tiles stay colour 0, T 1.
    `max_weight` [M + 1] (the pad last), if given, is raised to each splat's largest blend weight; `counts`, if
    given, gets (tile ids, blended Gaussians per pixel) per batch."""
    device = splats.xy.device
    chunk_elements = max(1, min(_MAX_CHUNK_ELEMENTS, budget // _LIVE_BYTES_PER_ELEMENT))
    params, rgb = _pack_params(splats)
    needs_grad = torch.is_grad_enabled() and (params.requires_grad or rgb.requires_grad)
    pairs = int(torch.where(rects.ok, (rects.tx1 - rects.tx0 + 1) * (rects.ty1 - rects.ty0 + 1), 0).sum())
    use_checkpoint = needs_grad and pairs * grid.pixels * _LIVE_BYTES_PER_ELEMENT > budget
    kwargs = {"params": params, "rgb": rgb, "grid": grid, "chunk_elements": chunk_elements, "max_weight": max_weight,
              "counts": counts, "alpha_min": alpha_min}
    colors, transmittances, done_tiles = [], [], []
    for y0, y1 in _row_bands(rects, grid, max(1, budget // (4 * _PAIR_BYTES))):
        batches = _batch_lists(_bin_band(rects, y0, y1, grid), grid.pixels, chunk_elements, len(splats.radius))
        # Checkpointing a group of batches (recomputed together in backward, within the budget) rather than
        # each batch keeps the number of checkpoint regions, and the heap fragmentation they cause, small.
        for group in _group_batches(batches, grid.pixels, max(1, budget // _LIVE_BYTES_PER_ELEMENT)):
            if use_checkpoint:
                color, trans = checkpoint(
                    _composite_group, group, use_reentrant=False, preserve_rng_state=False, **kwargs
                )
            else:
                color, trans = _composite_group(group, **kwargs)
            colors.append(color)
            transmittances.append(trans)
            done_tiles.extend(tile_ids for tile_ids, _ in group)
    color_all = torch.zeros(grid.tiles, grid.pixels, 3, dtype=rgb.dtype, device=device)
    trans_all = torch.ones(grid.tiles, grid.pixels, dtype=rgb.dtype, device=device)
    if colors:
        ids = torch.cat(done_tiles)
        color_all = color_all.index_copy(0, ids, torch.cat(colors))
        trans_all = trans_all.index_copy(0, ids, torch.cat(transmittances))
    return color_all, trans_all


def _batch_lists(bins: _Bins, pixels: int, chunk_elements: int, sentinel: int) -> list[tuple[Tensor, Tensor]]:
    """(tile ids [B], padded splat lists [B, K]) per batch; padding points at the sentinel splat (opacity 0)."""
    batches = []
    for tile_ids, k in _plan_batches(bins.count, pixels, chunk_elements):
        lists = bins.start[tile_ids].unsqueeze(1) + torch.arange(k, device=tile_ids.device)  # [B, K]
        valid = torch.arange(k, device=tile_ids.device) < bins.count[tile_ids].unsqueeze(1)  # [B, K]
        batches.append((tile_ids, torch.where(valid, bins.splat[torch.where(valid, lists, 0)], sentinel)))
    return batches


def _group_batches(
    batches: list[tuple[Tensor, Tensor]], pixels: int, max_elements: int
) -> list[list[tuple[Tensor, Tensor]]]:
    """Consecutive batches grouped so that each group's padded elements stay within max_elements (one at least)."""
    groups, current, size = [], [], 0
    for tile_ids, splat_ids in batches:
        elements = splat_ids.numel() * pixels
        if current and size + elements > max_elements:
            groups.append(current)
            current, size = [], 0
        current.append((tile_ids, splat_ids))
        size += elements
    return groups + [current] if current else groups


def _composite_group(
    group: list[tuple[Tensor, Tensor]], *, params: Tensor, rgb: Tensor, grid: _Grid, chunk_elements: int,
    max_weight: Tensor | None = None, counts: list | None = None, alpha_min: float = ALPHA_MIN,
) -> tuple[Tensor, Tensor]:
    """Composite each batch of a group; colours [sum B, P, 3] and transmittances [sum B, P] in group order."""
    results = [_composite_batch(t, s, params, rgb, grid=grid, chunk_elements=chunk_elements, max_weight=max_weight,
                                counts=counts, alpha_min=alpha_min) for t, s in group]
    return torch.cat([color for color, _ in results]), torch.cat([trans for _, trans in results])


def _pack_params(splats: _Splats) -> tuple[Tensor, Tensor]:
    """Per-splat scalars as rows (u, v, A, k, q, opacity, r) [7, M+1] and rgb [M+1, 3]; entry M pads (opacity 0)."""
    pad = torch.zeros(7, 1, dtype=splats.rgb.dtype, device=splats.rgb.device)
    params = torch.cat(
        [splats.xy.T, splats.shape.T, splats.opacity.unsqueeze(0), splats.radius.unsqueeze(0)], dim=0
    )  # [7, M]
    rgb = torch.cat([splats.rgb, pad[:3].T], dim=0)  # [M+1, 3]
    return torch.cat([params, pad], dim=1), rgb


def _plan_batches(count: Tensor, pixels: int, chunk_elements: int) -> list[tuple[Tensor, int]]:
    """Group non-empty tiles, longest lists first, into batches of (tile ids, padded list length K)."""
    order = torch.sort(count, descending=True, stable=True).indices
    order = order[count[order] > 0]
    sizes = count[order].tolist()
    batches, i = [], 0
    while i < len(sizes):
        k = sizes[i]
        max_tiles = max(1, chunk_elements // (pixels * min(k, max(1, chunk_elements // pixels))))
        j = i + 1
        while j < len(sizes) and j - i < max_tiles and sizes[j] >= _MIN_FILL * k:
            j += 1
        batches.append((order[i:j], k))
        i = j
    return batches


def _composite_batch(
    tile_ids: Tensor, splat_ids: Tensor, params: Tensor, rgb: Tensor, *, grid: _Grid, chunk_elements: int,
    max_weight: Tensor | None = None, counts: list | None = None, alpha_min: float = ALPHA_MIN,
) -> tuple[Tensor, Tensor]:
    """Front-to-back compositing of B tiles' padded lists [B, K], walked in K chunks that carry T and `done`."""
    ts = grid.tile_size
    local = torch.arange(grid.pixels, device=rgb.device)  # [P]
    px = ((tile_ids % grid.tiles_x).unsqueeze(1) * ts + local % ts).float() + PIXEL_CENTER_OFFSET  # [B, P]
    py = ((tile_ids // grid.tiles_x).unsqueeze(1) * ts + local // ts).float() + PIXEL_CENTER_OFFSET
    px, py = px.unsqueeze(-1), py.unsqueeze(-1)  # [B, P, 1] pixel centres
    n_tiles, k_total = splat_ids.shape
    pixels = px.shape[1]
    k_chunk = max(1, min(k_total, chunk_elements // (n_tiles * pixels)))
    color = torch.zeros(n_tiles, pixels, 3, dtype=rgb.dtype, device=rgb.device)  # [B, P, 3]
    trans = torch.ones(n_tiles, pixels, dtype=rgb.dtype, device=rgb.device)  # [B, P]
    done = torch.zeros(n_tiles, pixels, dtype=torch.bool, device=rgb.device)  # [B, P] stopped by T_MIN
    blended = torch.zeros(n_tiles, pixels, 2, dtype=torch.int64, device=rgb.device) if counts is not None else None
    for k0 in range(0, k_total, k_chunk):
        ids = splat_ids[:, k0 : k0 + k_chunk]  # [B, k]
        u, v, a, slope, q, opacity, r = params[:, ids].unsqueeze(2).unbind(0)  # each [B, 1, k]
        dx = px - u  # [B, P, k] pixel centre - projected centre
        dy = py - v
        inside = torch.maximum(dx.abs(), dy.abs()) <= r  # [B, P, k] the contract's exact per-pixel extent
        # Offsets clamped to the extent: unchanged inside, and keep_mask's bound keeps the power finite outside.
        dx, dy = torch.clamp(dx, -r, r), torch.clamp(dy, -r, r)
        alpha = alpha_from_components(dx, dy, a, slope, q, opacity, inside, alpha_min)  # [B, P, k], 0 = skipped
        color, trans, done, weight = _blend_chunk(alpha, rgb[ids], color, trans, done)
        if max_weight is not None:
            with torch.no_grad():
                max_weight.scatter_reduce_(0, ids.reshape(-1), weight.amax(1).reshape(-1), "amax")
        if blended is not None:  # blended at all; blended while T >= 1/255 (weight = alpha T >= alpha / 255)
            w = weight.detach()
            blended[..., 0] += torch.count_nonzero(w > 0, dim=-1)
            blended[..., 1] += torch.count_nonzero((w > 0) & (255.0 * w >= alpha.detach()), dim=-1)
        if bool(done.all()):
            break
    if counts is not None:
        counts.append((tile_ids, blended))
    return color, trans


def _blend_chunk(
    alpha: Tensor, rgb: Tensor, color: Tensor, trans: Tensor, done: Tensor
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Blend one chunk [B, P, k] (alpha 0 = skipped) onto carried colour/T; the kept set is a prefix since T falls.
    Returns colour, T, done and the blend weights alpha_i T_i [B, P, k]."""
    start = torch.where(done, 0.0, trans)  # a stopped pixel takes nothing more
    t_seq = torch.cumprod(torch.cat([start.unsqueeze(-1), 1.0 - alpha], dim=-1), dim=-1)  # [B, P, k+1]
    with torch.no_grad():
        # 3DGS: test_T = T * (1 - alpha); if test_T < T_MIN the pixel stops before this Gaussian.
        include = t_seq[..., 1:] >= TRANSMITTANCE_MIN  # [B, P, k], a prefix since T never grows
        n_included = torch.count_nonzero(include, dim=-1).unsqueeze(-1)  # [B, P, 1]
    weight = alpha * t_seq[..., :-1] * include  # [B, P, k] alpha_i T_i on the included prefix
    color = color + torch.bmm(rgb.transpose(1, 2), weight.transpose(1, 2)).transpose(1, 2)  # [B, P, 3]
    trans = torch.where(done, trans, t_seq.gather(-1, n_included).squeeze(-1))  # [B, P] T after the prefix
    return color, trans, done | (t_seq[..., -1] < TRANSMITTANCE_MIN), weight


def _untile(values: Tensor, grid: _Grid) -> Tensor:
    """[tiles, P, ...] in row-major tile order -> [tiles_y * ts, tiles_x * ts, ...] image layout."""
    ts, rest = grid.tile_size, values.shape[2:]
    tiled = values.reshape(grid.tiles_y, grid.tiles_x, ts, ts, *rest)
    return tiled.transpose(1, 2).reshape(grid.tiles_y * ts, grid.tiles_x * ts, *rest)
