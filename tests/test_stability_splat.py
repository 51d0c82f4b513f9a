"""Splatting stage at the extremes: the torch reference rasterizer against the OpenGL runtime splatter (and, for the
scale and rotation sweep and the pinned cull-boundary cases, the CPU tile splatter too).

Every case renders the same float32 Gaussians with `render_reference` (torch) and `GLSplatter.render(...,
output="float")` (GL), where named also `CPUSplatter.render` (CPU), and checks: no NaN/Inf in any pixel on either
side; the frames agree; each Gaussian of the case, rendered alone, is drawn by both sides or by neither (a cull on
one side only is a disagreement, unless every pixel it draws is a threshold flip, below); and the GL context
survives: after the case, a normal scene renders bit-identically to a fresh splatter's render. Each case's
observed numbers go into the stability table.

Bound, and why: max |torch - GL| <= ABS_TOL + c * (REL_TOL + COND_TOL * k), c the largest colour magnitude in the
case (at least 1), k the largest rounding_products/det of its screen covariances (1 for a round splat; see
COND_TOL and `conditioning`), plus a threshold-flip term at the few pixels where one is possible (below).
Both sides evaluate the same float32 formulas in a different order (torch tensor ops vs the GLSL compiler), so
what remains is a few float32 roundings per contribution, ~1e-7 of the colour for ordinary splats and up to 7e-6
measured here on colours <= 1.2 (the worst: needles and grazing view angles, whose conditioning amplifies a
rounding). ABS_TOL = 1e-4 leaves >10x margin over that; REL_TOL = 1e-6 (~16 ulps of c) covers colours far beyond
1 (SH 1e3..1e30, measured ~1.3e-7 of c), where rounding is relative to c. Scenes keep opacity <= 0.7 (or two
Gaussians at most at alpha 0.99), so transmittance never reaches the contract's 1e-4 stop that fixed-function
blending cannot make.

Threshold flips: a contribution is skipped when its alpha is below ALPHA_MIN = 1/255, a threshold on a rounded
value, so where one Gaussian's alpha at a pixel lies within the sides' rounding of 1/255 one side adds it and
another skips it. The term `flip_allowance` models that, per Gaussian and pixel, around torch's own values:
* Which alphas a side can compute: alpha = opacity * w * exp(power). The sides' rho = det / (DET_MIN_RELATIVE
  noise) of `determinant_and_noise` differ by at most d_rho = FLIP_ULPS * 2^-24 / DET_MIN_RELATIVE, FLIP_ULPS ulps
  of the noise (measured between torch and GL: up to 5.4 ulps, 99 % below 3.2, over 12k Gaussians with rho < 300;
  FLIP_ULPS = 8), so w = `reliability_fade` lies in [w(rho - d_rho), w(rho + d_rho)]. The determinant's relative
  error is then d_rho / rho, and the power's is taken as 3 d_rho / rho (a and c are off by at most twice the
  determinant's relative error, since rounding_products bounds their noise, and A = c / det); the power is <= 0
  on every side, so it lies in [power (1 + 3 d_rho / rho), min(0, power (1 - 3 d_rho / rho))]. exp and the
  products add at most EXP_TOL = 2^-16 relatively (the CPU splatter's polynomial exp is within 3.5e-6). A flip is
  possible where that interval of alphas holds ALPHA_MIN, inside the extent.
* What it changes: skipping a contribution of alpha at a pixel whose transmittance in front of it is T changes the
  pixel by T alpha (rgb - R), R the composite behind it (a convex combination of later colours and the
  background), so by at most alpha * spread, spread the largest per-channel range of the case's colours and the
  background. The term is that, alpha the interval's top (at most ALPHA_MAX), at each pixel where a flip is
  possible: ALPHA_MIN * spread to within 1e-4 for ordinary splats, and up to about twice that near the cut
  (rho < ~5), where w's interval is relatively wide.
Everywhere else the bound above is unchanged. The extent edge (|dx| = r) is a threshold too, but a pixel centre
lies within the radius's rounding of it with probability ~1e-7 per pixel: not modelled (no such flip in the heavy
sweep's 20,000 cases, where 2 pixels needed the threshold-flip term).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import pytest
import torch
from hypothesis import example, given, settings
from hypothesis import strategies as st

from gaussiantalker.exporter.model.rasterizer import render_reference
from gaussiantalker.exporter.model.splat_math import (
    alpha_shape,
    camera_to_pixel,
    clamped_ratios,
    conic_from_cov2d,
    cov3d_from_rotation_scale,
    covariance_2d,
    covariance_2d_determinant,
    determinant_and_noise,
    extent_radius,
    keep_mask,
    quat_to_rotmat,
    rounding_products,
    sh_to_rgb,
    sigma_matrix,
    world_to_camera,
)
from gaussiantalker.runtime.splat.cpu import CPUSplatter
from gaussiantalker.runtime.splat.gl import GLSplatter
from gaussiantalker.sdk.camera import Camera
from gaussiantalker.sdk.errors import CameraError
from gaussiantalker.sdk.numerics import ALPHA_MAX, ALPHA_MIN, COLOR_LIMIT, DET_MIN_RELATIVE, LOW_PASS_PX2

BACKGROUND = (0.2, 0.4, 0.1)
ABS_TOL = 1e-4
REL_TOL = 1e-6
# Both sides round a, b, c of the screen covariance to float32 in different orders, each entry to a few ulps of
# its magnitude (the sum of its terms' absolute values, far above the entry where the terms cancel); the
# determinant a*c - b^2 and hence the conic carry that error times k = rounding_products / det (`conditioning`).
# 2^-24 (one ulp) per unit of k adds < 6e-6 for any splat with k < 100 (all ordinary ones) and bounds slabs seen
# nearly edge-on (the pinned k = 5.7e5 gives 3.4e-2; measured 3.1e-3).
COND_TOL = 2.0**-24
# Threshold flips (see the module docstring): the sides' rho differ by at most FLIP_ULPS ulps of the determinant's
# noise (measured up to 5.4), and exp and the alpha products by at most EXP_TOL relatively.
FLIP_ULPS = 8.0
EXP_TOL = 2.0**-16
FEW = settings(derandomize=True, max_examples=8, deadline=None)
# The scale and rotation sweep draws its cases from a seeded numpy generator, so they never depend on what else is
# loaded (Hypothesis mines constants from every loaded module, derandomized or not): the quick run checks the first
# SWEEP_CASES of the sequence, the heavy run (GT_HEAVY=1) the first HEAVY_SWEEP_CASES.
SWEEP_SEED = 20250
SWEEP_CASES = 400
HEAVY_SWEEP_CASES = 20000

Scene = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]  # means [N, 3], cov3d [N, 6], rgb [N, 3], opacity [N]


# -- scenes ------------------------------------------------------------------------------------------------------


def rotation(angles: tuple[float, float, float]) -> np.ndarray:
    """Rotation about x, then y, then z by the given angles (radians). # [3, 3]"""
    ax, ay, az = angles
    rx = np.array([[1, 0, 0], [0, math.cos(ax), -math.sin(ax)], [0, math.sin(ax), math.cos(ax)]])
    ry = np.array([[math.cos(ay), 0, math.sin(ay)], [0, 1, 0], [-math.sin(ay), 0, math.cos(ay)]])
    rz = np.array([[math.cos(az), -math.sin(az), 0], [math.sin(az), math.cos(az), 0], [0, 0, 1]])
    return rz @ ry @ rx


