"""GL splatter vs a literal numpy implementation of the numerics contract (needs numpy + moderngl, no torch).

Parity bound: the GL frame is computed in float32 (vertex/fragment shaders, RGBA32F blending) and the reference
in float64; with the same sort order and the same per-pixel extent/threshold decisions the two differ only by
float32 rounding of the projection, exp() and the blend arithmetic, a few 1e-7 per contribution, so float frames
agree to 1e-5 max abs (measured ~1e-6). A contribution right at a threshold (|dx| == r, alpha == 1/255) could
flip between the two; with the fixed seeds below none does. uint8 frames agree exactly except where a value sits
within ~1e-6 of a rounding boundary, which can move it by one level. The one deliberate difference is the
contract's early termination, which fixed-function blending cannot do; `test_early_termination_bound` measures it.
"""

from __future__ import annotations

import dataclasses
import re
import sys

import numpy as np
import pytest

from gaussiantalker.runtime.splat import gl as splatter_module
from gaussiantalker.runtime.splat import gl_context
from gaussiantalker.runtime.splat import programs as programs_module
from gaussiantalker.runtime.splat.common import STAGES, pack_gaussians
from gaussiantalker.runtime.splat.depth_sort import depth_order, stable_argsort_positive
from gaussiantalker.runtime.splat.gl import GLSplatter, draw_runs, extent_radius_bound
from gaussiantalker.sdk import numerics
from gaussiantalker.sdk.camera import Camera
from gaussiantalker.sdk.errors import RenderError
from gaussiantalker.shaders import load_shader

FLOAT_TOL = 1e-5
BACKGROUND = (0.2, 0.4, 0.1)


@pytest.fixture(scope="module")
def splatter():
    """One splatter (and context) for the whole module (no GL context is a failure: the install provides one)."""
    instance = GLSplatter()
    yield instance
    instance.release()


# -- literal numpy reference of the contract -------------------------------------------------------------------


def reference_projection(mean, cov, camera: Camera):
    """(u, v, dilated 2D covariance, extent radius) of one Gaussian in float64, or None when det <= 0."""
    p = camera.R @ np.asarray(mean, np.float64) + camera.t
    u = camera.fx * p[0] / p[2] + camera.cx
    v = camera.fy * p[1] / p[2] + camera.cy
    x_lo, x_hi, y_lo, y_hi = camera.fov_clamp_limits()
    xz = np.clip(p[0] / p[2], x_lo, x_hi)
    yz = np.clip(p[1] / p[2], y_lo, y_hi)
    jac = np.array([[camera.fx / p[2], 0.0, -camera.fx * xz / p[2]],
                    [0.0, camera.fy / p[2], -camera.fy * yz / p[2]]])
    c = np.asarray(cov, np.float64)
    sigma = np.array([[c[0], c[1], c[2]], [c[1], c[3], c[4]], [c[2], c[4], c[5]]])
    m = jac @ camera.R
    cov2d = m @ sigma @ m.T + numerics.LOW_PASS_PX2 * np.eye(2)
    det = cov2d[0, 0] * cov2d[1, 1] - cov2d[0, 1] ** 2
    if not det > 0:
        return None
    mid = 0.5 * (cov2d[0, 0] + cov2d[1, 1])
    radius = numerics.EXTENT_SIGMAS * np.sqrt(mid + np.sqrt(max(mid * mid - det, 0.0)))
    return u, v, cov2d, radius


