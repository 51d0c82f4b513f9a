"""The frame's path as public stages (docs/embedding.md, "Stages"): TalkingHead is a thin front over a Driver per rig,
a FrameRenderer with a Splatter, and a Compositor; the names it had before keep working for one release and warn once
("Renamed names")."""

from __future__ import annotations

import ast
import inspect
import warnings

import numpy as np
import pytest

import gaussiantalker.runtime.head as head_module
from gaussiantalker.runtime import BackendSettings, OutputSettings, RenderSettings, TalkingHead, renamed
from gaussiantalker.runtime.compositor import Compositor
from gaussiantalker.runtime.driver import ArkitDriver, FlameDriver
from gaussiantalker.runtime.frame_renderer import FrameRenderer
from gaussiantalker.runtime.splat.common import Splatter
from gaussiantalker.runtime.splat.gl import GLSplatter
from gaussiantalker.sdk.errors import RenderError, SettingsError

MAX_HEAD_LINES = 250
MAX_HEAD_PUBLIC_NAMES = 25
SPEECH_RATE = 16000


def _speech(seconds: float = 0.5) -> np.ndarray:
    t = np.arange(int(seconds * SPEECH_RATE)) / SPEECH_RATE
    return (0.3 * np.sin(2 * np.pi * 180 * t) * (1 + np.sin(2 * np.pi * 3 * t))).astype(np.float32)


@pytest.fixture(autouse=True)
def fresh_warnings(monkeypatch):
    """Each test sees every renamed name's first warning (they warn once per process)."""
    monkeypatch.setattr(renamed, "_warned", set())


def test_head_file_is_a_thin_front():
    source = inspect.getsource(head_module)
    assert len(source.splitlines()) <= MAX_HEAD_LINES


def test_head_has_at_most_25_public_names(small_export):
    with TalkingHead(small_export.path, resolution=(64, 64), composite=False) as head:
        names = {name for name in dir(TalkingHead) if not name.startswith("_")}
        names |= {name for name in vars(head) if not name.startswith("_")}
    assert len(names) <= MAX_HEAD_PUBLIC_NAMES, sorted(names)
    assert {"driver", "frame_renderer", "compositor", "frames", "drives", "render", "write_video", "live"} <= names


def test_the_stages_a_head_is_built_from(small_export, lam_voice_bundle):
    with TalkingHead(small_export.path, resolution=(64, 64), composite=False, renderer="gl") as head:
        assert isinstance(head.driver, FlameDriver) and isinstance(head.frame_renderer, FrameRenderer)
        assert head.compositor is None and isinstance(head.frame_renderer.splatter, GLSplatter)
        assert isinstance(head.frame_renderer.splatter, Splatter)
        assert head.driver.timings is head.frame_renderer.timings is head.timings
    with TalkingHead(lam_voice_bundle, resolution=(64, 64), renderer="cpu") as head:
        assert isinstance(head.driver, ArkitDriver) and head.renderer == "cpu"
        assert isinstance(head.frame_renderer.splatter, Splatter)


def test_composited_head_has_a_compositor(clip_export):
    with TalkingHead(clip_export.path, resolution=(64, 80)) as head:
        assert isinstance(head.compositor, Compositor)
        drive = next(head.drives(_speech(), SPEECH_RATE))
        direct = head.render(drive, reference_frame=0)
        staged = head.compositor.frame(head.frame_renderer.draw(head.frame_renderer.prepare(drive), "rgba_float"), 0)
        assert np.array_equal(direct, staged)


def test_frames_through_the_stages_equal_the_head_frames(small_export):
    with TalkingHead(small_export.path, resolution=(64, 64), composite=False, pipeline=False) as head:
        frames = list(head.frames(_speech(), SPEECH_RATE))
        drives = list(head.driver.drives(_speech(), SPEECH_RATE))
        staged = [head.frame_renderer.render(drive) for drive in drives]
    assert len(frames) == len(staged) == head.driver.frame_count(_speech().shape[0])
    assert all(np.array_equal(a, b) for a, b in zip(frames, staged, strict=True))


def test_motion_frames_are_frames_of_a_motion(lam_voice_bundle):
    weights = np.zeros((4, 52), np.float32)
    weights[:, 24] = np.linspace(0, 1, 4)  # jawOpen
    with TalkingHead(lam_voice_bundle, resolution=(64, 64)) as head:
        new = list(head.frames(motion=weights))
        with pytest.warns(DeprecationWarning, match=r"motion_frames is deprecated.*frames\(motion="):
            old = list(head.motion_frames(weights))
    assert len(new) == 4 and all(np.array_equal(a, b) for a, b in zip(new, old, strict=True))


@pytest.mark.parametrize("name", sorted(renamed.RENAMED_ATTRIBUTES))
def test_each_renamed_name_warns_once_and_still_works(small_export, name):
    with TalkingHead(small_export.path, resolution=(64, 64), composite=False) as head:
        with pytest.warns(DeprecationWarning, match=f"TalkingHead.{name} is deprecated") as caught:
            value = getattr(head, name)
        assert len(caught) == 1 and caught[0].filename == __file__  # points at the caller's line
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            again = getattr(head, name)  # once per process: no second warning
        if name == "composite_frame":
            with pytest.raises(RenderError, match="compositing is off for this head"):
                value(np.zeros((64, 64, 4), np.float32), 0)
            return
        expected = renamed.RENAMED_ATTRIBUTES[name][1](head)
        if callable(expected) and not isinstance(expected, np.ndarray):
            assert callable(value) and callable(again)
        else:
            assert value is expected or np.array_equal(value, expected)


