"""The GL splatter's experimental early stop of saturated pixels (RenderSettings.early_stop; docs/numerics.md,
"Early stop of saturated pixels"): agreement with the plain draw, identical frames where nothing saturates, the
segment cutting, and settings validation."""

from __future__ import annotations

import numpy as np
import pytest
from test_splatter import BACKGROUND, FLOAT_TOL, make_camera, random_scene

from gaussiantalker.runtime.splat.gl import GLSplatter, early_stop_segments
from gaussiantalker.sdk import numerics
from gaussiantalker.sdk.render_settings import MAX_EARLY_STOPS, RenderSettings

SETTINGS = ((0.5,), (0.2, 0.4, 0.6, 0.8))


@pytest.fixture(scope="module")
def plain():
    instance = GLSplatter()
    yield instance
    instance.release()


def _early(plain: GLSplatter, fractions: tuple[float, ...], **settings) -> GLSplatter:
    return GLSplatter(plain.ctx, settings=RenderSettings(early_stop=fractions, **settings))


def _bound(rgb: np.ndarray) -> float:
    """What a pixel marked saturated can differ by: the later Gaussians' blend weights sum to at most its
    transmittance when marked (< TRANSMITTANCE_MIN), and each moves the pixel by weight * |colour - background|;
    FLOAT_TOL covers the float32 blending of the two draws' different sums."""
    return numerics.TRANSMITTANCE_MIN * float(np.abs(rgb[:, None, :] - np.asarray(BACKGROUND)).max()) + FLOAT_TOL


@pytest.mark.parametrize("fractions", SETTINGS)
def test_dense_opaque_scene_agrees_with_the_plain_draw(plain, fractions):
    """Nearly opaque splats: pixels saturate early, the early stop changes them, by no more than `_bound`."""
    camera = make_camera(64, 48)
    scene = random_scene(7, n=200, opacity_max=0.99, scale=0.15)
    expected = plain.render(*scene, camera, BACKGROUND, output="float")
    transmittance = 1.0 - plain.render(*scene, camera, BACKGROUND, output="rgba_float")[..., 3]
    assert (transmittance < numerics.TRANSMITTANCE_MIN).mean() > 0.2  # the scene does saturate
    early = _early(plain, fractions)
    try:
        frame = early.render(*scene, camera, BACKGROUND, output="float")
        premultiplied = early.render(*scene, camera, BACKGROUND, output="rgba_float")
    finally:
        early.release()
    difference = np.abs(frame - expected)
    assert difference.max() > 0  # skipped Gaussians did change pixels: the stop is really applied
    assert difference.max() <= _bound(scene[2])
    # The alpha output stops alike: coverage 1 - T moves by at most the skipped weights (< TRANSMITTANCE_MIN).
    assert np.abs(premultiplied[..., 3] - (1.0 - transmittance)).max() <= numerics.TRANSMITTANCE_MIN + FLOAT_TOL


def test_demo_speaker_agrees_with_the_plain_draw(plain):
    """The opaque demo head at 96 px: within `_bound` of the plain draw, and within one 8-bit level."""
    torch = pytest.importorskip("torch")
    from gaussiantalker.exporter.demo.demo_speaker import make_demo_speaker
    from tools.bench.early_stop import splat_inputs

    torch.manual_seed(0)
    speaker, _ = make_demo_speaker(2000, train_seconds=0, progress=False)
    inputs = splat_inputs(speaker, 96, pose_frame=25)
    early = _early(plain, (0.3, 0.6))
    try:
        frame = early.render(*inputs, BACKGROUND, output="float")
        frame8 = early.render(*inputs, BACKGROUND).astype(int)
    finally:
        early.release()
    expected = plain.render(*inputs, BACKGROUND, output="float")
    difference = np.abs(frame - expected)
    assert difference.max() > 0
    assert difference.max() <= _bound(inputs[2])
    # Differences below TRANSMITTANCE_MIN can still cross an 8-bit rounding boundary: one level at most.
    assert np.abs(frame8 - plain.render(*inputs, BACKGROUND).astype(int)).max() <= 1