def normal_camera(width: int = 32, height: int = 24) -> Camera:
    """A rotated, translated camera with fx != fy and an off-centre principal point."""
    return Camera(width, height, 1.1 * width, 1.0 * width, 0.45 * width, 0.55 * height,
                  rotation((0.2, 0.3, 0.05)), np.array([0.1, -0.05, 3.0]))


def covariances(scales, quats) -> np.ndarray:
    """Packed world covariances from per-axis scales [N, 3] and (w, x, y, z) quaternions [N, 4], as the exporter."""
    rot = quat_to_rotmat(torch.as_tensor(np.asarray(quats, np.float32)))
    return cov3d_from_rotation_scale(rot, torch.as_tensor(np.asarray(scales, np.float32))).numpy()


def scene_of(means, cov3d, rgb, opacity) -> Scene:
    """Four float32 arrays, the inputs both renderers take."""
    return tuple(np.asarray(x, np.float32).reshape(shape) for x, shape in
                 zip((means, cov3d, rgb, opacity), ((-1, 3), (-1, 6), (-1, 3), (-1,)), strict=True))


def join(*scenes: Scene) -> Scene:
    """Concatenate scenes Gaussian-wise."""
    return tuple(np.concatenate(parts) for parts in zip(*scenes, strict=True))


def normal_scene(seed: int = 0, n: int = 6) -> Scene:
    """n ordinary Gaussians around the world origin (in front of normal_camera), opacity <= 0.7."""
    rng = np.random.default_rng(seed)
    scales = np.exp(rng.uniform(math.log(0.02), math.log(0.3), (n, 3)))
    return scene_of(rng.normal(0.0, 0.4, (n, 3)), covariances(scales, rng.normal(size=(n, 4))),
                    rng.uniform(0.0, 1.2, (n, 3)), rng.uniform(0.2, 0.7, n))


def at_pixel(camera: Camera, u: float, v: float, depth: float, sigma_px: float, **kwargs) -> Scene:
    """One isotropic Gaussian whose centre projects to continuous pixel (u, v) at camera depth, ~sigma_px wide."""
    p_cam = np.array([(u - camera.cx) / camera.fx * depth, (v - camera.cy) / camera.fy * depth, depth])
    world = camera.R.T @ (p_cam - camera.t)
    scale = sigma_px * depth / math.sqrt(camera.fx * camera.fy)
    return scene_of(world, covariances([[scale] * 3], [kwargs.get("quat", (1, 0, 0, 0))]),
                    kwargs.get("rgb", (1.0, 0.5, 0.2)), kwargs.get("opacity", 0.7))


def spread_over_image(camera: Camera, seed: int, n: int = 4) -> Scene:
    """n Gaussians centred on pixels spread over the image, 0.5..W/4 px wide: visible through any lens."""
    rng = np.random.default_rng(seed)
    top = max(1.0, max(camera.width, camera.height) / 4.0)
    return join(*(at_pixel(camera, rng.uniform(0, camera.width), rng.uniform(0, camera.height),
                           rng.uniform(1.0, 4.0), rng.uniform(0.5, top),
                           rgb=rng.uniform(0.0, 1.2, 3), opacity=rng.uniform(0.2, 0.7)) for _ in range(n)))


# -- the two renderers and the checks ----------------------------------------------------------------------------


@pytest.fixture(scope="module")
def splatter():
    """One splatter (and GL context) shared by every case, as an app would keep it."""
    instance = GLSplatter()
    yield instance
    instance.release()


@pytest.fixture(scope="module")
def cpu_splatter():
    """The CPU tile splatter, for the cases that check it too."""
    instance = CPUSplatter()
    yield instance
    instance.release()


@pytest.fixture(scope="module")
def baseline():
    """The normal scene rendered by a fresh splatter with its own context (the context-survival reference)."""
    fresh = GLSplatter()
    try:
        return fresh.render(*normal_scene(), normal_camera(), BACKGROUND, output="float")
    finally:
        fresh.release()


def render_torch(scene: Scene, camera: Camera) -> np.ndarray:
    """The torch reference frame C + T * background. # [H, W, 3] float32"""
    with torch.no_grad():
        frame, _ = render_reference(*(torch.from_numpy(x) for x in scene), camera, BACKGROUND)
    return frame.numpy()


def render_gl(splatter: GLSplatter, scene: Scene, camera: Camera) -> np.ndarray:
    """The GL runtime float frame. # [H, W, 3] float32"""
    return splatter.render(*scene, camera, BACKGROUND, output="float")


