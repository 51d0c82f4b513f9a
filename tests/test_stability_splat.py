"""Splatting stage at the extremes: the torch reference rasterizer against the OpenGL runtime splatter.

Every case renders the same float32 Gaussians with `render_reference` (torch) and `GLSplatter.render(...,
output="float")` (GL) and checks: no NaN/Inf in any pixel on either side; the two frames agree; each Gaussian of
the case, rendered alone, is drawn by both sides or by neither (a cull on one side only is a disagreement); and
the GL context survives: after the case, a normal scene renders bit-identically to a fresh splatter's render.
Each case's observed numbers go into the stability table.

Bound, and why: max |torch - GL| <= ABS_TOL + c * (REL_TOL + COND_TOL * k), c the largest colour magnitude in the
case (at least 1), k the largest rounding_products/det of its screen covariances (1 for a round splat; see
COND_TOL and `conditioning`).
Both sides evaluate the same float32 formulas in a different order (torch tensor ops vs the GLSL compiler), so
what remains is a few float32 roundings per contribution, ~1e-7 of the colour for ordinary splats and up to 7e-6
measured here on colours <= 1.2 (the worst: needles and grazing view angles, whose conditioning amplifies a
rounding). ABS_TOL = 1e-4 leaves >10x margin over that; REL_TOL = 1e-6 (~16 ulps of c) covers colours far beyond
1 (SH 1e3..1e30, measured ~1.3e-7 of c), where rounding is relative to c. Scenes keep opacity <= 0.7 (or two
Gaussians at most at alpha 0.99), so transmittance never reaches the contract's 1e-4 stop that fixed-function
blending cannot make.
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
    clamped_ratios,
    cov3d_from_rotation_scale,
    covariance_2d,
    quat_to_rotmat,
    rounding_products,
    sh_to_rgb,
    sigma_matrix,
    world_to_camera,
)
from gaussiantalker.runtime.splatter import GLSplatter
from gaussiantalker.sdk.camera import Camera
from gaussiantalker.sdk.errors import CameraError
from gaussiantalker.sdk.numerics import ALPHA_MAX, COLOR_LIMIT, LOW_PASS_PX2

BACKGROUND = (0.2, 0.4, 0.1)
ABS_TOL = 1e-4
REL_TOL = 1e-6
# Both sides round a, b, c of the screen covariance to float32 in different orders, each entry to a few ulps of
# its magnitude (the sum of its terms' absolute values, far above the entry where the terms cancel); the
# determinant a*c - b^2 and hence the conic carry that error times k = rounding_products / det (`conditioning`).
# 2^-24 (one ulp) per unit of k adds < 6e-6 for any splat with k < 100 (all ordinary ones) and bounds slabs seen
# nearly edge-on (the pinned k = 5.7e5 gives 3.4e-2; measured 3.1e-3).
COND_TOL = 2.0**-24
FEW = settings(derandomize=True, max_examples=8, deadline=None)

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


def subset(scene: Scene, index) -> Scene:
    """Gaussians `index` of a scene."""
    return tuple(x[index] for x in scene)


@dataclass
class Outcome:
    """What one case did on both sides."""

    error: float  # max |torch - GL| over the frame
    drawn: list[bool]  # per Gaussian: drawn when rendered alone (the same on both sides, or the check failed)
    torch_frame: np.ndarray
    gl_frame: np.ndarray

    def describe(self) -> str:
        """The observed behaviour, for the stability table (Gaussian 0 is the case's; any others its neighbours)."""
        fate = "drawn by both sides" if self.drawn[0] else "culled on both sides"
        if len(self.drawn) > 1:
            neighbours = f"{sum(self.drawn[1:])} of {len(self.drawn) - 1} neighbours drawn by both"
            fate = f"the case's Gaussian {fate}, {neighbours}"
        return f"finite on both sides; {fate}; torch vs GL max abs {self.error:.1e}"


def is_drawn(frame: np.ndarray) -> bool:
    """Whether anything but the background reached the frame."""
    return bool(np.any(frame != np.asarray(BACKGROUND, np.float32)))


def compare(splatter: GLSplatter, scene: Scene, camera: Camera) -> Outcome:
    """Render on both sides; assert finite pixels, agreement within `tolerance`, the same culls Gaussian by Gaussian."""
    torch_frame, gl_frame = render_torch(scene, camera), render_gl(splatter, scene, camera)
    assert np.isfinite(torch_frame).all(), "NaN/Inf in the torch frame"
    assert np.isfinite(gl_frame).all(), "NaN/Inf in the GL frame"
    error = float(np.abs(torch_frame.astype(np.float64) - gl_frame).max())
    bound = tolerance(scene, camera)
    assert error <= bound, f"torch vs GL max abs {error:.3g} > {bound:.3g}"
    if len(scene[0]) == 1:
        assert is_drawn(torch_frame) == is_drawn(gl_frame)
        drawn = [is_drawn(torch_frame)]
    else:
        alone = [(is_drawn(render_torch(subset(scene, [i]), camera)),
                  is_drawn(render_gl(splatter, subset(scene, [i]), camera))) for i in range(len(scene[0]))]
        assert all(t == g for t, g in alone), f"culled on one side only (torch, GL) per Gaussian: {alone}"
        drawn = [t for t, _ in alone]
    return Outcome(error, drawn, torch_frame, gl_frame)


def assert_context_survives(splatter: GLSplatter, baseline: np.ndarray) -> None:
    """After an extreme case, the normal scene renders exactly as a fresh splatter rendered it."""
    np.testing.assert_array_equal(render_gl(splatter, normal_scene(), normal_camera()), baseline)


def run_case(splatter: GLSplatter, baseline: np.ndarray, scene: Scene, camera: Camera) -> Outcome:
    """compare(), then the context-survival check."""
    outcome = compare(splatter, scene, camera)
    assert_context_survives(splatter, baseline)
    return outcome


def summarise(outcomes: list[Outcome]) -> str:
    """One table row for a property-based test: examples, how many Gaussians drawn/culled, the worst error."""
    drawn = sum(sum(o.drawn) for o in outcomes)
    total = sum(len(o.drawn) for o in outcomes)
    worst = max(o.error for o in outcomes)
    return (f"{len(outcomes)} examples: finite on both sides; {drawn} of {total} Gaussians drawn by both sides, "
            f"the rest culled by both; torch vs GL max abs {worst:.1e}")


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


def test_scale_and_rotation_range(splatter, baseline, stability):
    camera = normal_camera()

    @collect
    def check(log_scales, quat) -> Outcome:
        extreme = at_pixel(camera, 15.0, 11.0, 2.0, 1.0)
        cov3d = covariances([[10.0**e for e in log_scales]], [quat])
        return run_case(splatter, baseline, scene_of(extreme[0], cov3d, extreme[2], extreme[3]), camera)

    exponent = st.floats(-40.0, 19.5)
    unit = st.floats(-1.0, 1.0)

    @FEW
    @given(st.tuples(exponent, exponent, exponent), st.tuples(unit, unit, unit, unit))
    @example((-40.0, -40.0, 19.0), (0.3, 0.5, -0.2, 0.7))  # a needle far longer than any screen, 1e-40 thin
    @example((18.0, 18.0, 18.0), (1.0, 0.0, 0.0, 0.0))  # 2D covariance near float32 max: products overflow
    @example((5.0, 0.0, 0.0), (0.0, 0.0625, 0.0, -0.5))  # 1e5 m x 1 m needle: its det is rounding noise, culled
    @example((3.0, -1.0, 0.0), (0.0625, 1.0, 0.0, 0.25))  # a slab nearly edge-on: k = 5.7e5, error 3.1e-3
    @example((3.5, -1.0, 0.0), (0.111328125, 0.625, 0.0, 0.3125))  # det within rounding: culled by both sides
    def cases(log_scales, quat):
        check(log_scales, quat)

    cases()
    stability.record("gaussians", "scales 1e-40..3e19 m per axis, random quaternions (incl. needles)",
                     summarise(check.outcomes))


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
