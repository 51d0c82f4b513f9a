"""The CPU tile splatter (runtime/splat/cpu.py) against the torch reference and the GL splatter.

Bounds, and why:
* vs the torch reference (render_reference): both are the contract in float32 with the same stop rule; they differ
  by float32 reassociation (matmul order, fx / z as a reciprocal in torch) and the CPU's exp (relative error
  < 5e-6, `test_exp_error_bound`), a few 1e-7 per contribution. Float frames: max abs <= 1e-5 (measured ~5e-7);
  8-bit frames: PSNR >= 60 dB (below one 8-bit level of RMS error; measured: identical or a level at a few pixels).
* vs GL: GL cannot stop at T_MIN (docs/numerics.md, "Compositing order and early termination"), so a stopped pixel
  may differ by up to 0.01 * max |colour - background|; the 8-bit PSNR bound is again 60 dB.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from test_reference_rasterizer import off_centre_camera, random_scene, stacked_scene

from gaussiantalker.exporter.model.rasterizer import render_reference
from gaussiantalker.exporter.model.splat_math import cov3d_from_rotation_scale, quat_to_rotmat
from gaussiantalker.runtime.splat import cpu as cs
from gaussiantalker.runtime.splat.common import FRAME_OUTPUTS
from gaussiantalker.runtime.splat.cpu import CPUSplatter, exp_approx, upscale_bilinear
from gaussiantalker.runtime.splat.gl import GLSplatter
from gaussiantalker.sdk import numerics
from gaussiantalker.sdk.bundle import Bundle
from gaussiantalker.sdk.camera import Camera
from gaussiantalker.sdk.errors import RenderError
from gaussiantalker.sdk.image import psnr_db, to_uint8
from gaussiantalker.sdk.render_settings import RenderSettings

BACKGROUND = (0.2, 0.4, 0.1)
FLOAT_TOL = 1e-5  # vs the torch reference (see the module docstring)
MIN_PSNR_8BIT = 60.0


@pytest.fixture(scope="module")
def cpu():
    return CPUSplatter()


@pytest.fixture(scope="module")
def gl():
    instance = GLSplatter()
    yield instance
    instance.release()


def _numpy(scene):
    means, cov3d, rgb, opacity, camera = scene
    return [x.numpy() for x in (means, cov3d, rgb, opacity)], camera


def _reference(arrays, camera, alpha_min: float = numerics.ALPHA_MIN) -> np.ndarray:
    image, _ = render_reference(*[torch.from_numpy(a) for a in arrays], camera, BACKGROUND, alpha_min=alpha_min)
    return image.numpy()


def _psnr8(a: np.ndarray, b: np.ndarray) -> float:
    return psnr_db(to_uint8(a).astype(np.float64) / 255, to_uint8(b).astype(np.float64) / 255)


def assert_matches_reference(cpu, arrays, camera) -> np.ndarray:
    frame = cpu.render(*arrays, camera, BACKGROUND, output="float")
    want = _reference(arrays, camera)
    assert frame.shape == want.shape and frame.dtype == np.float32
    assert np.abs(frame - want).max() <= FLOAT_TOL
    assert _psnr8(frame, want) >= MIN_PSNR_8BIT
    return frame


def test_exp_error_bound():
    """`_exp`'s max relative error over [-10, 0] (the range where alpha can pass), stated in docs/numerics.md."""
    x = np.linspace(-10.0, 0.0, 1_000_001, dtype=np.float32)
    want = np.exp(x.astype(np.float64))
    error = np.abs(exp_approx(x) - want) / want
    assert error.max() < 5e-6  # measured 3.5e-6
    below = exp_approx(np.array([-10.5, -50.0, -1e30, -np.inf], dtype=np.float32))
    assert np.all(below >= 0) and np.all(below * 1.0 < 1 / 255)  # opacity <= 1: skipped, as exp(x) would be
    assert exp_approx(np.array([0.0, 1.0], dtype=np.float32)).tolist() == [1.0, 1.0]  # power > 0 is skipped anyway


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_random_scenes_match_reference_and_gl(cpu, gl, seed):
    arrays, camera = _numpy(random_scene(seed, n=120, camera=off_centre_camera(61, 43)))
    frame = assert_matches_reference(cpu, arrays, camera)
    gl_frame = gl.render(*arrays, camera, BACKGROUND, output="float")
    colour_gap = np.abs(arrays[2][:, None, :] - np.asarray(BACKGROUND)).max()
    assert np.abs(frame - gl_frame).max() <= 0.01 * colour_gap + FLOAT_TOL  # GL's missing stop (docstring)
    assert _psnr8(frame, gl_frame) >= MIN_PSNR_8BIT


def test_claims_hand_out_each_work_item_once():
    """`claim` (runtime/jit.py): threads that take work items as they finish get every item exactly once, with
    no items, one, many, and more workers than threads; the counter ends one failed claim per worker past the end."""
    from gaussiantalker.runtime.jit import claim, njit, numba, prange

    @njit(parallel=True, nogil=True)
    def take(counter, marks, workers):
        for _worker in prange(workers):
            while True:
                item = claim(counter)
                if item >= marks.shape[0]:
                    break
                marks[item] += 1

    for n, workers in ((0, 2), (1, 2), (1000, 1), (1000, 5), (200_000, numba.get_num_threads())):
        marks, counter = np.zeros(n, dtype=np.int64), np.zeros(1, dtype=np.int64)
        take(counter, marks, workers)
        assert np.all(marks == 1) and counter[0] == n + workers, (n, workers)