def reference_render(means, cov3d, rgb, opacity, camera: Camera, background, early_stop: bool = True):
    """Dense per-pixel 3DGS compositing following docs/numerics.md literally, in float64. # [H, W, 3]"""
    means = np.asarray(means, np.float32)
    z32 = (means[:, 0] * camera.R[2, 0].astype(np.float32) + means[:, 1] * camera.R[2, 1].astype(np.float32)
           + means[:, 2] * camera.R[2, 2].astype(np.float32) + np.float32(camera.t[2]))
    rows = np.concatenate([means, cov3d, rgb, np.asarray(opacity, np.float32)[:, None]], axis=1)
    with np.errstate(invalid="ignore"):
        keep = np.isfinite(rows).all(axis=1) & np.isfinite(z32) & (z32 >= np.float32(camera.near))
    kept = np.flatnonzero(keep)
    order = kept[np.argsort(z32[kept], kind="stable")]

    ys, xs = np.mgrid[0:camera.height, 0:camera.width].astype(np.float64) + numerics.PIXEL_CENTER_OFFSET
    color = np.zeros((camera.height, camera.width, 3))
    trans = np.ones((camera.height, camera.width))
    active = np.ones((camera.height, camera.width), dtype=bool)
    for i in order:
        projected = reference_projection(means[i], cov3d[i], camera)
        if projected is None:
            continue
        u, v, cov2d, radius = projected
        det = cov2d[0, 0] * cov2d[1, 1] - cov2d[0, 1] ** 2
        ca, cb, cc = cov2d[1, 1] / det, -cov2d[0, 1] / det, cov2d[0, 0] / det
        dx, dy = xs - u, ys - v
        power = -0.5 * (ca * dx * dx + cc * dy * dy) - cb * dx * dy
        alpha = np.minimum(numerics.ALPHA_MAX, float(opacity[i]) * np.exp(np.minimum(power, 0.0)))
        hit = active & (np.abs(dx) <= radius) & (np.abs(dy) <= radius) & (power <= 0)
        hit &= alpha >= numerics.ALPHA_MIN
        test_t = trans * (1.0 - alpha)
        if early_stop:
            stop = hit & (test_t < numerics.TRANSMITTANCE_MIN)
            active &= ~stop
            hit &= ~stop
        color += np.where(hit[..., None], (alpha * trans)[..., None] * rgb[i].astype(np.float64), 0.0)
        trans = np.where(hit, test_t, trans)
    return color + trans[..., None] * np.asarray(background, np.float64)


def reference_uint8(frame: np.ndarray) -> np.ndarray:
    """The contract's single 8-bit conversion, floor(clamp(v, 0, 1) * 255 + 0.5) in float32."""
    v = np.clip(frame.astype(np.float32), 0, 1) * np.float32(255) + np.float32(0.5)
    return np.floor(v).astype(np.uint8)


# -- scenes ----------------------------------------------------------------------------------------------------


def make_camera(width: int = 32, height: int = 24) -> Camera:
    """Non-square image, off-centre principal point, fx != fy, a rotated and translated camera."""
    angle = 0.3
    rot_y = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]])
    rot_x = np.array([[1, 0, 0], [0, np.cos(0.2), -np.sin(0.2)], [0, np.sin(0.2), np.cos(0.2)]])
    return Camera(width, height, fx=1.1 * width, fy=1.0 * width, cx=0.41 * width, cy=0.57 * height,
                  R=rot_x @ rot_y, t=np.array([0.1, -0.05, 3.0]))


def random_scene(seed: int, n: int = 50, opacity_max: float = 0.9, scale: float = 0.08):
    """n Gaussians around the world origin, anisotropic covariances, colours up to 1.5 (no upper clamp).

    With n >= 10, three wide Gaussians sit outside make_camera()'s clamped field of view (x/z or y/z beyond
    the limits) with tails reaching into the image, so the clamp of J matters.
    """
    rng = np.random.default_rng(seed)
    means = rng.normal(0.0, 0.5, (n, 3)).astype(np.float32)
    basis = rng.normal(0.0, scale, (n, 3, 3))
    cov = basis @ basis.transpose(0, 2, 1)
    cov3d = cov[:, [0, 0, 0, 1, 1, 2], [0, 1, 2, 1, 2, 2]].astype(np.float32)
    rgb = rng.uniform(0.0, 1.5, (n, 3)).astype(np.float32)
    opacity = rng.uniform(0.05, opacity_max, n).astype(np.float32)
    if n >= 10:
        camera = make_camera()
        outside = np.array([(-0.62, 0.1, 1.0), (0.8, -0.2, 1.0), (0.1, 0.6, 1.0)]) * 3.0  # camera space
        means[:3] = (outside - camera.t) @ camera.R  # world = R^T (p_cam - t)
        cov3d[:3] = (0.3, 0.05, 0.2, 0.25, -0.1, 0.8)
    return means, cov3d, rgb, opacity


def one_gaussian(z: float, scale: float = 0.02, rgb=(1.0, 0.0, 0.0), opacity: float = 0.9):
    """A single isotropic Gaussian on the optical axis at camera-space depth z (identity camera)."""
    means = np.array([[0.0, 0.0, z]], np.float32)
    cov3d = np.array([[scale**2, 0, 0, scale**2, 0, scale**2]], np.float32)
    return means, cov3d, np.array([rgb], np.float32), np.array([opacity], np.float32)


