"""The pure-torch reference rasterizer against a literal per-pixel 3DGS loop, plus its splat math and extremes."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
import torch

from gaussiantalker.exporter.model.rasterizer import render_reference
from gaussiantalker.exporter.model.splat_math import (
    alpha_shape,
    camera_to_pixel,
    conic_from_cov2d,
    cov3d_from_rotation_scale,
    covariance_2d,
    covariance_2d_determinant,
    extent_radius,
    keep_mask,
    quat_to_rotmat,
    sh_to_rgb,
    splat_alpha,
    world_to_camera,
)
from gaussiantalker.sdk.camera import Camera
from gaussiantalker.sdk.numerics import (
    ALPHA_MAX,
    ALPHA_MIN,
    EXTENT_SIGMAS,
    LOW_PASS_PX2,
    PIXEL_CENTER_OFFSET,
    SH_C0,
    SH_C1,
    SH_C2,
    SH_C3,
    TRANSMITTANCE_MIN,
)

BACKGROUND = (0.2, 0.4, 0.9)


# --------------------------------------------------------------------------- a literal 3DGS forward, in numpy


def brute_force(means, cov3d, rgb, opacity, camera: Camera, background, counts: np.ndarray | None = None
                ) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel, per Gaussian, in float32, written the way the 3DGS CUDA forward pass reads. `counts` [2, H, W],
    if given, gets the Gaussians blended per pixel: all, and those blended while T >= 1/255."""
    f32 = np.float32
    means, cov3d, rgb, opacity = (np.asarray(x.detach(), dtype=f32) for x in (means, cov3d, rgb, opacity))
    R, t = camera.R.astype(f32), camera.t.astype(f32)
    fx, fy, cx, cy = (f32(v) for v in (camera.fx, camera.fy, camera.cx, camera.cy))
    lim = [f32(v) for v in camera.fov_clamp_limits()]
    splats = []  # (depth, index, center, conic, radius)
    for i in range(len(means)):
        with np.errstate(all="ignore"):  # extreme-input scenes: inf/NaN here means culled
            p = R @ means[i] + t
        if not np.all(np.isfinite(p)) or not p[2] >= f32(camera.near):
            continue
        center = np.array([fx * p[0] / p[2] + cx, fy * p[1] / p[2] + cy], dtype=f32)
        xz = min(max(p[0] / p[2], lim[0]), lim[1])
        yz = min(max(p[1] / p[2], lim[2]), lim[3])
        J = np.array([[fx / p[2], 0, -fx * xz / p[2]], [0, fy / p[2], -fy * yz / p[2]]], dtype=f32)
        s = cov3d[i]
        sigma = np.array([[s[0], s[1], s[2]], [s[1], s[3], s[4]], [s[2], s[4], s[5]]], dtype=f32)
        with np.errstate(all="ignore"):
            cov = J @ R @ sigma @ R.T @ J.T
        a, b, c = cov[0, 0] + f32(LOW_PASS_PX2), cov[0, 1], cov[1, 1] + f32(LOW_PASS_PX2)
        det = a * c - b * b
        if not det > 0:
            continue
        mid = f32(0.5) * (a + c)
        radius = f32(EXTENT_SIGMAS) * np.sqrt(mid + np.sqrt(max(mid * mid - det, f32(0))))
        conic = np.array([c / det, -b / det, a / det], dtype=f32)
        if np.all(np.isfinite(center)) and np.all(np.isfinite(conic)) and np.isfinite(radius):
            splats.append((p[2], i, center, conic, radius))
    splats.sort(key=lambda s: (s[0], s[1]))  # by depth, ties in index order (a stable sort)
    image = np.zeros((camera.height, camera.width, 3), dtype=f32)
    trans = np.ones((camera.height, camera.width), dtype=f32)
    for y in range(camera.height):
        for x in range(camera.width):
            T, C = f32(1), np.zeros(3, dtype=f32)
            pixel = np.array([x + PIXEL_CENTER_OFFSET, y + PIXEL_CENTER_OFFSET], dtype=f32)
            for _, i, center, conic, radius in splats:
                d = pixel - center
                if not (abs(d[0]) <= radius and abs(d[1]) <= radius):
                    continue
                power = f32(-0.5) * (conic[0] * d[0] * d[0] + conic[2] * d[1] * d[1]) - conic[1] * d[0] * d[1]
                if power > 0:
                    continue
                alpha = min(f32(ALPHA_MAX), opacity[i] * np.exp(power))
                if alpha < f32(ALPHA_MIN):
                    continue
                test_T = T * (f32(1) - alpha)
                if test_T < f32(TRANSMITTANCE_MIN):
                    break
                if counts is not None:
                    counts[0, y, x] += 1
                    counts[1, y, x] += int(f32(255) * (alpha * T) >= alpha)
                C = C + rgb[i] * alpha * T
                T = test_T
            image[y, x] = C + T * np.asarray(background, dtype=f32)
            trans[y, x] = T
    return image, trans