def test_nothing_saturated_gives_identical_frames(plain):
    """Translucent splats never take T below TRANSMITTANCE_MIN: no pixel is marked, the frames are bit-identical."""
    camera = make_camera(64, 48)
    scene = random_scene(3, n=60, opacity_max=0.3, scale=0.1)
    transmittance = 1.0 - plain.render(*scene, camera, BACKGROUND, output="rgba_float")[..., 3]
    assert transmittance.min() > numerics.TRANSMITTANCE_MIN
    expected = plain.render(*scene, camera, BACKGROUND, output="float")
    early = _early(plain, SETTINGS[1])
    try:
        np.testing.assert_array_equal(early.render(*scene, camera, BACKGROUND, output="float"), expected)
    finally:
        early.release()


def test_render_scale_and_point_quad_mix_with_early_stop(plain):
    """Early stop under a render scale (the upscale pass after it) and with quads only agrees with the plain draw
    under the same settings."""
    camera = make_camera(64, 48)
    scene = random_scene(7, n=200, opacity_max=0.99, scale=0.15)
    scaled_plain = GLSplatter(plain.ctx, settings=RenderSettings(render_scale=0.5))
    scaled_early = _early(plain, (0.5,), render_scale=0.5)
    quads_early = GLSplatter(plain.ctx, point_sprites=False, settings=RenderSettings(early_stop=(0.5,)))
    try:
        expected = scaled_plain.render(*scene, camera, BACKGROUND, output="float")
        frame = scaled_early.render(*scene, camera, BACKGROUND, output="float")
        assert frame.shape == expected.shape == (48, 64, 3)
        assert np.abs(frame - expected).max() <= _bound(scene[2])  # bilinear weights sum to 1: same bound
        full = plain.render(*scene, camera, BACKGROUND, output="float")
        assert np.abs(quads_early.render(*scene, camera, BACKGROUND, output="float") - full).max() <= \
            _bound(scene[2])
    finally:
        for s in (scaled_plain, scaled_early, quads_early):
            s.release()


def test_segments_cover_every_gaussian_once_in_order():
    runs = [(0, 10, False), (10, 15, True), (15, 20, False)]
    segments = early_stop_segments(runs, (0.25, 0.6))
    assert segments == [[(0, 5, False)], [(5, 10, False), (10, 12, True)], [(12, 15, True), (15, 20, False)]]
    assert early_stop_segments(runs, ()) == [runs]
    assert early_stop_segments([(0, 2, False)], (0.1,)) == [[(0, 2, False)]]  # rounds to 0: no cut
    assert early_stop_segments([], (0.5,)) == [[]]


@pytest.mark.parametrize("bad", [0.5, "0.5", (0.0,), (1.0,), (0.5, 0.5), (0.6, 0.4), (float("nan"),), (True,),
                                 tuple(0.05 * (i + 1) for i in range(MAX_EARLY_STOPS + 1))])
def test_bad_early_stop_settings_are_refused(bad):
    with pytest.raises(ValueError, match="early_stop must be"):
        RenderSettings(early_stop=bad)


def test_early_stop_setting_round_trips_through_a_manifest_table():
    settings = RenderSettings(early_stop=[0.25, 0.5])
    assert settings.early_stop == (0.25, 0.5)
    assert RenderSettings.from_dict(settings.to_dict()) == settings
    assert "early_stop" not in RenderSettings().to_dict()  # off: bundles stay readable by older runtimes


@pytest.mark.parametrize("target", ["float16", "uint8"])
def test_lower_precision_targets_agree_with_their_plain_draw(plain, target):
    """float16/uint8 framebuffers round the stored 1 - T, so a pixel is marked at T up to ~2.4e-4 / 1/510; the skipped
    weights sum to at most that (measured: the frames are identical, the rounded alpha reaches 1 and the plain draw
    adds nothing after it either)."""
    camera = make_camera(64, 48)
    scene = random_scene(7, n=200, opacity_max=0.99, scale=0.15)
    same = GLSplatter(plain.ctx, settings=RenderSettings(render_target=target))
    early = _early(plain, (0.3, 0.6), render_target=target)
    try:
        expected = same.render(*scene, camera, BACKGROUND, output="float")
        frame = early.render(*scene, camera, BACKGROUND, output="float")
    finally:
        same.release()
        early.release()
    mark_t = {"float16": 2.0**-12, "uint8": 0.5 / 255}[target]  # the largest T that rounds to a stored alpha of 1
    assert np.abs(frame - expected).max() <= mark_t * np.abs(scene[2][:, None, :] - np.asarray(BACKGROUND)).max() \
        + FLOAT_TOL