def identity_camera(width: int = 16, height: int = 12) -> Camera:
    """Camera at the origin looking down +z; the optical axis hits the centre of pixel (width/2, height/2)."""
    return Camera(width, height, fx=20.0, fy=20.0, cx=width / 2 + 0.5, cy=height / 2 + 0.5)


# -- parity ----------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_float_frame_matches_reference(splatter, seed):
    camera = make_camera()
    scene = random_scene(seed)
    frame = splatter.render(*scene, camera, BACKGROUND, output="float")
    expected = reference_render(*scene, camera, BACKGROUND)
    assert frame.shape == (24, 32, 3) and frame.dtype == np.float32
    assert np.abs(frame - expected).max() <= FLOAT_TOL
    assert np.abs(frame - BACKGROUND).max() > 0.1  # the scene is actually visible


@pytest.mark.parametrize("seed", [4, 5])
def test_uint8_frame_matches_reference(splatter, seed):
    camera = make_camera(40, 30)
    scene = random_scene(seed, n=80)
    frame = splatter.render(*scene, camera, BACKGROUND)
    expected = reference_uint8(reference_render(*scene, camera, BACKGROUND))
    assert frame.dtype == np.uint8 and frame.shape == (30, 40, 3)
    diff = np.abs(frame.astype(int) - expected.astype(int))
    assert diff.max() <= 1 and (diff > 0).mean() < 0.01


def test_uint8_is_the_rounded_float_frame(splatter):
    camera = make_camera()
    scene = random_scene(6)
    as_float = splatter.render(*scene, camera, BACKGROUND, output="float")
    np.testing.assert_array_equal(splatter.render(*scene, camera, BACKGROUND), reference_uint8(as_float))


def test_early_termination_bound(splatter):
    """Dense, nearly opaque scene: GL equals the no-stop rule; the 3DGS stop changes pixels by < 0.01 * colour."""
    camera = make_camera()
    scene = random_scene(7, n=200, opacity_max=0.99, scale=0.15)
    frame = splatter.render(*scene, camera, BACKGROUND, output="float")
    no_stop = reference_render(*scene, camera, BACKGROUND, early_stop=False)
    literal = reference_render(*scene, camera, BACKGROUND, early_stop=True)
    assert np.abs(literal - no_stop).max() > 0  # termination does happen in this scene
    assert np.abs(frame - no_stop).max() <= FLOAT_TOL
    max_colour_difference = np.abs(scene[2][:, None, :] - np.asarray(BACKGROUND)).max()
    assert np.abs(frame - literal).max() <= 0.01 * max_colour_difference + FLOAT_TOL
    # In practice the residual transmittance at the stop is ~1e-4..1e-3 (measured 7e-4 max here, colours up to
    # 1.5): below half an 8-bit level.
    assert np.abs(frame - literal).max() < 0.5 / 255


def test_stable_order_for_equal_depths(splatter):
    """Two Gaussians at the same z: the lower index is in front (stable sort)."""
    camera = identity_camera()
    means = np.array([[0, 0, 1], [0, 0, 1]], np.float32)
    cov3d = np.tile(np.array([0.01, 0, 0, 0.01, 0, 0.01], np.float32), (2, 1))
    rgb = np.array([[1, 0, 0], [0, 0, 1]], np.float32)
    opacity = np.array([0.99, 0.99], np.float32)
    frame = splatter.render(means, cov3d, rgb, opacity, camera, (0, 0, 0), output="float")
    centre = frame[6, 8]
    assert centre[0] > 0.9 and centre[2] < 0.1  # red (index 0) in front of blue
    np.testing.assert_allclose(frame, reference_render(means, cov3d, rgb, opacity, camera, (0, 0, 0)),
                               atol=FLOAT_TOL)