# --------------------------------------------------------------------------- scenes


def off_centre_camera(width: int = 24, height: int = 17) -> Camera:
    """A tilted camera whose principal point is well off the image centre."""
    base = Camera.looking_at([0.3, -0.2, -3.0], [0.0, 0.1, 0.0], [0.1, -1.0, 0.0], width, height, 40.0)
    return Camera(width, height, base.fx * 1.1, base.fy, 0.31 * width, 0.62 * height, base.R, base.t)


def random_scene(seed: int, n: int = 40, camera: Camera | None = None, px_sigma: tuple[float, float] = (0.4, 4.0)):
    """Gaussians around the origin sized ~px_sigma pixels, some of them behind the camera or off screen."""
    camera = camera or off_centre_camera()
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g) * torch.tensor([0.9, 0.7, 1.2])
    means[: n // 10, 2] -= 5.0  # some behind the camera (world z -3 is the camera)
    log_lo, log_hi = math.log(px_sigma[0]), math.log(px_sigma[1])
    scale = torch.exp(torch.empty(n, 3).uniform_(log_lo, log_hi, generator=g)) * 3.0 / camera.fy
    cov3d = cov3d_from_rotation_scale(quat_to_rotmat(torch.randn(n, 4, generator=g)), scale)
    rgb = torch.rand(n, 3, generator=g) * 1.2
    opacity = torch.rand(n, generator=g)
    return means, cov3d, rgb, opacity, camera


def stacked_scene():
    """Opaque Gaussians stacked at one spot (termination triggers), z ties with different colours, late faint ones."""
    camera = Camera(24, 17, 30.0, 28.0, 13.7, 6.2)  # identity pose: world z is camera z exactly
    z = [2.0, 2.0, 2.0, 2.5, 3.0, 3.0, 3.5, 4.0, 4.0, 6.0]
    n = len(z)
    means = torch.zeros(n, 3)
    means[:, 2] = torch.tensor(z)
    means[:, 0] = torch.linspace(-0.05, 0.05, n)
    scale = torch.full((n, 3), 0.12)
    cov3d = cov3d_from_rotation_scale(quat_to_rotmat(torch.randn(n, 4, generator=torch.Generator().manual_seed(3))),
                                      scale * means[:, 2:3] / 2.0)
    rgb = torch.rand(n, 3, generator=torch.Generator().manual_seed(4))
    opacity = torch.tensor([0.95, 0.9, 0.97, 0.95, 0.99, 0.5, 0.95, 0.3, 0.2, 0.1])
    # A second, fainter stack in the corner where ties in z decide the colour.
    extra = torch.tensor([[-0.8, 0.3, 2.0], [-0.8, 0.3, 2.0], [-0.8, 0.3, 2.0]])
    means = torch.cat([means, extra])
    cov3d = torch.cat([cov3d, cov3d_from_rotation_scale(torch.eye(3).expand(3, 3, 3), torch.full((3, 3), 0.1))])
    rgb = torch.cat([rgb, torch.eye(3)])
    opacity = torch.cat([opacity, torch.tensor([0.6, 0.7, 0.8])])
    return means, cov3d, rgb, opacity, camera


def assert_matches_brute_force(means, cov3d, rgb, opacity, camera, **kwargs) -> tuple[torch.Tensor, torch.Tensor]:
    image, trans = render_reference(means, cov3d, rgb, opacity, camera, BACKGROUND, **kwargs)
    want_image, want_trans = brute_force(means, cov3d, rgb, opacity, camera, BACKGROUND)
    assert image.shape == (camera.height, camera.width, 3) and image.dtype == torch.float32
    assert trans.shape == (camera.height, camera.width)
    np.testing.assert_allclose(image.detach().numpy(), want_image, atol=1e-5, rtol=0)
    np.testing.assert_allclose(trans.detach().numpy(), want_trans, atol=1e-5, rtol=0)
    # Relative on T too: tells "stop at T_MIN" from "skip that one Gaussian and go on" (both leave T ~ 1e-4).
    np.testing.assert_allclose(trans.detach().numpy(), want_trans, rtol=1e-4, atol=1e-9)
    return image, trans


# --------------------------------------------------------------------------- (a) equality with the literal loop


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_matches_brute_force_random(seed):
    image, trans = assert_matches_brute_force(*random_scene(seed))
    assert float(trans.min()) < 0.5 < float(trans.max())  # a busy scene, not a blank or a solid one


def test_matches_brute_force_termination_and_ties():
    means, cov3d, rgb, opacity, camera = stacked_scene()
    image, trans = assert_matches_brute_force(means, cov3d, rgb, opacity, camera)
    t = trans.numpy()
    assert t.min() < 1e-3 and t.min() >= TRANSMITTANCE_MIN  # the stop rule is exercised, never crossed
    # The stop carried across one-Gaussian chunks gives the same frame.
    chunked, chunked_t = render_reference(means, cov3d, rgb, opacity, camera, BACKGROUND, memory_budget_bytes=1)
    torch.testing.assert_close(chunked, image, atol=1e-6, rtol=0)
    torch.testing.assert_close(chunked_t, trans, atol=0, rtol=1e-5)
    # Swapping the tied Gaussians 10 and 12 (same z) changes the picture: order among ties is the index order.
    perm = torch.arange(len(means))
    perm[10], perm[12] = 12, 10
    swapped, _ = render_reference(means[perm], cov3d[perm], rgb[perm], opacity[perm], camera, BACKGROUND)
    assert float((swapped - image).abs().max()) > 0.05
    assert_matches_brute_force(means[perm], cov3d[perm], rgb[perm], opacity[perm], camera)


def test_blend_count_matches_the_literal_loop():
    """The per-pixel blend counts (docs/demo-speaker.md, "Surface") agree exactly with the literal loop's, on a scene
    whose pixels hit the stop rule, with one-Gaussian chunks too (the count carries across chunks)."""
    means, cov3d, rgb, opacity, camera = stacked_scene()
    want = np.zeros((2, camera.height, camera.width), np.int64)
    brute_force(means, cov3d, rgb, opacity, camera, BACKGROUND, counts=want)
    assert (want[0] > want[1]).any() and want[1].max() > 0  # some pixels blend Gaussians after saturating visibly
    for budget in (1, 1 << 30):
        got = torch.zeros(2, camera.height, camera.width, dtype=torch.int64)
        render_reference(means, cov3d, rgb, opacity, camera, BACKGROUND, blend_count=got, memory_budget_bytes=budget)
        np.testing.assert_array_equal(got.numpy(), want)
    with pytest.raises(ValueError, match="without gradients"):
        render_reference(means.requires_grad_(True), cov3d, rgb, opacity, camera, BACKGROUND, blend_count=got)


@pytest.mark.parametrize(("tile_size", "budget"), [(1, 20_000), (5, 1), (16, 1 << 30), (64, 1 << 30)])
def test_tiles_and_chunks_do_not_change_results(tile_size, budget):
    scene = random_scene(5, n=60)
    want, want_t = render_reference(*scene, BACKGROUND)
    # A tiny budget forces one-row bands, one-Gaussian chunks (T carried across chunks) and checkpointing.
    got, got_t = render_reference(*scene, BACKGROUND, tile_size=tile_size, memory_budget_bytes=budget)
    torch.testing.assert_close(got, want, atol=1e-6, rtol=0)
    torch.testing.assert_close(got_t, want_t, atol=1e-6, rtol=0)


# --------------------------------------------------------------------------- (b) gradients


def _grads(scene, **kwargs):
    means, cov3d, rgb, opacity, camera = scene
    params = [x.clone().requires_grad_(True) for x in (means, cov3d, rgb, opacity)]
    image, trans = render_reference(*params, camera, BACKGROUND, **kwargs)
    loss = (image * torch.linspace(0.5, 1.5, 3)).sum() + trans.sum()
    return params, torch.autograd.grad(loss, params)


def test_gradients_exist_and_are_finite():
    scene = random_scene(0)
    params, grads = _grads(scene)
    for name, grad in zip(("means", "cov3d", "rgb", "opacity"), grads, strict=True):
        assert torch.isfinite(grad).all(), name
        assert grad.abs().sum() > 0, name
    # Checkpointed, chunk-carrying path gives the same gradients.
    _, grads_ckpt = _grads(scene, memory_budget_bytes=1, tile_size=5)
    for grad, grad_ckpt in zip(grads, grads_ckpt, strict=True):
        torch.testing.assert_close(grad_ckpt, grad, atol=1e-4, rtol=1e-4)


def test_gradients_match_finite_differences():
    means, cov3d, rgb, opacity, camera = random_scene(1)
    _, (g_means, _, g_rgb, g_opacity) = _grads((means, cov3d, rgb, opacity, camera))

    def loss(m=means, c=rgb, o=opacity):
        image, trans = render_reference(m, cov3d, c, o, camera, BACKGROUND)
        return float((image.double() * torch.linspace(0.5, 1.5, 3).double()).sum() + trans.double().sum())

    i = int(torch.argmax(g_opacity.abs()))  # a Gaussian that matters
    eps = 1e-2
    e_rgb = torch.zeros_like(rgb)
    e_rgb[i, 1] = eps
    assert (loss(c=rgb + e_rgb) - loss(c=rgb - e_rgb)) / (2 * eps) == pytest.approx(float(g_rgb[i, 1]), rel=1e-3)
    e_op = torch.zeros_like(opacity)
    e_op[i] = 1e-3
    fd = (loss(o=opacity + e_op) - loss(o=opacity - e_op)) / 2e-3
    assert fd == pytest.approx(float(g_opacity[i]), rel=0.05, abs=0.05)
    e_m = torch.zeros_like(means)
    e_m[i, 0] = 1e-3
    fd = (loss(m=means + e_m) - loss(m=means - e_m)) / 2e-3
    assert fd == pytest.approx(float(g_means[i, 0]), rel=0.1, abs=0.5)


# --------------------------------------------------------------------------- (c) extremes stay finite


def test_extreme_inputs_stay_finite_and_cull_by_the_rules():
    camera = Camera(32, 24, 30.0, 30.0, 16.0, 12.0)  # identity pose: camera space == world space
    near = camera.near
    below_near = float(np.nextafter(np.float32(near), np.float32(0)))
    rows = [  # (mean, quaternion, scale, opacity)
        ([0.0, 0.0, 2.0], [0, 0, 0, 0], [0.05] * 3, 0.8),  # zero quaternion -> identity rotation
        ([0.3, 0.1, 2.0], [1, 2, 3, 4], [0.0] * 3, 1.0),  # scale 0: only the low-pass filter remains
        ([-0.2, 0.2, 3.0], [1, 0, 0, 0], [1e3] * 3, 0.5),  # far bigger than the screen
        ([0.1, -0.1, 2.0], [1, 0, 0, 0], [0.1] * 3, 0.0),  # opacity 0
        ([0.0, 0.0, 0.0], [1, 0, 0, 0], [0.1] * 3, 1.0),  # at the camera centre: culled
        ([0.01, 0.0, near], [1, 0, 0, 0], [0.002] * 3, 1.0),  # exactly at the near plane: kept
        ([0.0, 0.01, below_near], [1, 0, 0, 0], [0.002] * 3, 1.0),  # just in front of it: culled
        ([math.inf, 0.0, 2.0], [1, 0, 0, 0], [0.1] * 3, 1.0),  # infinite mean: culled
        ([0.0, math.nan, 2.0], [1, 0, 0, 0], [0.1] * 3, 1.0),  # NaN mean: culled
        ([0.2, 0.2, 2.0], [1, 0, 0, 0], [1e20] * 3, 1.0),  # covariance overflows: culled
        ([50.0, -40.0, 1.0], [1, 0, 0, 0], [0.5] * 3, 1.0),  # far outside the field of view
    ]
    means = torch.tensor([r[0] for r in rows], dtype=torch.float32)
    rot = quat_to_rotmat(torch.tensor([r[1] for r in rows], dtype=torch.float32))
    cov3d = cov3d_from_rotation_scale(rot, torch.tensor([r[2] for r in rows], dtype=torch.float32))
    opacity = torch.tensor([r[3] for r in rows], dtype=torch.float32)
    rgb = torch.rand(len(rows), 3, generator=torch.Generator().manual_seed(0))

    R, t = torch.eye(3), torch.zeros(3)
    limits = camera.fov_clamp_limits()
    points = world_to_camera(means, R, t)
    xy = camera_to_pixel(points, camera.fx, camera.fy, camera.cx, camera.cy)
    cov2d = covariance_2d(points, cov3d, R, camera.fx, camera.fy, limits)
    det = covariance_2d_determinant(points, cov3d, cov2d, R, camera.fx, camera.fy, limits)
    keep = keep_mask(points, xy, cov2d, det, conic_from_cov2d(cov2d, det), alpha_shape(cov2d, det),
                     extent_radius(cov2d), near, rgb, opacity)
    assert keep.tolist() == [True, True, True, True, False, True, False, False, False, False, True]

    params = [x.clone().requires_grad_(True) for x in (means, cov3d, rgb, opacity)]
    image, trans = render_reference(*params, camera, BACKGROUND)
    assert torch.isfinite(image).all() and torch.isfinite(trans).all()
    for grad in torch.autograd.grad(image.sum(), params):
        assert torch.isfinite(grad).all()

    # The Gaussian exactly at z = near is drawn; the one just in front of the plane is not.
    alone = [5, 6]
    image, _ = render_reference(means[alone], cov3d[alone], rgb[alone], opacity[alone], camera, BACKGROUND)
    at_near = image[12, 17]  # u = 30 * 0.01 / 0.2 + 16 = 17.5 -> pixel (17, 12)
    assert float((at_near - torch.tensor(BACKGROUND)).abs().max()) > 0.1
    assert_matches_brute_force(means, cov3d, rgb, opacity, camera)


def test_empty_and_all_culled():
    camera = off_centre_camera()
    empty = torch.zeros(0, 3)
    image, trans = render_reference(empty, torch.zeros(0, 6), empty, torch.zeros(0), camera, BACKGROUND)
    assert torch.equal(image, torch.tensor(BACKGROUND).expand(17, 24, 3)) and torch.equal(trans, torch.ones(17, 24))
    means = torch.tensor([[0.0, 0.0, -10.0], [math.nan, 0.0, 0.0]])
    image, trans = render_reference(means, torch.zeros(2, 6), torch.ones(2, 3), torch.ones(2), camera, BACKGROUND)
    assert torch.equal(trans, torch.ones(17, 24))


def test_huge_splat_is_bounded_by_tiles():
    camera = Camera(160, 120, 125.0, 125.0, 80.0, 60.0)
    n = 30
    means = torch.tensor([[0.0, 0.0, 1.0]] * n)
    cov3d = cov3d_from_rotation_scale(torch.eye(3).expand(n, 3, 3), torch.full((n, 3), 1e4))
    image, trans = render_reference(means, cov3d, torch.rand(n, 3), torch.full((n,), 0.01), camera, BACKGROUND)
    assert torch.isfinite(image).all()
    # Each layer covers the whole image with alpha 0.01 (exp(power) ~ 1): T = 0.99^n everywhere.
    torch.testing.assert_close(trans, torch.full_like(trans, 0.99**n), atol=1e-5, rtol=0)


# --------------------------------------------------------------------------- (d) SH colour


def _sh_basis(d: np.ndarray) -> list[float]:
    """The 16 real SH basis values used by 3DGS, written out from the textbook polynomials."""
    x, y, z = d / np.linalg.norm(d)
    return [
        SH_C0,
        -SH_C1 * y, SH_C1 * z, -SH_C1 * x,
        SH_C2[0] * x * y, SH_C2[1] * y * z, SH_C2[2] * (2 * z * z - x * x - y * y), SH_C2[3] * x * z,
        SH_C2[4] * (x * x - y * y),
        SH_C3[0] * y * (3 * x * x - y * y), SH_C3[1] * x * y * z, SH_C3[2] * y * (4 * z * z - x * x - y * y),
        SH_C3[3] * z * (2 * z * z - 3 * x * x - 3 * y * y), SH_C3[4] * x * (4 * z * z - x * x - y * y),
        SH_C3[5] * z * (x * x - y * y), SH_C3[6] * x * (x * x - 3 * y * y),
    ]


def test_sh_degree_zero():
    sh = torch.randn(5, 1, 3)
    rgb = sh_to_rgb(sh, torch.randn(5, 3), 0)
    torch.testing.assert_close(rgb, torch.clamp_min(SH_C0 * sh[:, 0] + 0.5, 0.0))


@pytest.mark.parametrize("degree", [1, 2, 3])
def test_sh_higher_degrees_match_direct_formula(degree):
    g = torch.Generator().manual_seed(degree)
    sh = torch.randn(16, 3, generator=g, dtype=torch.float64) * 0.3
    direction = np.array([0.3, -1.7, 2.2])  # unnormalised on purpose
    rgb = sh_to_rgb(sh, torch.tensor(direction), degree)  # sh holds degree 3; only (degree+1)^2 are used
    count = (degree + 1) ** 2
    want = np.asarray(_sh_basis(direction)[:count]) @ sh[:count].numpy() + 0.5
    np.testing.assert_allclose(rgb.numpy(), np.maximum(want, 0.0), atol=1e-12)


def test_sh_clamps_below_only_and_zero_direction_is_finite():
    sh = torch.zeros(2, 1, 3)
    sh[0, 0] = torch.tensor([-10.0, 10.0, 0.0])
    rgb = sh_to_rgb(sh, torch.zeros(2, 3), 0)
    assert rgb[0, 0] == 0 and rgb[0, 1] > 1 and torch.all(rgb[1] == 0.5)
    full = torch.randn(2, 16, 3, requires_grad=True)
    dirs = torch.zeros(2, 3, requires_grad=True)
    out = sh_to_rgb(full, dirs, 3)
    assert torch.isfinite(out).all()
    assert all(torch.isfinite(g).all() for g in torch.autograd.grad(out.sum(), [full, dirs]))


# --------------------------------------------------------------------------- splat math units


def test_quat_to_rotmat_zero_and_random():
    assert torch.equal(quat_to_rotmat(torch.zeros(4)), torch.eye(3))
    q = torch.randn(20, 4, dtype=torch.float64)
    rot = quat_to_rotmat(q)
    torch.testing.assert_close(rot @ rot.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(20, 3, 3))
    torch.testing.assert_close(torch.linalg.det(rot), torch.ones(20, dtype=torch.float64))
    torch.testing.assert_close(quat_to_rotmat(q * 7.5), rot)
    zero = torch.zeros(4, requires_grad=True)
    (grad,) = torch.autograd.grad(quat_to_rotmat(zero).sum(), zero)
    assert torch.isfinite(grad).all()


def test_cov3d_packing():
    rot = quat_to_rotmat(torch.randn(4, 4, dtype=torch.float64))
    scale = torch.rand(4, 3, dtype=torch.float64)
    full = rot @ torch.diag_embed(scale**2) @ rot.transpose(1, 2)
    packed = cov3d_from_rotation_scale(rot, scale)
    want = torch.stack([full[:, 0, 0], full[:, 0, 1], full[:, 0, 2], full[:, 1, 1], full[:, 1, 2], full[:, 2, 2]], 1)
    torch.testing.assert_close(packed, want)


def test_projection_covariance_extent_against_float64():
    means, cov3d, _, _, camera = random_scene(7, n=30)
    R, t = torch.tensor(camera.R, dtype=torch.float32), torch.tensor(camera.t, dtype=torch.float32)
    lim = camera.fov_clamp_limits()
    points = world_to_camera(means, R, t)
    xy = camera_to_pixel(points, camera.fx, camera.fy, camera.cx, camera.cy)
    cov2d = covariance_2d(points, cov3d, R, camera.fx, camera.fy, lim)
    det = covariance_2d_determinant(points, cov3d, cov2d, R, camera.fx, camera.fy, lim)
    for i in range(len(means)):
        p = camera.R @ means[i].double().numpy() + camera.t
        if p[2] < camera.near:
            continue
        np.testing.assert_allclose(xy[i], [camera.fx * p[0] / p[2] + camera.cx, camera.fy * p[1] / p[2] + camera.cy],
                                   rtol=1e-5, atol=1e-4)
        tx = np.clip(p[0] / p[2], lim[0], lim[1]) * p[2]
        ty = np.clip(p[1] / p[2], lim[2], lim[3]) * p[2]
        J = np.array([[camera.fx / p[2], 0, -camera.fx * tx / p[2] ** 2],
                      [0, camera.fy / p[2], -camera.fy * ty / p[2] ** 2]])
        s = cov3d[i].double().numpy()
        sigma = np.array([[s[0], s[1], s[2]], [s[1], s[3], s[4]], [s[2], s[4], s[5]]])
        cov = J @ camera.R @ sigma @ camera.R.T @ J.T + LOW_PASS_PX2 * np.eye(2)
        np.testing.assert_allclose(cov2d[i], [cov[0, 0], cov[0, 1], cov[1, 1]], rtol=1e-4, atol=1e-4)
        lam = np.linalg.eigvalsh(cov).max()
        assert float(extent_radius(cov2d[i : i + 1])[0]) == pytest.approx(EXTENT_SIGMAS * math.sqrt(lam), rel=1e-4)
        inv = np.linalg.inv(cov)
        np.testing.assert_allclose(conic_from_cov2d(cov2d[i : i + 1], det[i : i + 1])[0],
                                   [inv[0, 0], inv[0, 1], inv[1, 1]], rtol=1e-3, atol=1e-6)


def _shape_of_conic(conic: torch.Tensor) -> torch.Tensor:
    """The `alpha_shape` form (A, k, q) = (A, -B/A, C - B^2/A) of a conic (A, B, C): the same quadratic form."""
    a, b, c = conic.unbind(-1)
    return torch.stack([a, -b / a, c - b * b / a], dim=-1)


def test_splat_alpha_rules():
    conic = torch.tensor([[0.5, 0.1, 0.3]]).expand(4, 3)
    d = torch.tensor([[0.0, 0.0], [1.0, -2.0], [30.0, 30.0], [0.5, 0.5]])
    opacity = torch.tensor([1.0, 0.8, 1.0, 0.001])
    alpha = splat_alpha(d, _shape_of_conic(conic), opacity)
    assert alpha[0] == pytest.approx(ALPHA_MAX)  # capped
    power = -0.5 * (0.5 * 1 + 0.3 * 4) - 0.1 * 1 * -2
    assert float(alpha[1]) == pytest.approx(0.8 * math.exp(power), rel=1e-6)
    assert alpha[2] == 0 and alpha[3] == 0  # below ALPHA_MIN: skipped
    bad = splat_alpha(torch.tensor([[1.0, 1.0]]), _shape_of_conic(torch.tensor([[-1.0, 0.0, -1.0]])), torch.ones(1))
    assert bad[0] == 0  # power > 0 is skipped, as in 3DGS


# --------------------------------------------------------------------------- (e) odd image shapes


@pytest.mark.parametrize("size", [(1, 1), (7, 300), (300, 7)])
def test_odd_image_shapes_match_brute_force(size):
    width, height = size
    base = Camera.looking_at([0.0, 0.0, -3.0], [0.0, 0.0, 0.0], [0.0, -1.0, 0.0], width, height, 30.0)
    camera = Camera(width, height, base.fy, base.fy * 1.3, width * 0.7, height * 0.4, base.R, base.t)
    n = 12 if width * height > 1 else 25
    _, trans = assert_matches_brute_force(*random_scene(11, n=n, camera=camera, px_sigma=(0.5, 3.0)))
    assert float(trans.min()) < 0.9  # something is drawn


def test_principal_point_outside_the_image():
    base = off_centre_camera()
    camera = Camera(24, 17, base.fx, base.fy, -15.0, 30.0, base.R, base.t)
    means, cov3d, rgb, opacity, _ = random_scene(4, n=60, px_sigma=(1.0, 6.0))
    assert_matches_brute_force(means, cov3d, rgb, opacity, camera)


def test_rejects_bad_shapes_and_dtypes():
    camera = off_centre_camera()
    with pytest.raises(ValueError, match="cov3d"):
        render_reference(torch.zeros(3, 3), torch.zeros(3, 3), torch.zeros(3, 3), torch.zeros(3), camera, BACKGROUND)
    with pytest.raises(ValueError, match="float32"):
        render_reference(torch.zeros(3, 3, dtype=torch.float64), torch.zeros(3, 6), torch.zeros(3, 3),
                         torch.zeros(3), camera, BACKGROUND)


# --------------------------------------------------------------------------- timing (not a test)


def _timing_scene(n: int, size: int):
    """n Gaussians filling a head-sized ball, 3-sigma radii ~2-20 px at 256^2 (scaled with the image)."""
    g = torch.Generator().manual_seed(0)
    camera = Camera.looking_at([0, 0, -2.5], [0, 0, 0], [0, -1, 0], size, size, 20.0)
    d = torch.randn(n, 3, generator=g)
    means = 0.45 * d / d.norm(dim=1, keepdim=True) * torch.rand(n, 1, generator=g) ** (1 / 3)
    sigma_px_256 = torch.exp(torch.empty(n, 3).uniform_(math.log(0.7), math.log(6.7), generator=g))
    scale = sigma_px_256 * 2.5 / (camera.fy * 256 / size)
    cov3d = cov3d_from_rotation_scale(quat_to_rotmat(torch.randn(n, 4, generator=g)), scale)
    return means, cov3d, torch.rand(n, 3, generator=g), torch.rand(n, generator=g), camera


if __name__ == "__main__":
    for side in (256, 512):
        scene = _timing_scene(10_000, side)
        render_reference(*scene, BACKGROUND)  # warm-up
        times = []
        for _ in range(3):
            start = time.perf_counter()
            render_reference(*scene, BACKGROUND)
            times.append(time.perf_counter() - start)
        params = [x.clone().requires_grad_(True) for x in scene[:4]]
        start = time.perf_counter()
        image, _ = render_reference(*params, scene[4], BACKGROUND)
        mid = time.perf_counter()
        torch.autograd.grad(image.sum(), params)
        end = time.perf_counter()
        print(f"10k Gaussians at {side}x{side}: forward {min(times):.3f} s (best of 3; all {times}), "
              f"forward with grad {mid - start:.3f} s + backward {end - mid:.3f} s")