def test_prefetch_compiles_and_changes_nothing():
    """`prefetch` (runtime/jit.py) lowers to LLVM's prefetch call and reads nothing itself: a loop that fetches rows
    ahead, past the array's end too (a prefetch never faults), sums what numpy sums; the rows the CPU splatter
    fetches start on cache lines."""
    from gaussiantalker.runtime.jit import njit, prefetch
    from gaussiantalker.runtime.splat import cpu

    @njit
    def sum_first_column(rows, ahead):
        total = 0.0
        for i in range(rows.shape[0]):
            prefetch(rows, i + ahead)
            total += rows[i, 0]
        return total

    rows = np.arange(64, dtype=np.float32).reshape(16, 4)
    for ahead in (0, 2, 1000):
        assert sum_first_column(rows, ahead) == rows[:, 0].sum()
    assert "llvm.prefetch" in sum_first_column.inspect_llvm(sum_first_column.signatures[0])
    for n in (1, 7, 1000):
        params = cpu._aligned_rows(n)
        assert params.shape == (n, cpu._PARAMS) and params.ctypes.data % 64 == 0 and params.strides[0] == 64


def test_bytes_the_blend_writes_are_the_float_frame_converted():
    """Asked for 8 bits at the drawn size, the blend writes them as each tile ends (`splat_frame(...,
    background=...)`): the same bytes as the float (C, T) frame converted afterwards, on an image whose edge tiles are
    partial, for backgrounds inside and outside [0, 1]; and `draw` takes that path for "uint8" only."""
    arrays, camera = _numpy(random_scene(11, n=300, camera=off_centre_camera(150, 110), px_sigma=(0.3, 12.0)))
    prepared = CPUSplatter().prepare(*arrays, camera)
    for background in ((0.2, 0.4, 0.1), (1.5, -0.3, 0.0), (0.0, 0.0, 0.0)):
        rgb = np.asarray(background, dtype=np.float32)
        written, _, _ = cs.splat_frame(prepared.rows, prepared.camera, background=rgb)
        floats, _, _ = cs.splat_frame(prepared.rows, prepared.camera)
        assert written.dtype == np.uint8 and written.shape == (110, 150, 3)
        np.testing.assert_array_equal(written, cs._convert(floats, rgb, "uint8"))
        assert np.ptp(written) > 20  # something is drawn
    splatter = CPUSplatter()
    floats = splatter.draw(prepared, BACKGROUND, output="float")
    assert splatter.last_timings["readback"] > 0.0
    np.testing.assert_array_equal(splatter.draw(prepared, BACKGROUND), to_uint8(floats))
    assert splatter.last_timings["readback"] == 0.0


def test_frames_do_not_depend_on_which_thread_drew_a_tile():
    """Threads claim tiles and Gaussian chunks as they finish (`claim`): one thread and every thread draw the
    same bits, on a scene with tiles of very different work."""
    arrays, camera = _numpy(random_scene(7, n=400, camera=off_centre_camera(150, 110), px_sigma=(0.3, 12.0)))
    frames = [CPUSplatter(threads=threads).render(*arrays, camera, BACKGROUND, output="float")
              for threads in (1, None, 1, None)]
    for frame in frames[1:]:
        np.testing.assert_array_equal(frame, frames[0])
    assert np.ptp(frames[0]) > 0.1  # something is drawn


def test_termination_and_depth_ties_match_reference(cpu):
    means, cov3d, rgb, opacity, camera = stacked_scene()
    assert_matches_reference(cpu, [x.numpy() for x in (means, cov3d, rgb, opacity)], camera)


@pytest.mark.parametrize("size", [(1, 1), (2, 1), (17, 31), (33, 16), (16, 16)])
def test_image_sizes(cpu, size):
    width, height = size
    arrays, camera = _numpy(random_scene(5, n=60, camera=off_centre_camera(width, height), px_sigma=(0.3, 6.0)))
    assert_matches_reference(cpu, arrays, camera)


def test_4096_frame_with_few_gaussians(cpu, gl):
    """The largest size, cheap with few Gaussians; against GL (the torch reference's 4096^2 tiles cost seconds)."""
    base = off_centre_camera(4096, 4096)
    arrays, camera = _numpy(random_scene(2, n=12, camera=base, px_sigma=(50.0, 400.0)))
    frame = cpu.render(*arrays, camera, BACKGROUND)
    want = gl.render(*arrays, camera, BACKGROUND)
    assert frame.shape == (4096, 4096, 3) and frame.dtype == np.uint8
    assert (frame != to_uint8(np.broadcast_to(np.float32(BACKGROUND), (1, 1, 3)))).any()  # something was drawn
    assert psnr_db(frame.astype(np.float64) / 255, want.astype(np.float64) / 255) >= MIN_PSNR_8BIT


def test_extreme_inputs_match_reference(cpu):
    """The stability extremes of tests/test_reference_rasterizer.py: zero quaternion, zero and huge scales, opacity
    0, at the camera centre, exactly at and just in front of the near plane, Inf/NaN means, an overflowing
    covariance, far outside the field of view."""
    camera = Camera(32, 24, 30.0, 30.0, 16.0, 12.0)
    near = camera.near
    below_near = float(np.nextafter(np.float32(near), np.float32(0)))
    rows = [
        ([0.0, 0.0, 2.0], [0, 0, 0, 0], [0.05] * 3, 0.8), ([0.3, 0.1, 2.0], [1, 2, 3, 4], [0.0] * 3, 1.0),
        ([-0.2, 0.2, 3.0], [1, 0, 0, 0], [1e3] * 3, 0.5), ([0.1, -0.1, 2.0], [1, 0, 0, 0], [0.1] * 3, 0.0),
        ([0.0, 0.0, 0.0], [1, 0, 0, 0], [0.1] * 3, 1.0), ([0.01, 0.0, near], [1, 0, 0, 0], [0.002] * 3, 1.0),
        ([0.0, 0.01, below_near], [1, 0, 0, 0], [0.002] * 3, 1.0), ([math.inf, 0.0, 2.0], [1, 0, 0, 0], [0.1] * 3, 1.0),
        ([0.0, math.nan, 2.0], [1, 0, 0, 0], [0.1] * 3, 1.0), ([0.2, 0.2, 2.0], [1, 0, 0, 0], [1e20] * 3, 1.0),
        ([50.0, -40.0, 1.0], [1, 0, 0, 0], [0.5] * 3, 1.0), ([0.0, 0.05, 2.0], [1, 0.3, 0, 0], [1e-6, 0.3, 1e-9], 0.9),
    ]
    means = torch.tensor([r[0] for r in rows], dtype=torch.float32)
    rot = quat_to_rotmat(torch.tensor([r[1] for r in rows], dtype=torch.float32))
    cov3d = cov3d_from_rotation_scale(rot, torch.tensor([r[2] for r in rows], dtype=torch.float32))
    opacity = torch.tensor([r[3] for r in rows], dtype=torch.float32)
    rgb = torch.rand(len(rows), 3, generator=torch.Generator().manual_seed(0))
    arrays = [x.numpy() for x in (means, cov3d, rgb, opacity)]
    frame = assert_matches_reference(cpu, arrays, camera)
    assert np.isfinite(frame).all()
    alone = [5, 6]  # the Gaussian at z = near is drawn, the one just in front of it is not
    at_near = cpu.render(*[a[alone] for a in arrays], camera, BACKGROUND, output="float")[12, 17]
    assert np.abs(at_near - np.float32(BACKGROUND)).max() > 0.1