def test_points_and_quads_give_identical_pixels(splatter, monkeypatch):
    """Point sprites, instanced quads, and alternating runs of both draw exactly the same pixels."""
    camera = make_camera(40, 30)
    scene = random_scene(16, n=40, scale=0.1)
    rows = pack_gaussians(*scene)[depth_order(pack_gaussians(*scene), camera)]
    quads_only = GLSplatter(splatter.ctx, point_sprites=False)
    try:
        expected = quads_only.render(*scene, camera, BACKGROUND, output="float")
        np.testing.assert_array_equal(splatter.render(*scene, camera, BACKGROUND, output="float"), expected)
        # A point-size limit in the middle of the splat sizes: many alternating point/quad runs.
        monkeypatch.setattr(splatter, "max_point_size", float(np.median(2 * extent_radius_bound(rows, camera))))
        monkeypatch.setattr(splatter_module, "RUN_COST_IN_SPLATS", 0)
        assert len(splatter.plan_runs(rows, camera)) > 4
        np.testing.assert_array_equal(splatter.render(*scene, camera, BACKGROUND, output="float"), expected)
        monkeypatch.setattr(splatter_module, "RUN_COST_IN_SPLATS", 1000)  # runs too costly: quads only
        assert splatter.plan_runs(rows, camera) == [(0, len(rows), True)]
        np.testing.assert_array_equal(splatter.render(*scene, camera, BACKGROUND, output="float"), expected)
    finally:
        quads_only.release()


def test_extent_radius_bound_is_an_upper_bound():
    camera = make_camera()
    means, cov3d, rgb, opacity = random_scene(17, n=200, scale=0.3)
    cov3d[:20, 1] *= -3.0  # not positive semi-definite: the bound must still hold wherever det > 0
    bound = extent_radius_bound(pack_gaussians(means, cov3d, rgb, opacity), camera)
    for i in range(len(means)):
        projected = reference_projection(means[i], cov3d[i], camera)
        if projected is not None:
            assert projected[3] <= bound[i] * (1 + 1e-9)


def test_draw_runs_split_by_primitive_kind():
    assert draw_runs(np.array([], bool)) == []
    assert draw_runs(np.array([False, False, True, False])) == [(0, 2, False), (2, 3, True), (3, 4, False)]


def test_fast_stable_argsort_equals_numpy_stable():
    rng = np.random.default_rng(18)
    for z in (rng.uniform(0.2, 5.0, 1000), np.round(rng.uniform(0.2, 5.0, 1000), 1), np.full(7, 0.5)):
        z = z.astype(np.float32)
        np.testing.assert_array_equal(stable_argsort_positive(z), np.argsort(z, kind="stable"))


# -- primitives: a point sprite never drops a pixel the box draws -----------------------------------------------
#
# The GL renderer only chooses which fragments are tried; the fragment shader decides every pixel exactly. Point
# sprites are squares placed to touch the fewest 4x4 pixel blocks (splat.vert, `point_start`); instanced quads are
# the conservative pixel box itself (`pixel_box`). Both run the same fragment shader in the same order, so a frame
# drawn with points must equal the quads-only frame bit for bit (tolerance 0): any pixel the square failed to
# cover would be missing its contribution, which changes the composited float value.

COVERAGE_CAMERA = Camera(61, 47, fx=50.0, fy=45.0, cx=30.2, cy=23.9)  # odd sizes: no side is a multiple of 4
COVERAGE_Z = 2.0
# Centre pixel positions: inside, on and beyond every edge, a corner, exact half-integer and integer centres.
COVERAGE_CENTRES = ((30.3, 23.7), (1.2, 20.5), (59.9, 10.1), (33.3, 0.4), (12.6, 46.2), (-3.7, 30.2),
                    (64.1, -2.9), (20.5, 30.5), (41.0, 12.0), (57.6, 44.8), (6.0, 3.5))