def conditioning(scene: Scene, camera: Camera) -> float:
    """Largest rounding_products / det of the kept Gaussians' screen covariances (a, b, c), in float64 with the
    entries' magnitudes (the quadratic forms over |J W| and |Sigma|): how much float32 rounding of (a, b, c) is
    amplified in the determinant and conic (1 for round splats, ~1e5 for a screen-crossing needle, more where the
    entries themselves cancel: a slab seen edge-on)."""
    R = torch.tensor(camera.R, dtype=torch.float64)
    t = torch.tensor(camera.t, dtype=torch.float64)
    means, cov3d = torch.from_numpy(scene[0]).double(), torch.from_numpy(scene[1]).double()
    points = world_to_camera(means, R, t)
    limits = camera.fov_clamp_limits()
    cov2d = covariance_2d(points, cov3d, R, camera.fx, camera.fy, limits)
    xz, yz = clamped_ratios(points, limits).unbind(-1)
    z, zero = points[:, 2], torch.zeros_like(points[:, 2])
    j = torch.stack([torch.stack([camera.fx / z, zero, -camera.fx * xz / z], -1),
                     torch.stack([zero, camera.fy / z, -camera.fy * yz / z], -1)], -2)  # [N, 2, 3]
    rows = (j @ R).abs()
    magnitude = rows @ sigma_matrix(cov3d).abs() @ rows.transpose(-1, -2)  # [N, 2, 2]
    magnitude = torch.stack([magnitude[:, 0, 0] + LOW_PASS_PX2, magnitude[:, 0, 1],
                             magnitude[:, 1, 1] + LOW_PASS_PX2], -1)
    a, b, c = cov2d.unbind(-1)
    ratio = rounding_products(cov2d, magnitude) / (a * c - b * b)
    ratio = ratio[torch.isfinite(ratio) & (ratio > 0) & (points[:, 2] >= camera.near)]
    return float(ratio.max()) if ratio.numel() else 1.0


def tolerance(scene: Scene, camera: Camera) -> float:
    """ABS_TOL + c * (REL_TOL + COND_TOL * conditioning): see the module docstring."""
    rgb = np.abs(scene[2][np.isfinite(scene[2])])
    c = max(1.0, float(np.minimum(rgb, COLOR_LIMIT).max(initial=0.0)))
    return ABS_TOL + c * (REL_TOL + COND_TOL * conditioning(scene, camera))


def torch_splats(scene: Scene, camera: Camera) -> dict[str, np.ndarray]:
    """Each Gaussian as the torch reference projects it, in float32 (the contract's functions, as
    `render_reference` calls them): kept, centre [N, 2], alpha_shape [N, 3], radius, and rho = det /
    (DET_MIN_RELATIVE noise) of `determinant_and_noise` (inf where the noise underflowed)."""
    means, cov3d, rgb, opacity = (torch.from_numpy(x) for x in scene)
    R = torch.as_tensor(camera.R, dtype=torch.float32)
    t = torch.as_tensor(camera.t, dtype=torch.float32)
    fx, fy, cx, cy = (float(v) for v in (camera.fx, camera.fy, camera.cx, camera.cy))
    limits = camera.fov_clamp_limits()
    with torch.no_grad():
        points = world_to_camera(means, R, t)
        xy = camera_to_pixel(points, fx, fy, cx, cy)
        cov2d = covariance_2d(points, cov3d, R, fx, fy, limits)
        det = covariance_2d_determinant(points, cov3d, cov2d, R, fx, fy, limits)
        raw, noise = determinant_and_noise(points, cov3d, cov2d, R, fx, fy, limits).double().unbind(-1)
        shape, radius = alpha_shape(cov2d, det), extent_radius(cov2d)
        keep = keep_mask(points, xy, cov2d, det, conic_from_cov2d(cov2d, det), shape, radius, float(camera.near),
                         rgb, opacity, cov3d)
        rho = torch.where(noise > 0, raw / (DET_MIN_RELATIVE * noise), torch.full_like(raw, math.inf))
    return {"keep": keep.numpy(), "xy": xy.numpy(), "shape": shape.numpy(), "radius": radius.numpy(),
            "rho": rho.numpy()}


def colour_spread(scene: Scene) -> float:
    """The largest per-channel range of the case's (clamped, finite) colours and the background."""
    rgb = np.clip(scene[2], -COLOR_LIMIT, COLOR_LIMIT).astype(np.float64)
    values = np.concatenate([rgb[np.isfinite(rgb).all(axis=1)], [BACKGROUND]])
    return float((values.max(axis=0) - values.min(axis=0)).max())


def fade_of(rho: float) -> float:
    """`reliability_fade` of a given rho, in float64."""
    return -math.expm1(-ALPHA_MIN * (rho - 1.0)) if rho > 1.0 else 0.0


def flip_allowance(scene: Scene, camera: Camera) -> np.ndarray:
    """Per Gaussian and pixel, what an alpha >= ALPHA_MIN threshold flip can add to |torch - other side| (0 where
    none is possible): spread times the largest alpha a side can compute there, where the interval of alphas the
    sides can compute holds ALPHA_MIN (the module docstring derives it). # [N, H, W] float64"""
    splats = torch_splats(scene, camera)
    allowance = np.zeros((len(scene[0]), camera.height, camera.width))
    spread = colour_spread(scene)
    d_rho = FLIP_ULPS * 2.0**-24 / DET_MIN_RELATIVE
    for i in np.flatnonzero(splats["keep"]):
        u, v = splats["xy"][i].astype(np.float64)
        a, k, q = splats["shape"][i].astype(np.float64)
        r, rho, opacity = float(splats["radius"][i]), float(splats["rho"][i]), float(scene[3][i])
        x0, x1 = max(0, math.floor(u - r - 1.0)), min(camera.width, math.ceil(u + r + 1.0))  # the extent's pixels
        y0, y1 = max(0, math.floor(v - r - 1.0)), min(camera.height, math.ceil(v + r + 1.0))
        fade_hi, fade_lo = fade_of(rho + d_rho), fade_of(rho - d_rho)
        if x0 >= x1 or y0 >= y1 or not opacity * fade_hi * math.exp(EXP_TOL) >= ALPHA_MIN:
            continue
        dx = (np.arange(x0, x1) + 0.5 - u)[None, :]
        dy = (np.arange(y0, y1) + 0.5 - v)[:, None]
        power = -0.5 * (a * (dx - k * dy) ** 2 + q * dy * dy)  # <= 0 on every side
        slack = 3.0 * d_rho / rho  # the power's relative difference between sides
        with np.errstate(divide="ignore", over="ignore", invalid="ignore"):
            log_hi = math.log(opacity * fade_hi) + np.minimum(power * (1.0 - slack), 0.0) + EXP_TOL
            log_lo = math.log(opacity * fade_lo) + power * (1.0 + slack) - EXP_TOL if fade_lo > 0 else -math.inf
            near = ((np.maximum(np.abs(dx), np.abs(dy)) <= r) & (log_lo <= math.log(ALPHA_MIN))
                    & (math.log(ALPHA_MIN) <= log_hi))
        log_hi = np.broadcast_to(log_hi, near.shape)
        allowance[i, y0:y1, x0:x1][near] = np.minimum(np.exp(log_hi[near]), ALPHA_MAX) * spread
    return allowance


