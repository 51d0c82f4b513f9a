"""TalkingHead's grouped settings (render_settings=, output_settings=, backend_settings=): the same frames as the
shortcut keywords, one setting given twice refused naming both, frozen groups that name a bad field, and write_video
from a VideoPlan."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from gaussiantalker.exporter.export.speech import synth_speech
from gaussiantalker.runtime import (
    BackendSettings,
    OutputSettings,
    RenderError,
    RenderSettings,
    SettingsError,
    TalkingHead,
    VideoError,
    VideoPlan,
    plan_video,
)
from gaussiantalker.sdk.camera import Camera

AUDIO = synth_speech(0.2, seed=6)  # 5 frames


@pytest.fixture(scope="module")
def bundle(small_export):
    return small_export.path


def _frames(head: TalkingHead) -> list[np.ndarray]:
    return [head.render_params(jaw_pose=[0.2, 0, 0], head_rotation=[0, 0.2, 0], output="float"),
            *head.frames(AUDIO, 16000)]


def test_groups_give_the_shortcuts_frames_bit_for_bit(bundle):
    """Every setting, once as a shortcut keyword and once in its group: the same settings and the same pixels."""
    camera = Camera.looking_at([0.1, 0, 0.7], [0, 0, 0], [0, 1, 0], 70, 50, 30.0)
    shortcuts = dict(resolution=(64, 48), camera=camera, background=(0.1, 0.2, 0.3), composite=False,
                     render_scale=0.5, render_target="float16", sort_interval=2, sort_key_bits=16, threads=1,
                     shader_target="410")
    groups = dict(output_settings=OutputSettings(resolution=(64, 48), camera=camera, background=(0.1, 0.2, 0.3),
                                        composite=False),
                  render_settings=RenderSettings(render_scale=0.5, render_target="float16", sort_interval=2,
                                                 sort_key_bits=16),
                  backend_settings=BackendSettings("onnxruntime", threads=1, shader_target="410"))
    # The same value given both ways is one setting, not a conflict.
    both = {**shortcuts, **groups}
    results = []
    for kwargs in (shortcuts, groups, both):
        with TalkingHead(bundle, **kwargs) as head:
            results.append((head.render_settings, head.backend_settings, head.output_settings, _frames(head)))
    expected = results[0]
    assert expected[0] == RenderSettings(0.5, "float16", 2, 16, graph_threads=1)
    assert expected[1] == BackendSettings("onnxruntime", 1, "410")
    assert expected[2] == groups["output_settings"]
    assert expected[3][0].shape == (48, 64, 3) and len(expected[3]) == 6
    for result in results[1:]:
        assert result[:3] == expected[:3]
        for frame, reference in zip(result[3], expected[3], strict=True):
            np.testing.assert_array_equal(frame, reference)


def test_the_cpu_splatters_knobs_reach_it_as_shortcuts_and_in_the_group(bundle):
    """alpha_min and transmittance_min, as keywords and in render_settings: the same settings on the CPU splatter
    and the same pixels."""
    knobs = dict(alpha_min=0.02, transmittance_min=4 / 255)
    results = []
    for kwargs in (knobs, {"render_settings": RenderSettings(**knobs)}):
        with TalkingHead(bundle, renderer="cpu", resolution=(64, 48), **kwargs) as head:
            assert head.frame_renderer.splatter.settings == head.render_settings
            results.append((head.render_settings, _frames(head)))
    assert results[0][0] == RenderSettings(**knobs)
    for frame, reference in zip(results[1][1], results[0][1], strict=True):
        np.testing.assert_array_equal(frame, reference)


def test_a_group_left_out_keeps_the_bundle_defaults(bundle):
    """No group and no shortcut: the bundle's camera, background and preset; a partial group sets only its own."""
    with TalkingHead(bundle, output_settings=OutputSettings(resolution=(40, 30))) as head:
        assert head.frame_size == (40, 30)
        assert head.render_settings == RenderSettings()  # the small bundle stores no preset: the contract's frame
        assert head.backend_settings == BackendSettings()
        np.testing.assert_array_equal(head.frame_renderer.background, np.float32(head.bundle.manifest["background"]))
        corner = head.render_params()[0, 0]
    with TalkingHead(bundle, resolution=(40, 30)) as shortcut:
        assert shortcut.output_settings == head.output_settings
        np.testing.assert_array_equal(shortcut.render_params()[0, 0], corner)