def adversarial_gaussians():
    """Gaussians whose screen ellipses cover the hard cases of a point square: rotated by 0..180 degrees in 15
    degree steps, aspect ratios 1..1000, sub-pixel to larger than the image, opacity just above ALPHA_MIN up to 1,
    centred inside, on the edges of and outside the image (camera space = world space, identity camera)."""
    camera = COVERAGE_CAMERA
    means, cov3d, opacity = [], [], []
    k = 0
    for angle in np.radians(np.arange(0.0, 180.0, 15.0)):
        for aspect in (1.0, 3.0, 30.0, 1000.0):
            for sigma_px in (0.05, 1.3, 5.0, 40.0):
                for alpha in (numerics.ALPHA_MIN * (1.0 + 1e-3), 0.03, 0.7, 1.0):
                    u, v = COVERAGE_CENTRES[k % len(COVERAGE_CENTRES)]
                    k += 1
                    means.append(((u - camera.cx) * COVERAGE_Z / camera.fx, (v - camera.cy) * COVERAGE_Z / camera.fy,
                                  COVERAGE_Z))
                    major = sigma_px * np.sqrt(aspect) * COVERAGE_Z / camera.fx
                    minor = sigma_px / np.sqrt(aspect) * COVERAGE_Z / camera.fx
                    c, s = np.cos(angle), np.sin(angle)
                    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
                    cov = rot @ np.diag([major**2, minor**2, (0.3 * minor) ** 2]) @ rot.T
                    cov3d.append(cov[[0, 0, 0, 1, 1, 2], [0, 1, 2, 1, 2, 2]])
                    opacity.append(alpha)
    n = len(means)
    rgb = np.random.default_rng(20).uniform(0.2, 1.5, (n, 3))
    return (np.array(means, np.float32), np.array(cov3d, np.float32), rgb.astype(np.float32),
            np.array(opacity, np.float32))


def coverage_mismatches(points: GLSplatter, quads: GLSplatter, scene, limit: int | None = None) -> list[int]:
    """Indices of the Gaussians whose frame drawn alone as a point differs from the quads-only frame."""
    means, cov3d, rgb, opacity = scene
    mismatches = []
    for i in range(len(means) if limit is None else limit):
        one = (means[i : i + 1], cov3d[i : i + 1], rgb[i : i + 1], opacity[i : i + 1])
        prepared = points.prepare(*one, COVERAGE_CAMERA)
        # As a point even where the host's radius bound would pick a quad: the box is clipped to the image,
        # so the square is never wider than the image, which fits the largest point size.
        prepared = dataclasses.replace(prepared, runs=[(0, len(prepared.rows), False)] if len(prepared.rows) else [])
        as_point = points.draw(prepared, BACKGROUND, output="float")
        if not np.array_equal(as_point, quads.render(*one, COVERAGE_CAMERA, BACKGROUND, output="float")):
            mismatches.append(i)
    return mismatches


@pytest.fixture(scope="module")
def quads_only(splatter):
    instance = GLSplatter(splatter.ctx, point_sprites=False)
    yield instance
    instance.release()


def test_point_squares_cover_every_pixel_the_box_draws(splatter, quads_only):
    assert splatter.max_point_size >= max(COVERAGE_CAMERA.width, COVERAGE_CAMERA.height)
    scene = adversarial_gaussians()
    assert coverage_mismatches(splatter, quads_only, scene) == []
    # Not vacuous: most of them draw something, and the whole set composited together matches as well.
    drawn = [np.abs(quads_only.render(*(a[i : i + 1] for a in scene), COVERAGE_CAMERA, BACKGROUND, output="float")
                    - np.asarray(BACKGROUND, np.float32)).max() > 0 for i in range(0, len(scene[0]), 7)]
    assert np.mean(drawn) > 0.6
    together = splatter.prepare(*scene, COVERAGE_CAMERA)
    together = dataclasses.replace(together, runs=[(0, len(together.rows), False)])
    np.testing.assert_array_equal(splatter.draw(together, BACKGROUND, output="float"),
                                  quads_only.render(*scene, COVERAGE_CAMERA, BACKGROUND, output="float"))


@pytest.mark.parametrize(("old", "new"), [
    ("    gl_PointSize = side;\n", "    gl_PointSize = side - 1.0;\n"),  # one pixel short on the high sides
    ("    float best = below;\n", "    float best = below + 1.0;\n"),  # one pixel too far where aligned
    ("    float lowest = max(hi - side, -0.5 * side);\n", "    float lowest = hi - side;\n"),  # centre may leave
    ("    float highest = min(lo, size - 0.5 * side);\n", "    float highest = lo;\n"),  # the image: point dropped
])
def test_the_coverage_check_can_fail(splatter, quads_only, monkeypatch, old, new):
    """A square one pixel too small or shifted by one pixel, or a point whose centre may leave the image (GL then
    drops the whole point), loses pixels, and the check above sees it."""
    source = load_shader("splat.vert")
    assert source.count(old) == 1
    monkeypatch.setattr(programs_module, "load_shader",
                        lambda name: source.replace(old, new) if name == "splat.vert" else load_shader(name))
    broken = GLSplatter(splatter.ctx)
    try:
        assert coverage_mismatches(broken, quads_only, adversarial_gaussians(), limit=200)
    finally:
        broken.release()