def subset(scene: Scene, index) -> Scene:
    """Gaussians `index` of a scene."""
    return tuple(x[index] for x in scene)


@dataclass
class Outcome:
    """What one case did on both sides (and on the CPU splatter, where it was checked)."""

    error: float  # max |torch - GL| over the frame
    drawn: list[bool]  # per Gaussian: drawn when rendered alone (the same on both sides, or the check failed)
    torch_frame: np.ndarray
    gl_frame: np.ndarray
    flips: int = 0  # pixels (over the sides compared) whose difference needed the threshold-flip term
    cpu_error: float | None = None  # max |torch - CPU|
    cpu_frame: np.ndarray | None = None

    def describe(self) -> str:
        """The observed behaviour, for the stability table (Gaussian 0 is the case's; any others its neighbours)."""
        sides = "both sides" if self.cpu_error is None else "all three sides"
        fate = f"drawn by {sides}" if self.drawn[0] else f"culled on {sides}"
        if len(self.drawn) > 1:
            neighbours = f"{sum(self.drawn[1:])} of {len(self.drawn) - 1} neighbours drawn by both"
            fate = f"the case's Gaussian {fate}, {neighbours}"
        errors = f"torch vs GL max abs {self.error:.1e}"
        if self.cpu_error is not None:
            errors += f", vs CPU {self.cpu_error:.1e}"
        return f"finite on {sides}; {fate}; {errors}"


def is_drawn(frame: np.ndarray) -> bool:
    """Whether anything but the background reached the frame."""
    return bool(np.any(frame != np.asarray(BACKGROUND, np.float32)))


def check_agreement(torch_frame: np.ndarray, frame: np.ndarray, bound: float, allowance: np.ndarray, name: str
                    ) -> tuple[float, int]:
    """Assert |torch - frame| <= bound + the pixel's threshold-flip terms (`allowance` [N, H, W]) everywhere;
    return the max abs difference and how many pixels needed the flip term."""
    assert np.isfinite(frame).all(), f"NaN/Inf in the {name} frame"
    difference = np.abs(torch_frame.astype(np.float64) - frame)
    pixel_bound = bound + allowance.sum(axis=0)[..., None]  # [H, W, 1]
    worst = np.unravel_index(int(np.argmax(difference - pixel_bound)), difference.shape)
    assert (difference <= pixel_bound).all(), (
        f"torch vs {name} max abs {float(difference.max()):.3g}; at pixel {worst[:2]} {difference[worst]:.3g} > "
        f"{bound:.3g} + threshold flips {float(pixel_bound[worst[:2]][0] - bound):.3g}")
    return float(difference.max()), int(np.any(difference > bound, axis=-1).sum())


def same_fate(torch_frame: np.ndarray, other: np.ndarray, flip_pixels: np.ndarray, name: str) -> bool:
    """Whether one Gaussian rendered alone was drawn; asserts both sides agree, unless the side that drew it drew
    only threshold-flip pixels (`flip_pixels` [H, W] bool), which then counts as not drawn."""
    changed = [np.any(frame != np.asarray(BACKGROUND, np.float32), axis=-1) for frame in (torch_frame, other)]
    if changed[0].any() == changed[1].any():
        return bool(changed[0].any())
    drew = changed[0] if changed[0].any() else changed[1]
    assert not (drew & ~flip_pixels).any(), (
        f"culled on one side only: torch drew {int(changed[0].sum())} pixels, {name} {int(changed[1].sum())}, "
        f"{int((drew & ~flip_pixels).sum())} of them no threshold flip")
    return False


def compare(splatter: GLSplatter, scene: Scene, camera: Camera, cpu: CPUSplatter | None = None) -> Outcome:
    """Render on both sides (and the CPU splatter, if given); assert finite pixels, agreement within `tolerance`
    plus `flip_allowance`, the same culls Gaussian by Gaussian."""
    torch_frame = render_torch(scene, camera)
    others = {"GL": lambda s: render_gl(splatter, s, camera)}
    if cpu is not None:
        others["CPU"] = lambda s: cpu.render(*s, camera, BACKGROUND, output="float")
    frames = {name: render(scene) for name, render in others.items()}
    assert np.isfinite(torch_frame).all(), "NaN/Inf in the torch frame"
    bound = tolerance(scene, camera)
    allowance = flip_allowance(scene, camera)  # [N, H, W]
    errors, flips = {}, 0
    for name, frame in frames.items():
        errors[name], flipped = check_agreement(torch_frame, frame, bound, allowance, name)
        flips += flipped
    drawn = []
    for i in range(len(scene[0])):
        alone = scene if len(scene[0]) == 1 else subset(scene, [i])
        torch_alone = torch_frame if len(scene[0]) == 1 else render_torch(alone, camera)
        fates = [same_fate(torch_alone, frames[name] if len(scene[0]) == 1 else render(alone), allowance[i] > 0,
                           name) for name, render in others.items()]
        drawn.append(all(fates))
    return Outcome(errors["GL"], drawn, torch_frame, frames["GL"], flips, errors.get("CPU"), frames.get("CPU"))


def assert_context_survives(splatter: GLSplatter, baseline: np.ndarray) -> None:
    """After an extreme case, the normal scene renders exactly as a fresh splatter rendered it."""
    np.testing.assert_array_equal(render_gl(splatter, normal_scene(), normal_camera()), baseline)


def run_case(splatter: GLSplatter, baseline: np.ndarray, scene: Scene, camera: Camera,
             cpu: CPUSplatter | None = None) -> Outcome:
    """compare(), then the context-survival check."""
    outcome = compare(splatter, scene, camera, cpu)
    assert_context_survives(splatter, baseline)
    return outcome


def summarise(outcomes: list[Outcome]) -> str:
    """One table row for a property-based test: examples, how many Gaussians drawn/culled, the worst errors and how
    many pixels needed the threshold-flip term."""
    drawn = sum(sum(o.drawn) for o in outcomes)
    total = sum(len(o.drawn) for o in outcomes)
    worst = max(o.error for o in outcomes)
    cpu = [o.cpu_error for o in outcomes if o.cpu_error is not None]
    errors = f"torch vs GL max abs {worst:.1e}" + (f", vs CPU {max(cpu):.1e}" if cpu else "")
    flips = sum(o.flips for o in outcomes)
    flipped = f"; {flips} pixels within the threshold-flip term" if flips else ""
    sides, each = ("all three sides", "all") if cpu else ("both sides", "both")
    return (f"{len(outcomes)} examples: finite on {sides}; {drawn} of {total} Gaussians drawn by {sides}, "
            f"the rest culled by {each}; {errors}{flipped}")