@pytest.mark.parametrize("kwargs, names", [
    ({"resolution": (64, 48), "output_settings": OutputSettings(resolution=(32, 32))},
     ("resolution=", "output.resolution=")),
    ({"background": (0, 0, 0), "output_settings": OutputSettings(background=(1, 1, 1))},
     ("background=", "output.background=")),
    ({"composite": True, "output_settings": OutputSettings(composite=False)}, ("composite=", "output.composite=")),
    ({"camera": Camera(8, 8, 8.0, 8.0, 4.0, 4.0),
      "output_settings": OutputSettings(camera=Camera(9, 9, 8.0, 8.0, 4.0, 4.0))},
     ("camera=", "output.camera=")),
    ({"threads": 2, "backend_settings": BackendSettings(threads=1)}, ("threads=2", "backend.threads=1")),
    ({"shader_target": "410", "backend_settings": BackendSettings(shader_target="300es")},
     ("shader_target='410'", "backend.shader_target='300es'")),
    ({"render_scale": 0.5, "render_settings": RenderSettings(render_scale=0.75)},
     ("render_scale=0.5", "render.render_scale=0.75")),
    ({"sort_key_bits": 16, "render_settings": RenderSettings()}, ("sort_key_bits=16", "render.sort_key_bits=32")),
    ({"transmittance_min": 0.01, "render_settings": RenderSettings()},
     ("transmittance_min=0.01", "render.transmittance_min=0.0001")),
    ({"threads": 2, "render_settings": RenderSettings(graph_threads=3)}, ("threads=2", "render.graph_threads=3")),
    ({"backend_settings": BackendSettings(threads=2), "render_settings": RenderSettings(graph_threads=3)},
     ("backend.threads=2", "render.graph_threads=3")),
])
def test_a_setting_given_twice_is_refused_naming_both(bundle, kwargs, names):
    with pytest.raises(SettingsError) as raised:
        TalkingHead(bundle, **kwargs)
    message = str(raised.value)
    assert all(name in message for name in names), message
    assert "given twice" in message and "give it once" in message
    assert isinstance(raised.value, ValueError) and isinstance(raised.value, RenderError)


def test_groups_are_frozen_and_compared_by_value():
    camera = Camera(8, 8, 8.0, 8.0, 4.0, 4.0)
    for group, name in ((OutputSettings(resolution=(8, 8)), "resolution"), (BackendSettings(), "threads"),
                        (RenderSettings(), "render_scale")):
        with pytest.raises(dataclasses.FrozenInstanceError):
            setattr(group, name, None)
    same = OutputSettings(camera=camera, background=[0, 0.5, 1])
    assert same == OutputSettings(camera=Camera(8, 8, 8.0, 8.0, 4.0, 4.0), background=(0.0, 0.5, 1.0))
    assert hash(same) == hash(OutputSettings(camera=Camera(8, 8, 8.0, 8.0, 4.0, 4.0), background=(0, 0.5, 1)))
    assert same != OutputSettings(camera=Camera(9, 8, 8.0, 8.0, 4.0, 4.0), background=(0, 0.5, 1))
    assert OutputSettings(resolution=np.array([64, 48])).resolution == (64, 48)
    assert BackendSettings("mnn", 2) == BackendSettings(name="mnn", threads=2, shader_target="330")


def test_overrides_leave_what_is_not_given_and_0_removes_the_pixel_cap():
    """with_overrides: None means "not given" (the stored value stays); the pixel cap, whose own "none" is None,
    is removed by 0; a negative cap is still refused."""
    stored = RenderSettings(render_scale=0.75, max_draw_pixels=256 * 256)
    assert stored.with_overrides(max_draw_pixels=None, render_scale=None) == stored
    assert stored.with_overrides(max_draw_pixels=0) == RenderSettings(render_scale=0.75)
    assert stored.with_overrides(max_draw_pixels=128 * 128).max_draw_pixels == 128 * 128
    with pytest.raises(ValueError, match="max_draw_pixels must be a whole number >= 1 or None"):
        stored.with_overrides(max_draw_pixels=-1)


@pytest.mark.parametrize("make, message", [
    (lambda: OutputSettings(resolution=(0, 48)), "output resolution must be \\(width, height\\)"),
    (lambda: OutputSettings(resolution=(64,)), "output resolution must be"),
    (lambda: OutputSettings(resolution=(64.5, 48)), "output resolution must be"),
    (lambda: OutputSettings(resolution=(True, 48)), "output resolution must be"),
    (lambda: OutputSettings(background=(1, 1)), "output background must be 3 finite numbers"),
    (lambda: OutputSettings(background=(np.nan, 0, 0)), "output background must be 3 finite numbers"),
    (lambda: OutputSettings(camera="front"), "output camera must be a gaussiantalker.sdk.camera.Camera, got str"),
    (lambda: OutputSettings(composite="yes"), "output composite must be True, False or None"),
    (lambda: BackendSettings("tensorrt"), "unknown graph backend 'tensorrt' \\(known: onnxruntime, mnn\\)"),
    (lambda: BackendSettings(threads=0), "backend threads must be a whole number >= 1"),
    (lambda: BackendSettings(threads=True), "backend threads must be a whole number >= 1"),
    (lambda: BackendSettings(shader_target="450"), "unknown shader target '450'; allowed: '330', '410', '300es'"),
])
def test_a_bad_field_is_named(make, message):
    with pytest.raises(SettingsError, match=message):
        make()