def test_renamed_calls_give_what_the_new_ones_give(small_export):
    audio = _speech()
    with TalkingHead(small_export.path, resolution=(64, 64), composite=False) as head, \
            warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        expression, jaw = head.translate(audio)
        blocks = list(head.translate_blocks(audio))
        drive = next(head.drives(audio, SPEECH_RATE))
        assert np.array_equal(head.gaussians(drive)["means"], head.frame_renderer.deform(drive)["means"])
        assert np.array_equal(head.draw(head.prepare(drive)), head.render(drive))
        assert head.frame_count(audio.shape[0]) == expression.shape[0]
        assert head.load_audio(audio, SPEECH_RATE).shape == audio.shape
    new = np.concatenate(list(head.driver.translate_blocks(audio)))
    assert np.array_equal(np.concatenate([b[0] for b in blocks]), new[:, :-3]) and np.array_equal(jaw, new[:, -3:])


def test_old_settings_keywords_warn_and_mean_the_new_ones(small_export):
    old = r"TalkingHead\((render|output|backend)=\.\.\.\) is deprecated"
    with pytest.warns(DeprecationWarning, match=old) as caught:
        head = TalkingHead(small_export.path, render=RenderSettings(render_scale=0.5),
                           output=OutputSettings(resolution=(64, 64), composite=False),
                           backend=BackendSettings("onnxruntime", threads=1))
    assert [str(w.message).split(" is ")[0] for w in caught] == [
        "TalkingHead(render=...)", "TalkingHead(output=...)", "TalkingHead(backend=...)"]
    assert "use render_settings=" in str(caught[0].message)
    with head:
        assert head.render_settings.render_scale == 0.5 and head.frame_size == (64, 64)
        assert head.backend_settings.threads == 1
    with pytest.raises(SettingsError, match="render= and render_settings= are one setting given twice"):
        TalkingHead(small_export.path, render=RenderSettings(), render_settings=RenderSettings())
    with pytest.raises(SettingsError, match="backend='mnn' and backend_settings.name='onnxruntime'"):
        TalkingHead(small_export.path, backend="mnn", backend_settings=BackendSettings("onnxruntime"))


def test_an_unknown_name_is_still_an_attribute_error(small_export):
    with TalkingHead(small_export.path, resolution=(64, 64), composite=False) as head:
        with pytest.raises(AttributeError, match="'TalkingHead' object has no attribute 'no_such_thing'"):
            head.no_such_thing  # noqa: B018
        assert not hasattr(head, "no_such_thing")


def test_package_code_uses_no_renamed_name():
    """The runtime's own code uses the stages, never a renamed name of TalkingHead (those warn): no `head.<old>` or
    `self.head.<old>` anywhere in it."""
    from test_layers import installed_roots

    def is_head(node: ast.AST) -> bool:
        return (isinstance(node, ast.Name) and node.id == "head") or (isinstance(node, ast.Attribute)
                                                                      and node.attr == "head")

    found = []
    for root in installed_roots(("runtime",)).values():
        for path in sorted(root.rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
                if isinstance(node, ast.Attribute) and is_head(node.value) and node.attr in renamed.RENAMED_ATTRIBUTES:
                    found.append(f"{path.name}:{node.lineno} head.{node.attr}")
    assert not found, found


def _intra_op_threads(head: TalkingHead) -> dict[str, int]:
    """Each onnxruntime session's intra-op thread count (0: onnxruntime's default, every core)."""
    return {name: session.get_session_options().intra_op_num_threads
            for name, session in head.frame_renderer.graphs.sessions.items()}


def test_graphs_run_on_one_thread_where_the_cpu_splatter_draws(small_export):
    """Where the CPU splatter draws, each graph gets one thread, pipelined or not (docs/speed.md, "Whole frames at
    once"; onnxruntime's results depend on its thread count); with GL or with threads asked for, the settings'
    own count."""
    pytest.importorskip("numba")
    cases = [({"renderer": "cpu"}, 1), ({"renderer": "cpu", "pipeline": True}, 1),
             ({"renderer": "cpu", "pipeline": False}, 1), ({"renderer": "cpu", "threads": 2}, 2),
             ({"renderer": "gl"}, 0), ({"renderer": "gl", "threads": 1}, 1)]
    for keywords, threads in cases:
        with TalkingHead(small_export.path, resolution=(32, 32), **keywords) as head:
            assert set(_intra_op_threads(head).values()) == {threads}, keywords
            assert head.backend_settings.threads == keywords.get("threads"), keywords  # the settings as given


def test_a_bundle_that_fails_to_load_releases_the_gl_it_chose(small_export, monkeypatch):
    """The renderer is chosen before the graphs load; a GL splatter made to choose it is released when the bundle
    then fails."""
    from gaussiantalker.runtime import stages
    from gaussiantalker.sdk.errors import BundleError

    released = []
    monkeypatch.setattr(GLSplatter, "release", lambda self: released.append(self))

    def broken(*args, **kwargs):
        raise BundleError("damaged graph")

    monkeypatch.setattr(stages, "open_backend", broken)
    with pytest.raises(BundleError, match="damaged graph"):
        TalkingHead(small_export.path, resolution=(32, 32), renderer="gl")
    assert len(released) == 1 and isinstance(released[0], GLSplatter)