def collect(check: Callable[..., Outcome]) -> Callable[..., Outcome]:
    """Wrap a per-example check so its outcomes are kept (read back with `check.outcomes`)."""
    outcomes: list[Outcome] = []

    def wrapped(*args, **kwargs) -> Outcome:
        outcome = check(*args, **kwargs)
        outcomes.append(outcome)
        return outcome

    wrapped.outcomes = outcomes
    return wrapped


# -- Gaussians ---------------------------------------------------------------------------------------------------


def one_in_company(camera: Camera, extreme: Scene) -> Scene:
    """The extreme Gaussian(s) first, then two ordinary ones: an extreme one must not disturb its neighbours."""
    return join(extreme, at_pixel(camera, 8.3, 7.6, 2.5, 2.0), at_pixel(camera, 22.2, 15.1, 3.5, 3.0))


@pytest.mark.parametrize("scale", [0.0, 1e-30, 1e-12])
def test_vanishing_scale_is_the_low_pass_dot(splatter, baseline, stability, scale):
    camera = normal_camera()
    extreme = at_pixel(camera, 16.4, 12.3, 2.0, 1.0)
    extreme = scene_of(extreme[0], covariances([[scale] * 3], [(0.3, 0.1, -0.5, 0.8)]), extreme[2], extreme[3])
    outcome = run_case(splatter, baseline, one_in_company(camera, extreme), camera)
    assert outcome.drawn[0]  # the 0.3 px^2 low-pass filter keeps a one-pixel dot
    stability.record("gaussians", f"scale {scale:g} m (low-pass dot)", outcome.describe())


@pytest.mark.parametrize("scale", [1e3, 1e6])
def test_huge_scale_covers_the_screen(splatter, baseline, stability, scale):
    camera = normal_camera()
    extreme = at_pixel(camera, 16.4, 12.3, 2.0, 1.0)
    extreme = scene_of(extreme[0], covariances([[scale, 0.5 * scale, 2 * scale]], [(0.9, 0.2, 0.1, -0.3)]),
                       extreme[2], extreme[3])
    outcome = run_case(splatter, baseline, one_in_company(camera, extreme), camera)
    for alone in (render_torch(extreme, camera), render_gl(splatter, extreme, camera)):
        assert (np.abs(alone - np.asarray(BACKGROUND, np.float32)).max(axis=2) > 0.1).all()  # every pixel covered
    stability.record("gaussians", f"scale {scale:g} m (splat bigger than the screen)",
                     outcome.describe() + "; covers every pixel")


# Pinned cases of the scale and rotation sweep, checked before its seeded ones.
PINNED_SCALES_AND_ROTATIONS = [
    ((-40.0, -40.0, 19.0), (0.3, 0.5, -0.2, 0.7)),  # a needle far longer than any screen, 1e-40 thin
    ((18.0, 18.0, 18.0), (1.0, 0.0, 0.0, 0.0)),  # 2D covariance near float32 max: products overflow
    ((5.0, 0.0, 0.0), (0.0, 0.0625, 0.0, -0.5)),  # 1e5 m x 1 m needle: its det is rounding noise, culled
    ((3.0, -1.0, 0.0), (0.0625, 1.0, 0.0, 0.25)),  # a slab nearly edge-on: k = 5.7e5, faded below ALPHA_MIN
    ((3.5, -1.0, 0.0), (0.111328125, 0.625, 0.0, 0.3125)),  # det within rounding: culled by both sides
]


def scales_and_rotations(count: int) -> list[tuple[tuple[float, ...], tuple[float, ...]]]:
    """The first `count` cases of the seeded sweep: log10 scales uniform in [-40, 19.5] per axis (1e-40 m to
    3e19 m, past float32's covariance range), quaternion components uniform in [-1, 1]."""
    rng = np.random.default_rng(SWEEP_SEED)
    cases = []
    for _ in range(count):
        log_scales, quat = rng.uniform(-40.0, 19.5, 3), rng.uniform(-1.0, 1.0, 4)
        cases.append((tuple(float(e) for e in log_scales), tuple(float(c) for c in quat)))
    return cases


def one_gaussian(camera: Camera, log_scales, quat) -> Scene:
    """The sweep's Gaussian: centred on pixel (15, 11) at depth 2, its scales 10^log_scales m, rotated by quat."""
    extreme = at_pixel(camera, 15.0, 11.0, 2.0, 1.0)
    return scene_of(extreme[0], covariances([[10.0**e for e in log_scales]], [quat]), extreme[2], extreme[3])


def sweep_scales_and_rotations(splatter, cpu_splatter, baseline, cases) -> list[Outcome]:
    """Each case alone through torch, GL and the CPU splatter (`run_case`); the case is named on a failure."""
    camera = normal_camera()
    outcomes = []
    for log_scales, quat in cases:
        try:
            outcomes.append(run_case(splatter, baseline, one_gaussian(camera, log_scales, quat), camera,
                                     cpu_splatter))
        except AssertionError as error:
            raise AssertionError(f"log10 scales {log_scales}, quaternion {quat}: {error}") from error
    return outcomes


def test_scale_and_rotation_range(splatter, cpu_splatter, baseline, stability):
    outcomes = sweep_scales_and_rotations(splatter, cpu_splatter, baseline,
                                          PINNED_SCALES_AND_ROTATIONS + scales_and_rotations(SWEEP_CASES))
    stability.record("gaussians", f"scales 1e-40..3e19 m per axis, random quaternions (incl. needles): "
                     f"{len(PINNED_SCALES_AND_ROTATIONS)} pinned + {SWEEP_CASES} seeded, torch vs GL and CPU",
                     summarise(outcomes))


@pytest.mark.heavy
def test_scale_and_rotation_range_heavy_sweep(splatter, cpu_splatter, baseline, stability):
    """The same sweep over HEAVY_SWEEP_CASES seeded cases (10 to 15 minutes on 2 cores)."""
    outcomes = sweep_scales_and_rotations(splatter, cpu_splatter, baseline, scales_and_rotations(HEAVY_SWEEP_CASES))
    stability.record("gaussians", f"scales 1e-40..3e19 m per axis, random quaternions: {HEAVY_SWEEP_CASES} seeded "
                     "(heavy run), torch vs GL and CPU", summarise(outcomes))


