"""`renderer="auto"` (runtime/splat/choice.py, docs/embedding.md "Renderer"), every branch of the choice on stubbed
GL: GL that cannot start (the real context code, its backends failing as without libEGL) with and without numba,
GL_RENDERER strings of software rasterizers (llvmpipe, softpipe, SwiftShader, Apple's, Microsoft's WARP) and of
hardware, and what "gl" and "cpu" do meanwhile. Then a TalkingHead on a machine whose GL cannot start draws with
the CPU splatter (needs numba, the cpu extra: skipped without it, failed where CI is set)."""

from __future__ import annotations

import logging
from types import SimpleNamespace

import numpy as np
import pytest
from ci_tools import need_module

from gaussiantalker.runtime.splat import choice, gl_context
from gaussiantalker.sdk.errors import RenderError, SettingsError
from gaussiantalker.sdk.render_settings import RenderSettings

SOFTWARE = {
    "llvmpipe": "llvmpipe (LLVM 15.0.6, 256 bits)",
    "softpipe": "softpipe",
    "swiftshader": "Google SwiftShader",
    "apple": "Apple Software Renderer",
    "warp": "D3D12 (Microsoft Basic Render Driver)",
}
HARDWARE = {
    "nvidia": "NVIDIA GeForce RTX 4090/PCIe/SSE2",
    "radeonsi": "AMD Radeon RX 7900 XTX (radeonsi, navi31, LLVM 15.0.7, DRM 3.54, 6.5.0)",  # LLVM, not llvmpipe
    "intel": "Mesa Intel(R) UHD Graphics 620 (KBL GT2)",
    "apple-gpu": "Apple M2",
    "wsl-gpu": "D3D12 (NVIDIA GeForce RTX 3080)",  # WSL's Mesa on a real GPU
}
NO_EGL = "libEGL.so.1: cannot open shared object file: No such file or directory"


class StubGL:
    """Stands for GLSplatter: a context whose GL_RENDERER is `name`; records what was made and released."""

    made: list[StubGL] = []
    name = ""

    def __init__(self, ctx=None, *, settings=None, shader_target="330") -> None:
        self.ctx = SimpleNamespace(info={"GL_RENDERER": self.name})
        self.settings, self.shader_target, self.released = settings, shader_target, False
        StubGL.made.append(self)

    def release(self) -> None:
        self.released = True


@pytest.fixture(autouse=True)
def fresh_log(monkeypatch):
    """Each test sees every choice logged (the log is once per process and reason)."""
    monkeypatch.setattr(choice, "_reported", set())
    monkeypatch.setattr(StubGL, "made", [])


@pytest.fixture
def cpu(monkeypatch):
    """numba present (or not: `cpu(False)`), the CPU splatter a stub; returns the list of stubs made."""
    made = []

    def setup(present: bool = True) -> list:
        monkeypatch.setattr(choice, "cpu_splatter_available", lambda: present)
        monkeypatch.setattr(choice, "_cpu_splatter", lambda settings: made.append(("cpu", settings)) or made[-1])
        return made

    return setup


@pytest.fixture
def gl(monkeypatch):
    """GL that starts with GL_RENDERER `name`; returns StubGL.made."""

    def setup(name: str) -> list:
        monkeypatch.setattr(choice, "GLSplatter", type("NamedStubGL", (StubGL,), {"name": name}))
        return StubGL.made

    return setup


@pytest.fixture
def no_gl(monkeypatch):
    """GL that cannot start: every context backend fails, as dlopen does without libEGL (the real context code
    and the real GLSplatter run up to that failure)."""
    tried = []

    def fail(backend):
        tried.append(backend)
        raise OSError(NO_EGL)

    monkeypatch.setattr(gl_context, "_try_backend", fail)
    return tried


def test_gl_that_cannot_start_falls_back_to_the_cpu_with_numba(no_gl, cpu, caplog):
    made = cpu(True)
    settings = RenderSettings(sort_interval=2)
    with caplog.at_level(logging.INFO, logger="gaussiantalker.runtime"):
        splatter, name = choice.make_splatter("auto", settings=settings)
    assert name == "cpu" and splatter == ("cpu", settings) and made == [splatter]
    assert no_gl == gl_context.default_backends()  # the real context code tried every backend
    (record,) = caplog.records
    assert record.levelno == logging.INFO
    assert "drawing with the cpu splatter" in record.getMessage() and NO_EGL in record.getMessage()


def test_gl_that_cannot_start_without_numba_is_one_error_naming_both(no_gl, cpu):
    made = cpu(False)
    with pytest.raises(RenderError) as caught:
        choice.make_splatter("auto")
    message = str(caught.value)
    assert not isinstance(caught.value, SettingsError)
    assert "OpenGL cannot run here" in message and NO_EGL in message  # the GL problem, with its install hint
    assert gl_context._INSTALL_HINTS[gl_context._platform_key()] in message
    assert "numba, which is not installed" in message and choice.CPU_EXTRA_HINT in message
    assert made == []