def test_point_squares_start_on_pixel_blocks(splatter, monkeypatch):
    """Along its shorter side a box's square starts on a multiple of 4 pixels (fewest 4x4 blocks), not centred,
    and still holds every pixel the Gaussian draws."""
    source = load_shader("splat.frag")
    main = source[source.index("void main() {"):]
    covered = source.replace(main, "void main() {\n    frag_color = vec4(1.0);\n}\n")  # every tried fragment
    monkeypatch.setattr(programs_module, "load_shader",
                        lambda name: covered if name == "splat.frag" else load_shader(name))
    probe = GLSplatter(splatter.ctx)
    camera = Camera(64, 96, fx=50.0, fy=50.0, cx=30.0, cy=48.0)
    scale = COVERAGE_Z / camera.fx  # world units per pixel at z = 2
    try:
        for v in (45.0, 46.3, 47.5, 48.9):  # the short (vertical) side's position against the 4-pixel grid
            means = np.array([[0.3 * scale, (v - camera.cy) * scale, COVERAGE_Z]], np.float32)
            cov = np.array([[(6.0 * scale) ** 2, 0, 0, (1.0 * scale) ** 2, 0, 1e-6]], np.float32)
            scene = (means, cov, np.ones((1, 3), np.float32), np.array([0.9], np.float32))
            as_point = dataclasses.replace(probe.prepare(*scene, camera), runs=[(0, 1, False)])  # one point
            tried = probe.draw(as_point, (0, 0, 0), output="float")[..., 0] > 0
            drawn = splatter.render(*scene, camera, (0, 0, 0), output="float")[..., 0] > 0
            rows, cols = np.nonzero(tried)
            side = cols.max() + 1 - cols.min()
            assert rows.max() + 1 - rows.min() == side > 3 * (np.ptp(np.nonzero(drawn)[0]) + 1)  # a wide box's square
            assert rows.min() % 4 == 0, (v, rows.min())
            assert tried[drawn].all() and drawn[:, cols.min()].any() and drawn[:, cols.max()].any()
    finally:
        probe.release()


# -- edge cases ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("output", ["float", "uint8"])
def test_no_gaussians_gives_background(splatter, output):
    camera = make_camera()
    empty = (np.zeros((0, 3)), np.zeros((0, 6)), np.zeros((0, 3)), np.zeros(0))
    frame = splatter.render(*empty, camera, BACKGROUND, output=output)
    expected = np.broadcast_to(np.asarray(BACKGROUND, np.float32), (24, 32, 3))
    if output == "uint8":
        expected = reference_uint8(expected)
    np.testing.assert_array_equal(frame, expected)


def test_near_plane_keeps_z_equal_to_near_and_culls_below(splatter):
    camera = identity_camera()
    near32 = np.float32(camera.near)
    at_near = one_gaussian(near32, scale=1e-3)
    below = one_gaussian(np.nextafter(near32, np.float32(0)), scale=1e-3)
    assert list(depth_order(pack_gaussians(*at_near), camera)) == [0]
    assert list(depth_order(pack_gaussians(*below), camera)) == []
    shown = splatter.render(*at_near, camera, (0, 0, 0), output="float")
    assert shown[6, 8, 0] > 0.85  # pixel (8, 6) has its centre (8.5, 6.5) on the optical axis
    np.testing.assert_allclose(shown[5:8, 7:10, 0], shown[5:8, 7:10, 0][::-1, ::-1], atol=1e-6)
    np.testing.assert_allclose(shown, reference_render(*at_near, camera, (0, 0, 0)), atol=FLOAT_TOL)
    culled = splatter.render(*below, camera, (0, 0, 0), output="float")
    assert not culled.any()


def test_non_finite_gaussians_are_culled_and_never_reach_a_pixel(splatter):
    camera = make_camera()
    means, cov3d, rgb, opacity = random_scene(8)
    bad = [(means, 0, 0, np.nan), (means, 1, 2, np.inf), (cov3d, 2, 1, np.nan), (cov3d, 3, 5, -np.inf),
           (rgb, 4, 0, np.nan), (rgb, 5, 1, np.inf), (opacity, 6, None, np.nan), (opacity, 7, None, np.inf)]
    for array, row, col, value in bad:
        array[row if col is None else (row, col)] = value
    frame = splatter.render(means, cov3d, rgb, opacity, camera, BACKGROUND, output="float")
    assert np.isfinite(frame).all()
    good = np.ones(len(means), bool)
    good[[row for _, row, _, _ in bad]] = False
    clean = splatter.render(means[good], cov3d[good], rgb[good], opacity[good], camera, BACKGROUND,
                            output="float")
    np.testing.assert_array_equal(frame, clean)