def test_the_agreement_checks_can_fail():
    """The flip term is local: a pixel skipped at the threshold passes, three times that fails, an ordinary
    difference elsewhere fails, and a Gaussian drawn on one side only fails."""
    camera = normal_camera()
    threshold = at_pixel(camera, 15.5, 11.5, 2.0, 1.5, opacity=ALPHA_MIN * (1.0 + 1e-6))  # alpha 1/255 at (15, 11)
    torch_frame = render_torch(threshold, camera)
    bound, allowance = tolerance(threshold, camera), flip_allowance(threshold, camera)
    flips = np.argwhere(allowance[0] > 0)
    assert [15, 11] in flips[:, ::-1].tolist() and len(flips) <= 4  # the centre pixel, and hardly any other
    background = np.asarray(BACKGROUND, np.float32)
    skipped = torch_frame.copy()
    skipped[11, 15] = background  # another side skipped it: torch's alpha * |rgb - background| off
    assert check_agreement(torch_frame, skipped, bound, allowance, "skipped")[1] == 1
    assert same_fate(torch_frame, np.broadcast_to(background, torch_frame.shape), allowance[0] > 0, "none") is False
    worse = torch_frame.copy()
    worse[11, 15] += 3.0 * (torch_frame[11, 15] - background)
    with pytest.raises(AssertionError, match="threshold flips"):
        check_agreement(torch_frame, worse, bound, allowance, "worse")
    elsewhere = torch_frame.copy()
    elsewhere[3, 4] += np.float32(2.0 * bound)
    with pytest.raises(AssertionError, match="threshold flips 0"):
        check_agreement(torch_frame, elsewhere, bound, allowance, "elsewhere")
    ordinary = at_pixel(camera, 15.5, 11.5, 2.0, 1.5)  # opacity 0.7: drawn on torch's side only fails
    ordinary_frame = render_torch(ordinary, camera)
    with pytest.raises(AssertionError, match="culled on one side only"):
        same_fate(ordinary_frame, np.broadcast_to(background, ordinary_frame.shape),
                  flip_allowance(ordinary, camera)[0] > 0, "none")


# Gaussians whose determinant lies within the sides' rounding of the reliability cut (rho = det / (DET_MIN_RELATIVE
# noise) = 1): with a hard cut, torch drew one and the GL and CPU splatters culled it, and the other way round.
AT_THE_CUT = {
    "screen-filling, 570 m x 4.4e5 m x 10 m": ((2.7536, 5.6424, 1.0), (-0.1690, -0.4588, -0.0884, 0.5935)),
    "170 m needle, 5e-34 m thin": ((2.2303, -33.3098, -29.4666), (-0.8958, -1.0, -0.7986, 0.95)),
}


@pytest.mark.parametrize("case", list(AT_THE_CUT))
def test_determinant_at_the_cut_is_decided_alike(splatter, cpu_splatter, baseline, stability, case):
    """Near the cut `reliability_fade` keeps every alpha below ALPHA_MIN, so the three sides' frames are the
    background, whichever side's rounding puts rho on which side of 1."""
    camera = normal_camera()
    scene = one_gaussian(camera, *AT_THE_CUT[case])
    rho = float(torch_splats(scene, camera)["rho"][0])
    exact = 1.0 / (DET_MIN_RELATIVE * conditioning(scene, camera))  # float64, the plain form's rho
    assert 0.9 < rho < 1.2 and 0.9 < exact < 1.2  # the case sits at the cut
    outcome = run_case(splatter, baseline, scene, camera, cpu_splatter)
    background = np.broadcast_to(np.asarray(BACKGROUND, np.float32), outcome.torch_frame.shape)
    for frame in (outcome.torch_frame, outcome.gl_frame, outcome.cpu_frame):
        np.testing.assert_array_equal(frame, background)
    stability.record("gaussians", f"determinant at the reliability cut: {case} (rho {exact:.3f} in float64, "
                     f"{rho:.3f} in torch's float32)", outcome.describe() + "; all three frames the background")


def test_zero_norm_quaternion_is_the_identity(splatter, baseline, stability):
    camera = normal_camera()
    base = at_pixel(camera, 16.4, 12.3, 2.0, 1.0)
    scales = [[0.05, 0.2, 0.01]]
    zero = scene_of(base[0], covariances(scales, [(0.0, 0.0, 0.0, 0.0)]), base[2], base[3])
    identity = scene_of(base[0], covariances(scales, [(1.0, 0.0, 0.0, 0.0)]), base[2], base[3])
    outcome = run_case(splatter, baseline, one_in_company(camera, zero), camera)
    np.testing.assert_array_equal(render_gl(splatter, zero, camera), render_gl(splatter, identity, camera))
    np.testing.assert_array_equal(render_torch(zero, camera), render_torch(identity, camera))
    stability.record("gaussians", "zero-norm quaternion", outcome.describe() + "; identical to the identity rotation")


@pytest.mark.parametrize("logit", [-1e4, 1e4])
def test_saturated_opacity_logits(splatter, baseline, stability, logit):
    camera = normal_camera()
    opacity = float(torch.sigmoid(torch.tensor(logit, dtype=torch.float32)))
    assert opacity in (0.0, 1.0)  # float32 sigmoid saturates exactly
    extreme = at_pixel(camera, 16.5, 12.5, 2.0, 1.5, rgb=(0.9, 0.1, 0.6), opacity=opacity)
    outcome = run_case(splatter, baseline, one_in_company(camera, extreme), camera)
    assert outcome.drawn[0] == (opacity > 0)
    centre = [render_torch(extreme, camera)[12, 16], render_gl(splatter, extreme, camera)[12, 16]]
    peak = max(float(np.abs(c - np.asarray(BACKGROUND)).max()) for c in centre)
    stability.record("gaussians", f"opacity logit {logit:+g} (sigmoid = {opacity:g})",
                     outcome.describe() + f"; centre pixel moved {peak:.3f} from the background")
    if opacity:  # alpha capped at ALPHA_MAX: the centre pixel is 0.99 colour + 0.01 background on both sides
        want = ALPHA_MAX * np.array([0.9, 0.1, 0.6]) + (1 - ALPHA_MAX) * np.asarray(BACKGROUND)
        for c in centre:
            np.testing.assert_allclose(c, want, atol=1e-5)