def test_huge_screen_covariance_is_drawn_like_the_reference(cpu):
    """A Gaussian of ~1e16 m, 2 m away: its 2D covariance entries (~1e35 px^2) are finite but beyond FINITE_LIMIT,
    while its conic, radius and power bound stay far below it. The contract culls a non-finite 2D covariance, not a
    large one (docs/numerics.md, "Near plane and culling"), so torch draws it over the whole image, and so must the
    CPU splatter."""
    camera = Camera(32, 24, 30.0, 30.0, 16.0, 12.0)
    rot = quat_to_rotmat(torch.tensor([[0.9, 0.2, 0.1, -0.3]]))
    cov3d = cov3d_from_rotation_scale(rot, torch.tensor([[1e16, 5e15, 2e16]]))
    assert 1e30 < float(cov3d.abs().max()) * (camera.fx / 2.0) ** 2 < 3e38
    arrays = [np.array([[0.1, -0.1, 2.0]], np.float32), cov3d.numpy(), np.array([[0.9, 0.3, 0.5]], np.float32),
              np.array([0.6], np.float32)]
    frame = assert_matches_reference(cpu, arrays, camera)
    assert (np.abs(frame - np.float32(BACKGROUND)).max(axis=2) > 0.1).all()


def test_output_modes_match_gl(cpu, gl):
    arrays, camera = _numpy(random_scene(4, n=80, camera=off_centre_camera(40, 30)))
    for output in FRAME_OUTPUTS:
        mine = cpu.render(*arrays, camera, BACKGROUND, output=output)
        theirs = gl.render(*arrays, camera, BACKGROUND, output=output)
        assert mine.shape == theirs.shape and mine.dtype == theirs.dtype, output
        scale = 255.0 if mine.dtype == np.uint8 else 1.0
        # uint8: a value within float rounding of a level boundary may move one level; float: GL's missing stop.
        assert np.abs(mine.astype(np.float64) - theirs.astype(np.float64)).max() / scale <= 1.01 / 255, output


def test_render_scale_upscales_like_gl(gl):
    settings = RenderSettings(render_scale=0.5)
    cpu = CPUSplatter(settings=settings)
    gl_scaled = GLSplatter(settings=settings)
    try:
        arrays, camera = _numpy(random_scene(6, n=80, camera=off_centre_camera(48, 36)))
        mine = cpu.render(*arrays, camera, BACKGROUND, output="float")
        theirs = gl_scaled.render(*arrays, camera, BACKGROUND, output="float")
        assert mine.shape == (36, 48, 3)
        # llvmpipe filters with 8-bit fractional weights: ~1/256 of a neighbour difference.
        assert _psnr8(mine, theirs) >= 45.0
    finally:
        gl_scaled.release()


@pytest.mark.parametrize("cut", [0.02, 0.05, 0.1])
def test_alpha_min_is_the_contract_with_its_alpha_test_raised(cut):
    """`RenderSettings(alpha_min=a)` draws what the contract draws with a in its alpha test (the reference's
    `alpha_min=a`, which a budget's refit draws with), within the reference bound; and it only ever removes
    fragments: the counting blend blends fewer of them than at the contract's 1/255. The reliability fade keeps 1/255
    in both."""
    arrays, camera = _numpy(random_scene(9, n=120, camera=off_centre_camera(48, 36), px_sigma=(1.0, 6.0)))
    contract = CPUSplatter().render(*arrays, camera, BACKGROUND, output="float")
    frame = CPUSplatter(settings=RenderSettings(alpha_min=cut)).render(*arrays, camera, BACKGROUND, output="float")
    want = _reference(arrays, camera, alpha_min=cut)
    assert np.isfinite(frame).all()
    assert np.abs(frame - want).max() <= FLOAT_TOL
    assert np.abs(frame - contract).max() > 1e-3  # the cut changes the frame: the check above has teeth
    counts = {}
    for alpha_min in (numerics.ALPHA_MIN, cut):
        prepared = CPUSplatter().prepare(*arrays, camera)
        totals = np.zeros(len(cs.BLEND_COUNTS), dtype=np.int64)
        cs.splat_frame(prepared.rows, prepared.camera, totals, alpha_min=alpha_min)
        counts[alpha_min] = dict(zip(cs.BLEND_COUNTS, totals.tolist(), strict=True))
    assert counts[cut]["fragments"] < counts[numerics.ALPHA_MIN]["fragments"]
    assert counts[cut]["pairs_binned"] <= counts[numerics.ALPHA_MIN]["pairs_binned"]