def test_extreme_finite_values_stay_finite(splatter):
    camera = make_camera()
    means, cov3d, rgb, opacity = random_scene(9)
    means[0] = (1e30, -1e30, 1e30)   # overflows camera-space arithmetic
    cov3d[1] = (1e35, 0, 0, 1e35, 0, 1e35)  # 2D covariance overflows to inf
    cov3d[2] = (1e12, 1e12, 0, 1e12, 0, 1e12)  # singular, huge
    rgb[3] = (3e38, -3e38, 3e38)  # colour beyond any real value
    rgb[4] = (-3e38, 3e38, -3e38)
    opacity[5] = 1e30
    for output in ("float", "uint8"):
        frame = splatter.render(means, cov3d, rgb, opacity, camera, BACKGROUND, output=output)
        assert np.isfinite(frame.astype(np.float64)).all()


def test_zero_covariance_is_the_low_pass_filter(splatter):
    camera = make_camera()
    means, cov3d, rgb, opacity = random_scene(10, n=10)
    cov3d[:] = 0.0
    frame = splatter.render(means, cov3d, rgb, opacity, camera, BACKGROUND, output="float")
    assert np.abs(frame - np.asarray(BACKGROUND)).max() > 0.05
    np.testing.assert_allclose(frame, reference_render(means, cov3d, rgb, opacity, camera, BACKGROUND),
                               atol=FLOAT_TOL)


def test_splat_larger_than_the_screen(splatter):
    camera = make_camera()
    means, cov3d, rgb, opacity = random_scene(11, n=5)
    cov3d[2] = (4.0, 0.5, 0.0, 3.0, 0.0, 2.0)  # metres-wide Gaussian ~3 m in front: covers everything
    frame = splatter.render(means, cov3d, rgb, opacity, camera, BACKGROUND, output="float")
    assert np.isfinite(frame).all()
    expected = reference_render(means, cov3d, rgb, opacity, camera, BACKGROUND)
    np.testing.assert_allclose(frame, expected, atol=FLOAT_TOL)
    assert (np.abs(frame - np.asarray(BACKGROUND)).max(axis=2) > 1e-3).all()


def test_resolutions_in_sequence(splatter):
    scene = random_scene(12)
    big, small = make_camera(32, 24), make_camera(17, 9)
    first = splatter.render(*scene, big, BACKGROUND, output="float")
    second = splatter.render(*scene, small, BACKGROUND, output="float")
    third = splatter.render(*scene, big, BACKGROUND, output="float")
    assert second.shape == (9, 17, 3)
    np.testing.assert_allclose(second, reference_render(*scene, small, BACKGROUND), atol=FLOAT_TOL)
    np.testing.assert_array_equal(first, third)
    np.testing.assert_allclose(first, reference_render(*scene, big, BACKGROUND), atol=FLOAT_TOL)


def test_one_by_one_image(splatter):
    camera = Camera(1, 1, fx=2.0, fy=2.0, cx=0.3, cy=0.6)
    means, cov3d, rgb, opacity = one_gaussian(2.0, scale=0.3)
    frame = splatter.render(means, cov3d, rgb, opacity, camera, BACKGROUND, output="float")
    assert frame.shape == (1, 1, 3)
    np.testing.assert_allclose(frame, reference_render(means, cov3d, rgb, opacity, camera, BACKGROUND),
                               atol=FLOAT_TOL)
    assert frame[0, 0, 0] > 0.5


def test_growing_and_shrinking_n_reuses_the_splatter(splatter):
    camera = make_camera()
    for n in (3, 1500, 7):
        scene = random_scene(13 + n, n=n, scale=0.02)
        frame = splatter.render(*scene, camera, BACKGROUND, output="float")
        if n < 100:
            np.testing.assert_allclose(frame, reference_render(*scene, camera, BACKGROUND), atol=FLOAT_TOL)
    assert set(splatter.last_timings) >= set(STAGES)
    assert all(value >= 0 for value in splatter.last_timings.values())