@pytest.mark.parametrize("magnitude", [1e3, 1e6, 1e30])
def test_large_sh_coefficients(splatter, baseline, stability, magnitude):
    camera = normal_camera()
    extreme = at_pixel(camera, 16.4, 12.3, 2.0, 2.0, opacity=0.7)
    sh = torch.full((1, 16, 3), magnitude)
    sh[0, :, 1] *= -1.0  # green: every coefficient negative (clamped at 0 below, never above)
    direction = torch.as_tensor(extreme[0] - camera.center, dtype=torch.float32)
    rgb = sh_to_rgb(sh, direction, 3).numpy()
    scene = one_in_company(camera, scene_of(extreme[0], extreme[1], rgb, extreme[3]))
    outcome = run_case(splatter, baseline, scene, camera)
    brightest = [float(frame.max()) for frame in (outcome.torch_frame, outcome.gl_frame)]
    assert min(brightest) > 1.0  # colours beyond 1 reach the frame: no upper clamp before compositing
    stability.record("gaussians", f"SH coefficients {magnitude:g} (rgb up to {float(rgb.max()):.2g})",
                     outcome.describe() + f"; brightest pixel {brightest[0]:.3g} (torch) / {brightest[1]:.3g} (GL)")


def test_centre_at_the_camera_centre(splatter, baseline, stability):
    camera = normal_camera()
    extreme = scene_of(camera.center, covariances([[0.1] * 3], [(1, 0, 0, 0)]), (1, 0, 0), 0.7)
    outcome = run_case(splatter, baseline, one_in_company(camera, extreme), camera)
    assert not outcome.drawn[0]
    stability.record("gaussians", "centre exactly at the camera centre", outcome.describe())


@pytest.mark.parametrize("where", ["at", "below"])
def test_centre_on_the_near_plane(splatter, baseline, stability, where):
    """Identity rotation, so camera z is the float32 world z exactly: z == near is kept, one ulp less is culled."""
    camera = Camera(32, 24, 30.0, 30.0, 16.0, 12.0, np.eye(3), np.zeros(3))
    near = np.float32(camera.near)
    z = near if where == "at" else np.nextafter(near, np.float32(0))
    extreme = scene_of((0.001, 0.0005, z), covariances([[0.001] * 3], [(1, 0, 0, 0)]), (1, 0, 0), 0.7)
    outcome = run_case(splatter, baseline, one_in_company(camera, extreme), camera)
    assert outcome.drawn[0] == (where == "at")
    stability.record("gaussians", f"centre {'exactly at' if where == 'at' else 'one ulp in front of'} the near "
                     f"plane (z = {float(z):.9g})", outcome.describe())


def test_near_plane_under_rotated_cameras(splatter, baseline, stability):
    """Camera z comes from float32 R X + t on both sides; the keep/cull decision at z ~ near must be the same."""

    @collect
    def check(angles, ulps) -> Outcome:
        camera = Camera(32, 24, 30.0, 30.0, 16.0, 12.0, rotation(angles), np.array([0.3, -0.2, 1.0]))
        z = float(np.float32(camera.near)) * (1.0 + ulps * 2.0**-23)
        world = camera.R.T @ (np.array([0.001, 0.002, z]) - camera.t)
        extreme = scene_of(world, covariances([[0.001] * 3], [(1, 0, 0, 0)]), (1, 0, 0), 0.7)
        return run_case(splatter, baseline, extreme, camera)

    angle = st.floats(-math.pi, math.pi)

    @FEW
    @given(st.tuples(angle, angle, angle), st.integers(-3, 3))
    def cases(angles, ulps):
        check(angles, ulps)

    cases()
    stability.record("gaussians", "centre within 3 ulps of the near plane, random camera rotations",
                     summarise(check.outcomes))


@pytest.mark.parametrize("centre", [(math.inf, 0.0, 2.0), (0.0, 0.0, -math.inf), (0.0, math.nan, 2.0),
                                    (3e38, -3e38, 3e38), (1e30, 0.0, 2.0)],
                         ids=["x=inf", "z=-inf", "y=nan", "3e38", "x=1e30"])
def test_centre_at_infinity_or_nan(splatter, baseline, stability, centre):
    camera = normal_camera()
    extreme = scene_of(centre, covariances([[0.1] * 3], [(1, 0, 0, 0)]), (1, 0, 0), 0.7)
    scene = one_in_company(camera, extreme)
    outcome = run_case(splatter, baseline, scene, camera)
    assert not outcome.drawn[0]
    rest = subset(scene, slice(1, None))  # the neighbours render exactly as they do without it, on both sides
    np.testing.assert_array_equal(outcome.torch_frame, render_torch(rest, camera))
    np.testing.assert_array_equal(outcome.gl_frame, render_gl(splatter, rest, camera))
    stability.record("gaussians", f"centre at {centre}", outcome.describe() + "; neighbours unchanged")


# -- cameras -----------------------------------------------------------------------------------------------------


def test_focal_lengths_tiny_to_huge(splatter, baseline, stability):
    """A head-sized scene 3 m away (a dot at fx = 1e-3, a few Gaussians filling the image at 1e7) plus Gaussians
    aimed at pixels all over the image (grazing view angles at tiny focal lengths)."""

    @collect
    def check(log_fx, log_fy, seed) -> Outcome:
        base = normal_camera()
        camera = Camera(32, 24, 10.0**log_fx, 10.0**log_fy, base.cx, base.cy, base.R, base.t)
        return run_case(splatter, baseline, join(normal_scene(seed, 4), spread_over_image(camera, seed)), camera)

    exponent = st.floats(-3.0, 7.0)

    @FEW
    @given(exponent, exponent, st.integers(0, 1000))
    @example(-3.0, -3.0, 0)
    @example(7.0, 7.0, 0)
    @example(-3.0, 7.0, 1)
    def cases(log_fx, log_fy, seed):
        check(log_fx, log_fy, seed)

    cases()
    stability.record("camera", "focal lengths fx, fy 1e-3..1e7 px (both ends and mixed included)",
                     summarise(check.outcomes))


@pytest.mark.parametrize("size", [(1, 1), pytest.param((4096, 4096), marks=pytest.mark.slow), (4096, 8), (8, 4096)],
                         ids=lambda s: f"{s[0]}x{s[1]}")  # 4096 x 4096: the torch reference frame takes ~4 s