def test_alpha_min_at_its_largest_on_saturating_stacks_stays_finite(cpu):
    """The largest cut on the stacked scene (termination, depth ties, late faint Gaussians): finite, and no pixel
    gains coverage it did not have at the contract's cut (a cut only removes contributions)."""
    arrays, camera = _numpy(stacked_scene())
    for output in ("float", "rgba_float"):
        contract = cpu.render(*arrays, camera, BACKGROUND, output=output)
        cut = CPUSplatter(settings=RenderSettings(alpha_min=0.1)).render(*arrays, camera, BACKGROUND, output=output)
        assert np.isfinite(cut).all()
        if output == "rgba_float":
            assert (cut[..., 3] <= contract[..., 3] + 1e-6).all()


def _dense_scene(seed: int):
    """Many overlapping, mostly opaque Gaussians: most pixels pass T = 1/255 long before the contract stops them."""
    return _numpy(random_scene(seed, n=400, camera=off_centre_camera(48, 36), px_sigma=(2.0, 8.0)))


@pytest.mark.parametrize("stop", [1 / 255, 4 / 255, 0.1])
@pytest.mark.parametrize("seed", [0, 1])
def test_transmittance_stop_is_within_its_bound_of_the_contract(seed, stop):
    """`RenderSettings(transmittance_min=t)`: a pixel whose T stays >= t is the contract's bit for bit; one that
    falls below t stops there, with T in [the contract's T, t), and each channel of C + T background within T times
    the largest |colour - background| of the contract's (the later contributions it skips carry at most T of the
    light; docs/numerics.md, "Transmittance stop"). The counting blend blends fewer fragments."""
    arrays, camera = _dense_scene(seed)
    contract = CPUSplatter().render(*arrays, camera, BACKGROUND, output="rgba_float")
    stopped = CPUSplatter(settings=RenderSettings(transmittance_min=stop)).render(*arrays, camera, BACKGROUND,
                                                                                 output="rgba_float")
    assert np.isfinite(stopped).all()
    t_contract, t_stopped = 1.0 - contract[..., 3], 1.0 - stopped[..., 3]
    clear = t_contract >= stop
    np.testing.assert_array_equal(stopped[clear], contract[clear])
    assert (~clear).sum() > 100  # the scene saturates: the bound below has teeth
    assert (t_stopped[~clear] >= t_contract[~clear] - 1e-7).all() and (t_stopped[~clear] < stop + 1e-7).all()
    spread = float(np.abs(arrays[2] - np.asarray(BACKGROUND, np.float32)).max())
    background = np.asarray(BACKGROUND, np.float32)
    error = np.abs((stopped[..., :3] - contract[..., :3]) - (stopped[..., 3:] - contract[..., 3:]) * background)
    error = error.max(axis=-1)  # C + T background, per channel: (1 - T) is the alpha plane of rgba_float
    assert (error <= t_stopped * spread + 1e-5).all()
    assert error.max() > 0.0
    prepared = CPUSplatter().prepare(*arrays, camera)
    fragments = {}
    for t_stop in (numerics.TRANSMITTANCE_MIN, stop):
        totals = np.zeros(len(cs.BLEND_COUNTS), dtype=np.int64)
        cs.splat_frame(prepared.rows, prepared.camera, totals, t_stop=t_stop)
        fragments[t_stop] = totals[cs.BLEND_COUNTS.index("fragments")]
    assert fragments[stop] < fragments[numerics.TRANSMITTANCE_MIN]


def test_transmittance_stop_keeps_every_output_and_saturating_stack_finite(cpu):
    """The largest stop on the stacked scene (the contract's own stop, depth ties, late faint Gaussians) in every
    output mode: finite, and the 8-bit frame the blend writes is the float frame converted."""
    arrays, camera = _numpy(stacked_scene())
    splatter = CPUSplatter(settings=RenderSettings(transmittance_min=0.1))
    for output in FRAME_OUTPUTS:
        assert np.isfinite(splatter.render(*arrays, camera, BACKGROUND, output=output)).all()
    floats = splatter.render(*arrays, camera, BACKGROUND, output="float")
    np.testing.assert_array_equal(splatter.render(*arrays, camera, BACKGROUND, output="uint8"), to_uint8(floats))


@pytest.mark.parametrize("value", [1e-5, 0.2, True, "0.01", float("nan")])
def test_bad_transmittance_stop_is_named(value):
    with pytest.raises(ValueError, match="transmittance_min must be a number in 0.0001 \\(the contract's\\) .. 0.1"):
        RenderSettings(transmittance_min=value)


def test_transmittance_stop_is_stored_only_when_set():
    """Manifest tables stay readable by runtimes before the knob: the contract's value is not written."""
    assert "transmittance_min" not in RenderSettings().to_dict()
    stored = RenderSettings(transmittance_min=0.02).to_dict()
    assert stored["transmittance_min"] == 0.02
    assert RenderSettings.from_dict(stored) == RenderSettings(transmittance_min=0.02)


@pytest.mark.parametrize("knob, value", [("alpha_min", 0.05), ("transmittance_min", 0.05)])
def test_the_gl_splatter_says_it_keeps_the_contracts_rule(gl, caplog, knob, value):
    """A CPU splatter's knob (the alpha cut, the transmittance stop) asked of the OpenGL splatter is named in a
    warning, and its frames are the plain ones: its shaders test alpha against the contract's 1/255 and its
    blending never stops a pixel."""
    import logging

    arrays, camera = _dense_scene(0)
    with caplog.at_level(logging.WARNING, logger="gaussiantalker.runtime"):
        asked = GLSplatter(settings=RenderSettings(**{knob: value}))
    try:
        assert f"{knob}={value} applies on the CPU splatter only" in caplog.text
        frame = asked.render(*arrays, camera, BACKGROUND, output="float")
        np.testing.assert_array_equal(frame, gl.render(*arrays, camera, BACKGROUND, output="float"))
    finally:
        asked.release()
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="gaussiantalker.runtime"):
        GLSplatter().release()
    assert knob not in caplog.text