# -- API and errors --------------------------------------------------------------------------------------------


def test_bad_inputs_raise_render_error_and_the_splatter_survives(splatter):
    camera = make_camera()
    scene = random_scene(14, n=4)
    with pytest.raises(RenderError, match="cov3d"):
        splatter.render(scene[0], scene[1][:, :5], scene[2], scene[3], camera, BACKGROUND)
    with pytest.raises(RenderError, match="background"):
        splatter.render(*scene, camera, (0.0, np.nan, 0.0))
    with pytest.raises(RenderError, match="output"):
        splatter.render(*scene, camera, BACKGROUND, output="f16")
    frame = splatter.render(*scene, camera, BACKGROUND, output="float")
    np.testing.assert_allclose(frame, reference_render(*scene, camera, BACKGROUND), atol=FLOAT_TOL)


def test_release_is_idempotent_and_accepts_a_shared_context(splatter):
    own = GLSplatter(splatter.ctx)
    frame = own.render(*random_scene(15, n=4), make_camera(), BACKGROUND)
    assert frame.shape == (24, 32, 3)
    own.release()
    own.release()
    assert splatter.ctx.version_code >= 330  # the shared context is still alive


def test_two_contexts_interleaved(splatter):
    """A second splatter with its own context (made current on creation) does not disturb the first."""
    camera = make_camera()
    scene = random_scene(19)
    expected = reference_render(*scene, camera, BACKGROUND)
    other = GLSplatter()
    try:
        np.testing.assert_allclose(splatter.render(*scene, camera, BACKGROUND, output="float"), expected,
                                   atol=FLOAT_TOL)
        np.testing.assert_allclose(other.render(*scene, camera, BACKGROUND, output="float"), expected,
                                   atol=FLOAT_TOL)
    finally:
        other.release()
    np.testing.assert_allclose(splatter.render(*scene, camera, BACKGROUND, output="float"), expected,
                               atol=FLOAT_TOL)
    with pytest.raises(RenderError, match="released"):
        other.render(*scene, camera, BACKGROUND)


def test_shaders_take_numerics_constants_from_python():
    """No contract constant is re-typed in GLSL (the torch/GLSL function mirror is tests/test_mirror_names.py)."""
    for name in ("splat.vert", "splat.frag"):
        source = load_shader(name)
        assert source.startswith("#version 330 core")
        for literal in ("0.99", "255", "0.3", "1e-4"):
            assert literal not in source, f"{name} re-types the contract constant {literal}"
    with pytest.raises(FileNotFoundError, match="splat.vert"):
        load_shader("missing.frag")


@pytest.mark.parametrize("platform", ["linux", "darwin", "win32"])
def test_context_errors_name_what_to_install(monkeypatch, platform):
    """The error ends with this platform's install hint, and names no other platform's."""
    monkeypatch.setattr(gl_context, "_platform_key", lambda: platform)
    hint = gl_context._INSTALL_HINTS[platform]
    with pytest.raises(RenderError, match=re.escape(f"; {hint}") + "$") as raised:
        gl_context.create_context(backend="no-such-backend")
    message = str(raised.value)
    assert message.startswith("could not create an OpenGL 3.3 core context (no-such-backend: ")
    for other, other_hint in gl_context._INSTALL_HINTS.items():
        if other != platform:
            assert other_hint not in message


def test_headless_linux_uses_egl(monkeypatch):
    monkeypatch.setattr(gl_context, "_platform_key", lambda: "linux")
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    assert gl_context.default_backends() == ["egl"]
    monkeypatch.setenv("DISPLAY", ":0")
    assert gl_context.default_backends() == [None, "egl"]
    monkeypatch.setattr(gl_context, "_platform_key", lambda: "darwin")
    assert gl_context.default_backends() == [None]


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="Linux-only fallback check")
def test_unreachable_display_falls_back_to_egl(monkeypatch):
    monkeypatch.setattr(gl_context, "_platform_key", lambda: "linux")
    monkeypatch.setenv("DISPLAY", ":987")  # no X server there: GLX fails, EGL must take over
    ctx = gl_context.create_context()  # the install provides EGL: a failure here is a real failure
    assert ctx.version_code >= 330
    ctx.release()