def test_image_sizes(splatter, baseline, stability, size):
    width, height = size
    camera = Camera(width, height, 0.8 * max(size), 0.8 * max(size), 0.5 * width, 0.5 * height)
    rng = np.random.default_rng(width + height)
    n = 1 if width * height > 1e6 else 3  # one Gaussian at 4096 x 4096: each torch frame there takes seconds
    scene = join(*(at_pixel(camera, rng.uniform(0, width), rng.uniform(0, height), 2.0,
                            rng.uniform(0.5, min(8.0, max(1.0, min(size) / 2))), rgb=rng.uniform(0, 1.2, 3))
                   for _ in range(n)))
    outcome = run_case(splatter, baseline, scene, camera)
    assert all(outcome.drawn) and outcome.gl_frame.shape == (height, width, 3)
    stability.record("camera", f"image {width}x{height}", outcome.describe())


def test_principal_point_far_outside_the_image(splatter, baseline, stability):

    @collect
    def check(cx_images, cy_images, seed) -> Outcome:
        base = normal_camera()
        camera = Camera(32, 24, base.fx, base.fy, cx_images * 32, cy_images * 24, base.R, base.t)
        return run_case(splatter, baseline, spread_over_image(camera, seed), camera)

    far = st.one_of(st.floats(-1e4, -2.0), st.floats(3.0, 1e4))  # in image widths/heights, outside it

    @FEW
    @given(far, far, st.integers(0, 1000))
    @example(-1e4, 1e4, 0)
    def cases(cx_images, cy_images, seed):
        check(cx_images, cy_images, seed)

    cases()
    stability.record("camera", "principal point 2..1e4 image sizes outside the image (up to 3.2e5 px)",
                     summarise(check.outcomes))


BAD_CAMERAS = {
    "fx = 0": ({"fx": 0.0}, "fx"),
    "fy < 0": ({"fy": -30.0}, "fy"),
    "fx = NaN": ({"fx": math.nan}, "fx"),
    "fx = inf": ({"fx": math.inf}, "fx"),
    "fx = 1e39 (overflows float32)": ({"fx": 1e39}, "fx"),
    "fx = 1e-300 (0 in float32)": ({"fx": 1e-300}, "fx"),
    "fx = None": ({"fx": None}, "fx"),
    "cy = NaN": ({"cy": math.nan}, "cy"),
    "cx = 1e39": ({"cx": 1e39}, "cx"),
    "width = 0": ({"width": 0}, "width"),
    "height = 0": ({"height": 0}, "height"),
    "width = NaN": ({"width": math.nan}, "width"),
    "width = 2.5": ({"width": 2.5}, "width"),
    "height = 1e6": ({"height": 10**6}, "height"),
    "R scaled by 2": ({"R": 2.0 * np.eye(3)}, "R"),
    "R a reflection": ({"R": np.diag([1.0, 1.0, -1.0])}, "R"),
    "R with NaN": ({"R": np.full((3, 3), math.nan)}, "R"),
    "R of shape 2x2": ({"R": np.eye(2)}, "R"),
    "t of shape 2": ({"t": np.zeros(2)}, " t "),
    "t = 1e39": ({"t": [0.0, 0.0, 1e39]}, " t "),
    "near = 0": ({"near": 0.0}, "near"),
}


@pytest.mark.parametrize("case", list(BAD_CAMERAS))
def test_invalid_camera_raises_camera_error(splatter, baseline, stability, case):
    fields, name = BAD_CAMERAS[case]
    good = {"width": 32, "height": 24, "fx": 30.0, "fy": 30.0, "cx": 16.0, "cy": 12.0}
    with pytest.raises(CameraError) as error:
        Camera(**{**good, **fields})
    assert name in str(error.value)
    assert_context_survives(splatter, baseline)
    stability.record("camera", f"invalid: {case}", f"CameraError: {error.value}")


BAD_LOOK_AT = {
    "eye == target": (([0, 0, 0], [0, 0, 0], [0, -1, 0], 40.0), "eye and target"),
    "up parallel to the view": (([0, 0, 0], [0, 0, 1], [0, 0, 2], 40.0), "up"),
    "fov 0 degrees": (([0, 0, 0], [0, 0, 1], [0, -1, 0], 0.0), "fov_y_deg"),
    "fov 180 degrees": (([0, 0, 0], [0, 0, 1], [0, -1, 0], 180.0), "fov_y_deg"),
    "fov NaN": (([0, 0, 0], [0, 0, 1], [0, -1, 0], math.nan), "fov_y_deg"),
}


@pytest.mark.parametrize("case", list(BAD_LOOK_AT))
def test_invalid_look_at_raises_camera_error(stability, case):
    (eye, target, up, fov), name = BAD_LOOK_AT[case]
    with pytest.raises(CameraError, match=name) as error:
        Camera.looking_at(eye, target, up, 32, 24, fov)
    stability.record("camera", f"invalid Camera.looking_at: {case}", f"CameraError: {error.value}")


# -- precision ---------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("scale", [256.0, 1e3, 1e10, 1e18, 1e19, 1e20])
def test_covariance_beyond_fp16_and_float32_range(splatter, baseline, stability, scale):
    """Every splatting computation is float32 on both sides today: torch takes float32 only, the GL buffers are
    float32 and the framebuffer RGBA32F; fp16 exists only as a bundle storage codec, decoded to float32 before use.
    So what matters now is float32 range: a covariance whose entries pass fp16's 65504 (scale 256 m: 65536 m^2) or
    whose 2D products pass float32's 3.4e38 (scale 1e10 m and up; scale 1e20 m: cov3d 1e40 = inf) must come out
    finite and equal on both sides, or culled on both."""
    camera = normal_camera()
    extreme = at_pixel(camera, 16.4, 12.3, 2.0, 1.0)
    extreme = scene_of(extreme[0], covariances([[scale] * 3], [(0.8, 0.1, 0.4, -0.2)]), extreme[2], extreme[3])
    outcome = run_case(splatter, baseline, one_in_company(camera, extreme), camera)
    for frame in (outcome.torch_frame, outcome.gl_frame):
        assert frame.dtype == np.float32
    cov = extreme[1]
    size = f"cov3d up to {float(np.abs(cov).max()):.3g} m^2" if np.isfinite(cov).all() else "cov3d inf/NaN in float32"
    stability.record("precision", f"scale {scale:g} m ({size}; fp16 max 65504)", outcome.describe())