def test_an_8bit_render_target_upscales_the_bytes_within_a_level():
    """With render_target="uint8" and a render scale, the CPU splatter keeps the drawn frame in 8 bits and
    upscales the bytes (as GL's 8-bit framebuffer does): within one level of the float frame's upscale, converted
    once, and exactly the bytes' bilinear samples rounded to the nearest level. Colours stay within 0..1 here:
    beyond it the 8 bits clamp before the upscale, the floats after it (GL's 8-bit framebuffer clamps first too)."""
    arrays, camera = _numpy(random_scene(11, n=150, camera=off_centre_camera(64, 48), px_sigma=(1.0, 5.0)))
    arrays[2] = np.clip(arrays[2], 0.0, 1.0)
    as_bytes = CPUSplatter(settings=RenderSettings(render_scale=0.6, render_target="uint8"))
    as_floats = CPUSplatter(settings=RenderSettings(render_scale=0.6))
    frame = as_bytes.render(*arrays, camera, BACKGROUND)
    assert frame.shape == (48, 64, 3) and frame.dtype == np.uint8
    reference = as_floats.render(*arrays, camera, BACKGROUND)
    assert np.abs(frame.astype(int) - reference.astype(int)).max() <= 1
    assert RenderSettings(render_scale=0.6).draw_size(64, 48) == (38, 29)
    drawn = CPUSplatter().render(*arrays, camera.resized(38, 29), BACKGROUND)  # the frame at its drawn size
    samples = upscale_bilinear(drawn.astype(np.float32), 64, 48)
    assert np.abs(frame.astype(np.float64) - samples).max() <= 0.5 + 1e-4
    assert as_bytes.render(*arrays, camera, BACKGROUND, output="float").dtype == np.float32  # other outputs: floats


def test_max_draw_pixels_caps_the_drawn_frame_on_both_splatters(gl):
    """A frame past the pixel cap is drawn at the scale that fits (here exactly 1/2: the frame of render_scale
    0.5, bit for bit on the CPU), a frame within it at its render scale; GL draws the same size."""
    arrays, camera = _numpy(random_scene(12, n=80, camera=off_centre_camera(64, 48)))
    capped = RenderSettings(render_scale=0.75, max_draw_pixels=32 * 24)
    assert capped.draw_size(64, 48) == (32, 24) and capped.draw_size(32, 24) == (24, 18)
    half = CPUSplatter(settings=RenderSettings(render_scale=0.5)).render(*arrays, camera, BACKGROUND, output="float")
    mine = CPUSplatter(settings=capped).render(*arrays, camera, BACKGROUND, output="float")
    np.testing.assert_array_equal(mine, half)
    gl_capped = GLSplatter(settings=capped)
    try:
        prepared = gl_capped.prepare(*arrays, camera)
        assert (prepared.camera.width, prepared.camera.height) == (32, 24)
        assert _psnr8(gl_capped.render(*arrays, camera, BACKGROUND, output="float"), mine) >= 45.0  # as render scale
    finally:
        gl_capped.release()


def test_upscale_bilinear_is_exact_on_linear_ramps():
    """Bilinear sampling at pixel centres reproduces a linear ramp inside the image (the edges clamp)."""
    ramp = np.arange(8, dtype=np.float32)[None, :, None] * np.ones((4, 1, 1), np.float32)
    up = upscale_bilinear(ramp, 16, 8)
    np.testing.assert_allclose(up[:, 1:-1, 0], np.broadcast_to((np.arange(1, 15) + 0.5) / 2 - 0.5, (8, 14)), atol=1e-6)


def test_upscale_bilinear_samples_every_channel_at_the_texel_weights():
    """Against the sampling written out per pixel in float64 (texel centres at (i + 0.5) * in / out - 0.5, edges
    clamped), on a random 4-channel image scaled by a non-integer factor in each axis, up and down."""
    rng = np.random.default_rng(5)
    image = rng.random((9, 7, 4), dtype=np.float32)
    for width, height in ((10, 12), (5, 4)):
        expected = np.empty((height, width, 4))
        for y in range(height):
            for x in range(width):
                fy, fx = (y + 0.5) * 9 / height - 0.5, (x + 0.5) * 7 / width - 0.5
                y0, x0 = int(np.floor(fy)), int(np.floor(fx))
                ty, tx = fy - y0, fx - x0
                row = [min(max(v, 0), 8) for v in (y0, y0 + 1)]
                col = [min(max(v, 0), 6) for v in (x0, x0 + 1)]
                expected[y, x] = ((1 - ty) * ((1 - tx) * image[row[0], col[0]] + tx * image[row[0], col[1]])
                                  + ty * ((1 - tx) * image[row[1], col[0]] + tx * image[row[1], col[1]]))
        np.testing.assert_allclose(upscale_bilinear(image, width, height), expected, atol=1e-6)


def test_released_and_bad_arguments(cpu):
    other = CPUSplatter()
    other.release()
    arrays, camera = _numpy(random_scene(0, n=5))
    with pytest.raises(RenderError, match="released"):
        other.render(*arrays, camera, BACKGROUND)
    with pytest.raises(RenderError, match="output"):
        cpu.render(*arrays, camera, BACKGROUND, output="png")
    with pytest.raises(RenderError, match="background"):
        cpu.render(*arrays, camera, (0.0, math.nan, 0.0))


def test_cache_dir_follows_the_user(monkeypatch, tmp_path):
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "mine"))
    assert cs.cache_dir() == tmp_path / "mine"
    monkeypatch.delenv("NUMBA_CACHE_DIR")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert cs.cache_dir() == tmp_path / "xdg" / "gaussiantalker" / "numba"