@pytest.mark.parametrize("kind", SOFTWARE)
def test_software_gl_is_replaced_by_the_cpu_splatter_with_numba(gl, cpu, caplog, kind):
    made_gl, made_cpu = gl(SOFTWARE[kind]), cpu(True)
    assert choice.is_software_renderer(SOFTWARE[kind])
    with caplog.at_level(logging.INFO, logger="gaussiantalker.runtime"):
        splatter, name = choice.make_splatter("auto", shader_target="410")
    assert name == "cpu" and made_cpu == [splatter]
    (stub,) = made_gl
    assert stub.released and stub.shader_target == "410"  # GL was started as asked, then let go
    assert f"{SOFTWARE[kind]!r} is a software rasterizer" in caplog.text and "the cpu splatter" in caplog.text


@pytest.mark.parametrize("kind", SOFTWARE)
def test_software_gl_stays_without_numba_and_says_so(gl, cpu, caplog, kind):
    made_gl, made_cpu = gl(SOFTWARE[kind]), cpu(False)
    with caplog.at_level(logging.INFO, logger="gaussiantalker.runtime"):
        splatter, name = choice.make_splatter("auto")
    assert name == "gl" and made_gl == [splatter] and not splatter.released and made_cpu == []
    assert "the gl splatter" in caplog.text and choice.CPU_EXTRA_HINT in caplog.text


@pytest.mark.parametrize("kind", HARDWARE)
def test_hardware_gl_draws(gl, cpu, caplog, kind):
    made_gl, made_cpu = gl(HARDWARE[kind]), cpu(True)
    assert not choice.is_software_renderer(HARDWARE[kind])
    with caplog.at_level(logging.INFO, logger="gaussiantalker.runtime"):
        splatter, name = choice.make_splatter("auto")
    assert name == "gl" and made_gl == [splatter] and not splatter.released and made_cpu == []
    assert f"{HARDWARE[kind]!r} is not a software rasterizer" in caplog.text


def test_a_bad_setting_is_not_taken_for_missing_gl(monkeypatch, cpu):
    """A SettingsError is a RenderError, but says the call is wrong: auto raises it instead of drawing on the CPU."""
    made = cpu(True)
    with pytest.raises(SettingsError, match="RenderSettings, got str"):
        choice.make_splatter("auto", settings="float32")

    def refuse(*args, **kwargs):
        raise SettingsError("settings must be a RenderSettings")

    monkeypatch.setattr(choice, "GLSplatter", refuse)
    with pytest.raises(SettingsError, match="RenderSettings"):
        choice.make_splatter("auto")
    assert made == []


def test_gl_and_cpu_are_what_was_asked_for(no_gl, gl, cpu, caplog):
    """"gl" never falls back (GL that cannot start is its RenderError), "gl" on software GL stays GL, "cpu" never
    starts GL, and "cpu" without numba names the extra."""
    made_cpu = cpu(True)
    with pytest.raises(RenderError, match="could not create an OpenGL 3.3 core context") as caught:
        choice.make_splatter("gl")
    assert NO_EGL in str(caught.value) and made_cpu == []
    made_gl = gl(SOFTWARE["llvmpipe"])
    with caplog.at_level(logging.INFO, logger="gaussiantalker.runtime"):
        assert choice.make_splatter("gl")[1] == "gl" and choice.make_splatter("cpu")[1] == "cpu"
    assert len(made_gl) == 1 and len(made_cpu) == 1  # "cpu" made no GL splatter
    assert caplog.text.count("asked for") == 2
    cpu(False)
    with pytest.raises(SettingsError, match=r"gaussiantalker-sdk\[cpu\]"):
        choice.make_splatter("cpu")


def test_a_head_without_gl_draws_on_the_cpu(no_gl, small_export):
    """TalkingHead(renderer="auto") where GL cannot start: the CPU splatter draws, the frames renderer="cpu"
    draws."""
    need_module("numba", "cpu")
    from gaussiantalker.runtime import TalkingHead

    with TalkingHead(small_export.path, resolution=(48, 48), renderer="auto") as head:
        assert head.renderer == "cpu"
        frame = head.render_params(jaw_pose=[0.2, 0.0, 0.0])
    with pytest.raises(RenderError, match="could not create an OpenGL"):
        TalkingHead(small_export.path, resolution=(48, 48), renderer="gl")
    with TalkingHead(small_export.path, resolution=(48, 48), renderer="cpu") as head:
        np.testing.assert_array_equal(frame, head.render_params(jaw_pose=[0.2, 0.0, 0.0]))
    assert frame.std() > 0  # the head is drawn