@pytest.mark.parametrize("kwargs, message", [
    ({"render_settings": {"render_scale": 0.5}}, "render_settings= must be a RenderSettings \\(or None\\), got dict"),
    ({"output_settings": (64, 48)}, "output_settings= must be a OutputSettings \\(or None\\), got tuple"),
    ({"backend_settings": "mnn"}, "backend_settings= must be a BackendSettings \\(or None\\), got str"),
    ({"backend": 3}, "backend= must be a backend name \\(onnxruntime, mnn\\) or a BackendSettings, got int"),
    ({"backend": "tensorrt"}, "unknown graph backend 'tensorrt'"),
    ({"resolution": (0, 4)}, "output resolution must be"),
    ({"render_scale": 0.05}, "render_scale must be a number in 0.1..1"),
    ({"render_settings": RenderSettings(), "render_scale": 0.05}, "render_scale given twice"),
])
def test_bad_groups_and_shortcuts_are_refused_before_loading(bundle, kwargs, message):
    with pytest.raises(SettingsError, match=message):
        TalkingHead(bundle, **kwargs)


# -- video plans ---------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def head(bundle):
    with TalkingHead(bundle, resolution=(32, 24)) as talking_head:
        yield talking_head


def test_write_video_from_a_plan_writes_the_same_file_as_from_a_path(head, tmp_path):
    """A png sequence (lossless, byte-stable): the plan form writes exactly the frames the path form writes."""
    by_path = head.write_video(tmp_path / "path" / "%03d.png", AUDIO, 16000)
    plan = head.plan_video(tmp_path / "plan" / "%03d.png")
    assert isinstance(plan, VideoPlan) and plan.size == (32, 24) == head.frame_size
    assert plan == plan_video(tmp_path / "plan" / "%03d.png", (32, 24))  # what sdk.video_formats plans
    by_plan = head.write_video(plan_video(tmp_path / "plan" / "%03d.png", (32, 24)), AUDIO, 16000)
    assert by_plan == plan.path
    written = sorted(p.name for p in by_path.parent.iterdir())
    assert len(written) == 5 and written == sorted(p.name for p in by_plan.parent.iterdir())
    for name in written:
        assert (by_path.parent / name).read_bytes() == (by_plan.parent / name).read_bytes()


def test_write_video_from_a_plan_with_alpha(head, tmp_path):
    plan = head.plan_video(tmp_path / "talk.webm", alpha=True)
    assert plan.alpha
    path = head.write_video(plan, AUDIO, 16000)
    from gaussiantalker.sdk.video import probe_video

    info = probe_video(path)
    assert (info["frames"], info["has_alpha"], info["has_audio"]) == (5, True, True)


def test_a_plan_that_does_not_fit_is_refused_before_the_first_frame(head, tmp_path, monkeypatch):
    monkeypatch.setattr(head, "frames", lambda *a, **k: pytest.fail("a frame was rendered"))
    plan = head.plan_video(tmp_path / "talk.mp4")
    for plan_given, options, message in [
        (plan_video(tmp_path / "talk.mp4", (64, 48)), {}, "VideoPlan is for 64x48 frames but this head renders 32x24"),
        (plan, {"codec": "h264"}, "a VideoPlan already sets the output; give it or codec='h264', not both"),
        (plan, {"crf": 20, "container": "mp4"}, "give it or crf=20, container='mp4', not both"),
        (plan, {"alpha": True}, "alpha=True but the VideoPlan has alpha=False"),
    ]:
        with pytest.raises(VideoError, match=message):
            head.write_video(plan_given, AUDIO, 16000, **options)
    assert head.write_video.__doc__ and list(tmp_path.iterdir()) == []


def test_output_view_says_the_frames_before_loading(bundle, tmp_path, monkeypatch):
    """TalkingHead.output_view reads the manifest only: the head it describes has its camera and compositing."""
    view = TalkingHead.output_view(bundle, OutputSettings(resolution=(40, 30)))
    assert view.size == (40, 30) and not view.composite
    assert TalkingHead.output_view(bundle, resolution=(40, 30)).camera.to_dict() == view.camera.to_dict()
    with pytest.raises(VideoError, match="mp4 cannot hold an alpha channel"):
        view.plan_video(tmp_path / "talk.mp4", alpha=True)
    with pytest.raises(SettingsError, match="resolution given twice"):
        TalkingHead.output_view(bundle, OutputSettings(resolution=(40, 30)), resolution=(41, 30))
    with TalkingHead(bundle, output_settings=OutputSettings(resolution=(40, 30))) as head:
        assert head.camera.to_dict() == view.camera.to_dict() and (head.compositor is not None) == view.composite