def test_a_cold_kernel_cache_is_announced_before_compiling(monkeypatch, caplog):
    """A first construction on a machine compiles for ~20 s: it says so first (a warning), a warm one is silent."""
    CPUSplatter()
    assert cs.kernels_cached(), "the kernels this process compiled or loaded are in the cache"
    monkeypatch.setattr(cs, "_WARM", False)
    with caplog.at_level("WARNING", logger="gaussiantalker.runtime"):
        CPUSplatter()
    assert not caplog.records
    monkeypatch.setattr(cs, "_WARM", False)
    monkeypatch.setattr(cs, "kernels_cached", lambda: False)
    with caplog.at_level("WARNING", logger="gaussiantalker.runtime"):
        CPUSplatter()
    assert "compiling the CPU splatter's kernels" in caplog.text and str(cs.cache_dir()) in caplog.text


def test_renderers_bench_runs_both_splatters(tmp_path):
    """`gt-bench renderers` on a tiny speaker: both splatters timed, ratios written (the speed itself: the bench)."""
    from typer.testing import CliRunner

    from tools.bench.app import app

    out = tmp_path / "renderers.json"
    result = CliRunner().invoke(app, ["renderers", "--gaussians", "500", "--sizes", "32", "--frames", "1",
                                      "--rounds", "1", "--threads", "1", "--json", str(out)])
    assert result.exit_code == 0, result.output
    (run,) = json.loads(out.read_text())["runs"]
    assert run["size"] == 32 and set(run["splat_ms"]) == {"gl", "cpu1"}
    assert all(math.isfinite(ms) and ms > 0 for ms in run["splat_ms"].values()), run  # both really timed
    # The ratio is GL's time over the CPU's (> 1: the CPU splatter is faster), as printed; never its inverse.
    ratio = run["splat_ms"]["gl"] / run["splat_ms"]["cpu1"]
    assert run["gl_over_cpu"] == {"cpu1": ratio}, run
    assert f"GL/CPU cpu1 {ratio:.2f}x" in result.output


def test_blend_counts_on_a_scene_every_pixel_blends():
    """The counting twin on image-filling faint layers (tools/bench/blend_limit.py's full-occupancy scene), where
    every count is known: each layer blends every pixel of a 40x24 image once (no pixel stops), so fragments =
    layers x pixels, and every block of each tile is tried and blended; its pixels are the drawing kernel's."""
    from tools.bench.blend_limit import full_occupancy_scene

    layers, width, height = 6, 40, 24
    arrays, square = full_occupancy_scene(width, layers)
    camera = square.resized(width, height)
    prepared = CPUSplatter().prepare(*arrays, camera)
    counts = np.zeros(len(cs.BLEND_COUNTS), dtype=np.int64)
    counted, _, _ = cs.splat_frame(prepared.rows, prepared.camera, counts)
    drawn, _, _ = cs.splat_frame(prepared.rows, prepared.camera)
    assert np.array_equal(counted, drawn)
    totals = dict(zip(cs.BLEND_COUNTS, counts.tolist(), strict=True))
    # 40x24 in TILE x TILE tiles (32: widths 32, 8 and height 24); a tile of w x h holds h / 2 row pairs and
    # (w / 4) x (h / 2) blocks of 4x2 pixels
    tiles = [(min(cs.TILE, width - x), min(cs.TILE, height - y))
             for x in range(0, width, cs.TILE) for y in range(0, height, cs.TILE)]
    assert len(tiles) > 1  # the scene crosses a tile edge
    row_pairs = sum(h // 2 for _, h in tiles)
    blocks = sum((w // 4) * (h // 2) for w, h in tiles)
    assert totals == {"pairs_binned": layers * len(tiles), "pairs_visited": layers * len(tiles),
                      "row_pairs": layers * row_pairs, "blocks_tried": layers * blocks,
                      "blocks_blended": layers * blocks, "fragments": layers * width * height}, totals
    assert np.all(counted[..., 3] > numerics.TRANSMITTANCE_MIN)  # no pixel stopped: the premise holds


def test_blend_counts_stop_at_saturation(cpu):
    """On opaque stacked Gaussians the twin visits at most the binned pairs and blends at most 8 fragments per
    block; its pixels are the drawing kernel's. Each Gaussian alone blends its whole footprint; together they
    blend fewer fragments than the footprints' sum, because covered pixels stop."""

    def counted(arrays) -> dict[str, int]:
        prepared = cpu.prepare(*arrays, camera)
        counts = np.zeros(len(cs.BLEND_COUNTS), dtype=np.int64)
        frame, _, _ = cs.splat_frame(prepared.rows, prepared.camera, counts)
        drawn, _, _ = cs.splat_frame(prepared.rows, prepared.camera)
        assert np.array_equal(frame, drawn)
        return dict(zip(cs.BLEND_COUNTS, counts.tolist(), strict=True))

    arrays, camera = _numpy(stacked_scene())
    together = counted(arrays)
    assert 0 < together["fragments"] <= 8 * together["blocks_blended"] <= 8 * together["blocks_tried"], together
    assert together["pairs_visited"] <= together["pairs_binned"], together
    alone = [counted([a[k: k + 1] for a in arrays])["fragments"] for k in range(len(arrays[0]))]
    assert together["fragments"] < sum(alone), (together, alone)


def test_blend_limit_bench_reports_counts_and_time(tmp_path):
    """`gt-bench blend-limit` on a tiny speaker: counts, per-fragment times and the ratio to full occupancy
    written (the speed itself: the bench)."""
    from typer.testing import CliRunner

    from tools.bench.app import app

    result = CliRunner().invoke(app, ["blend-limit", "--gaussians", "500", "--size", "32", "--layers", "4",
                                      "--threads", "1", "--frames", "1", "--rounds", "1", "--out", str(tmp_path)])
    assert result.exit_code == 0, result.output
    report = json.loads((tmp_path / "blend-limit.json").read_text())
    head, full = report["cases"]
    assert full["fragments"] == 4 * 32 * 32 and full["vs_full_occupancy"] == {"1": 1.0}, full
    assert 0 < head["fragments"] and head["blend_ms"]["1"] > 0, head
    ns = 1e6 * head["blend_ms"]["1"] / head["fragments"]
    assert head["core_ns_per_fragment"]["1"] == pytest.approx(ns), head
    assert "| demo head, 500 Gaussians |" in (tmp_path / "blend-limit.md").read_text()


# -- TalkingHead(renderer=...) ----------------------------------------------------------------------------------


def test_renderer_setting_is_checked():
    from gaussiantalker.runtime.settings import BackendSettings, merged_backend
    from gaussiantalker.sdk.errors import SettingsError

    assert BackendSettings().renderer == "auto"  # the CPU splatter where the only GL is a software one
    assert merged_backend("onnxruntime", renderer="cpu").renderer == "cpu"
    with pytest.raises(SettingsError, match="renderer"):
        BackendSettings(renderer="vulkan")
    with pytest.raises(SettingsError, match="given twice"):
        merged_backend(BackendSettings(renderer="gl"), renderer="cpu")


def test_auto_picks_cpu_on_a_software_gl_and_says_why(monkeypatch, caplog):
    from gaussiantalker.runtime.splat import choice as renderer_module
    from gaussiantalker.sdk.errors import SettingsError

    assert renderer_module.is_software_renderer("llvmpipe (LLVM 15.0.6, 256 bits)")
    assert renderer_module.is_software_renderer("Google SwiftShader")
    assert not renderer_module.is_software_renderer("NVIDIA GeForce RTX 4090/PCIe/SSE2")
    monkeypatch.setattr(renderer_module, "_reported", set())
    with caplog.at_level("INFO", logger="gaussiantalker.runtime"):
        splatter, name = renderer_module.make_splatter("auto")
    is_software = renderer_module.is_software_renderer(GLSplatter().ctx.info["GL_RENDERER"])
    assert name == ("cpu" if is_software else "gl") and isinstance(splatter, CPUSplatter) == (name == "cpu")
    assert f"the {name} splatter" in caplog.text
    splatter.release()
    monkeypatch.setattr(renderer_module, "cpu_splatter_available", lambda: False)
    splatter, name = renderer_module.make_splatter("auto")  # no numba: GL, whatever the GL is
    assert name == "gl"
    splatter.release()
    with pytest.raises(SettingsError, match=r"gaussiantalker-sdk\[cpu\]"):
        renderer_module.make_splatter("cpu")


def _head_frames(path, renderer, drives, output="uint8", **kwargs):
    from gaussiantalker.runtime import TalkingHead

    with TalkingHead(path, renderer=renderer, **kwargs) as head:
        assert head.renderer == renderer
        return [head.render(drive, output) for drive in drives]


@pytest.fixture(scope="module")
def small_drives(small_export):
    from gaussiantalker.exporter.export.probes import driven_clip

    return driven_clip(small_export.speaker, 4)[1]


def test_small_speaker_frames_match_torch(small_export):
    """End to end (audio -> translator -> deformation graph -> CPU splatter) against the torch speaker."""
    from gaussiantalker.exporter.verify.bundle_verify import verify_frames
    from gaussiantalker.runtime import TalkingHead

    with TalkingHead(small_export.path, resolution=(128, 128), renderer="cpu") as head:
        report = verify_frames(small_export.speaker, head, frames=4)
    assert all(f["finite"] for f in report["frames"])
    assert min(f["psnr_db"] for f in report["frames"]) >= MIN_PSNR_8BIT


@pytest.mark.parametrize("camera", ["bundle", "novel"])
def test_small_speaker_frames_match_gl(small_export, small_drives, camera):
    kwargs = {"resolution": (96, 80)}
    if camera == "novel":  # off-centre principal point, another angle and distance
        base = Camera.looking_at([0.25, -0.1, 0.45], [0.0, 0.0, 0.0], [0.0, -1.0, 0.0], 96, 80, 35.0)
        kwargs = {"camera": Camera(96, 80, base.fx, base.fy * 1.1, 30.0, 50.0, base.R, base.t)}
    cpu = _head_frames(small_export.path, "cpu", small_drives, **kwargs)
    gl = _head_frames(small_export.path, "gl", small_drives, **kwargs)
    for mine, theirs in zip(cpu, gl, strict=True):
        assert (mine != mine[0, 0]).any()  # the head is in view
        assert psnr_db(mine.astype(np.float64) / 255, theirs.astype(np.float64) / 255) >= MIN_PSNR_8BIT


def test_nan_drives_are_refused_before_the_cpu_splatter(small_export):
    from gaussiantalker.runtime import TalkingHead
    from gaussiantalker.sdk.errors import DriveError

    with TalkingHead(small_export.path, resolution=(32, 32), renderer="cpu") as head:
        with pytest.raises(DriveError, match="jaw pose has non-finite values"):
            head.render_params(jaw_pose=[np.nan, 0.0, 0.0])
        assert head.render_params(jaw_pose=[0.2, 0.0, 0.0]).std() > 0  # and the head still draws


@pytest.mark.parametrize("preset", ["quality", "balanced", "compact", "fast", "mobile"])
def test_presets_match_gl(small_export, reduced_export, small_drives, preset):
    """Every preset's bundle and its GL render settings, CPU vs GL (GL's framebuffer in float32: the CPU always
    blends in float32, so an 8-bit or float16 framebuffer is a GL-only loss). Both draw with the same settings: a
    preset's own CPU settings (`fast`'s alpha cut) are a trade of their own, measured in docs/precision.md. `fast`
    draws at 3/4 size: the upscale's bilinear weights are 8-bit in llvmpipe's sampler, so its bound is that of the
    render-scale test (45 dB)."""
    from dataclasses import replace

    from gaussiantalker.sdk.render_settings import stored_defaults

    path = small_export.path if preset == "quality" else reduced_export(preset)  # quality: the fp32 default
    settings = replace(stored_defaults(Bundle(path).manifest, "gl"), render_target="float32")
    cpu = _head_frames(path, "cpu", small_drives, resolution=(96, 96), render_settings=settings)
    gl = _head_frames(path, "gl", small_drives, resolution=(96, 96), render_settings=settings)
    bound = 45.0 if preset == "fast" else MIN_PSNR_8BIT
    for mine, theirs in zip(cpu, gl, strict=True):
        assert psnr_db(mine.astype(np.float64) / 255, theirs.astype(np.float64) / 255) >= bound


def test_semantic_and_alpha_outputs_match_gl(small_export, small_drives):
    drives = small_drives[:1]
    for output in ("semantic", "rgba", "rgba_float"):
        mine = _head_frames(small_export.path, "cpu", drives, output, resolution=(64, 64))[0]
        theirs = _head_frames(small_export.path, "gl", drives, output, resolution=(64, 64))[0]
        assert mine.shape == theirs.shape and mine.dtype == theirs.dtype
        scale = 255.0 if mine.dtype == np.uint8 else 1.0
        assert psnr_db(mine.astype(np.float64) / scale, theirs.astype(np.float64) / scale) >= MIN_PSNR_8BIT, output


@pytest.mark.parametrize("key_bits", [32, 16])
def test_fused_prepare_keeps_the_numpy_order_and_culls(key_bits):
    """`cpu_sort.sorted_packed_rows` (the CPU splatter's prepare when it sorts every frame) returns exactly the rows
    of numpy's `pack_gaussians(...)[depth_order(..., key_bits)]` on scenes built to split them: equal depths (the
    stable order decides), rows at and just in front of the near plane, NaN and infinities in every column,
    overflowing depths, signed zeros and denormals; seeded, 300 scenes, with 32-bit and 16-bit keys."""
    from gaussiantalker.runtime.splat.common import checked_gaussians, pack_gaussians
    from gaussiantalker.runtime.splat.cpu_sort import sorted_packed_rows
    from gaussiantalker.runtime.splat.depth_sort import depth_order

    rng = np.random.default_rng(7)
    tilted_camera, axis_camera = off_centre_camera(24, 16), Camera(24, 16, 20.0, 20.0, 12.0, 8.0, near=0.25)
    specials = np.array([np.nan, np.inf, -np.inf, 0.0, -0.0, 1e-45, 3e38, -3e38], dtype=np.float32)
    for case in range(300):
        n = int(rng.integers(0, 60))
        rows = rng.normal(0.0, 1.0, (n, 13)).astype(np.float32)
        if n and case % 3 == 0:  # depth ties: copies of a few means
            rows[:, 0:3] = rows[rng.integers(0, max(1, n // 4), n), 0:3]
        if n and case % 3 == 1:  # hostile values anywhere
            hits = rng.random((n, 13)) < 0.05
            rows[hits] = rng.choice(specials, int(hits.sum()))
        if n and case % 5 == 0:  # on the near plane of the axis-aligned camera (z = mean z exactly), and a ulp off
            near = np.float32(axis_camera.near)
            rows[: n // 2, 2] = rng.choice([near, np.nextafter(near, np.float32(0)), np.nextafter(near, np.float32(1))],
                                           n // 2)
        camera = axis_camera if case % 5 == 0 else tilted_camera
        arrays = (rows[:, 0:3], rows[:, 3:9], rows[:, 9:12], rows[:, 12])
        packed = pack_gaussians(*arrays)
        expected = packed[depth_order(packed, camera, key_bits)]
        got = sorted_packed_rows(*checked_gaussians(*arrays), camera, key_bits)
        assert got.shape == expected.shape and np.array_equal(got.view(np.uint32), expected.view(np.uint32)), case


def test_prepare_sorts_by_the_key_bits_asked_for():
    """The CPU splatter's prepare honours `sort_key_bits` (16-bit keys through the fused passes, as 32-bit ones):
    on depths that tie at 16 bits but not at 32, the 16-bit splatter keeps index order and the default one sorts
    exactly; with a sort interval it goes through `DepthSorter` and gives the same first order."""
    from gaussiantalker.runtime.splat.common import pack_gaussians
    from gaussiantalker.runtime.splat.depth_sort import depth_order

    camera = off_centre_camera(24, 16)
    # depths 3 + offset along the view axis: range 1, three within 1e-5 of 0.2 (one 16-bit level is 1 / 65535),
    # in decreasing depth for increasing index
    offsets = np.array([0.0, 1.0, 0.2 + 9e-6, 0.2 + 5e-6, 0.2 + 1e-6])
    means = (camera.center + np.outer(3.0 + offsets, camera.R[2])).astype(np.float32)
    arrays = [means, np.tile(np.float32([0.01, 0, 0, 0.01, 0, 0.01]), (5, 1)), np.full((5, 3), 0.5, np.float32),
              np.full(5, 0.8, np.float32)]
    packed = pack_gaussians(*arrays)
    quantised, exact = depth_order(packed, camera, 16), depth_order(packed, camera)
    assert list(quantised) == [0, 2, 3, 4, 1] and list(exact) == [0, 4, 3, 2, 1]  # the premise
    coarse = CPUSplatter(settings=RenderSettings(sort_key_bits=16))
    assert np.array_equal(coarse.prepare(*arrays, camera).rows, packed[quantised])
    assert np.array_equal(CPUSplatter().prepare(*arrays, camera).rows, packed[exact])
    every_other = CPUSplatter(settings=RenderSettings(sort_key_bits=16, sort_interval=2))
    assert np.array_equal(every_other.prepare(*arrays, camera).rows, packed[quantised])
