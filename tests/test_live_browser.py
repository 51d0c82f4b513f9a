"""The pixel mode of `gt-serve` in a real browser (docs/serve.md, docs/live.md "WebRTC sample"): Debian's chromium,
headless, with a fake microphone fed from a wav file, connects over WebRTC; the page must receive video at the
session's size and rate and an audio track carrying sound, and the server's session must move the mouth with the
speech it hears. Skips without chromium or the serve extra, except where CI is set: there .ci/browser and
.ci/install install them, and the tests fail (tests/ci_tools.py)."""

from __future__ import annotations

import json
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest
from ci_tools import need_chromium, need_module
from serve_clients import free_port

from tools.bench.live_clients import serving
from tools.browser.chromium import Chromium

ROOT = Path(__file__).resolve().parents[1]
SIZE = 64
# Chromium's fake capture devices and WebRTC on localhost: the microphone plays the wav (looped), the page may
# autoplay, and host candidates carry the real 127.0.0.1 address (not an mDNS name aiortc cannot resolve).
MEDIA_FLAGS = ("--use-fake-ui-for-media-stream", "--use-fake-device-for-media-stream",
               f"--use-file-for-fake-audio-capture={ROOT / 'samples' / 'demo_speech.wav'}",
               "--autoplay-policy=no-user-gesture-required", "--disable-features=WebRtcHideLocalIpsWithMdns")


def _requirements() -> None:
    """Skip without chromium or the serve extra; where CI is set, fail (tests/ci_tools.py)."""
    need_chromium()
    need_module("aiortc", "serve")


@pytest.fixture(scope="session")
def browser_tools() -> None:
    """_requirements as a fixture: named before small_export, it skips (or fails) before the speaker is made."""
    _requirements()


def _server(bundle: Path, port: int, python: tuple[str, ...] = ("-m", "gaussiantalker.cli.serve")) \
        -> subprocess.Popen:
    """gt-serve serving `bundle` on `port` in pixel mode, once it answers (on loopback without tokens, --debug for
    the counters); `python`: what runs the command (a `-c` program that runs it, as the failure tests do)."""
    return serving([sys.executable, *python, str(bundle), "--port", str(port), "--size", str(SIZE), "--debug",
                    "--drain-s", "1"], f"http://127.0.0.1:{port}/readyz", 60, name="gt-serve")


def _get(port: int, path: str):
    return json.loads(urllib.request.urlopen(f"http://127.0.0.1:{port}{path}", timeout=10).read())


def _wait_frames(browser: Chromium, count: int, timeout: float = 90.0) -> dict:
    """The page's liveStats once it has shown `count` frames (or failed, or timed out)."""
    deadline, stats = time.monotonic() + timeout, {}
    while time.monotonic() < deadline:
        stats = browser.evaluate("window.liveStats") or {}
        if stats.get("error") or stats.get("frames", 0) >= count:
            break
        time.sleep(0.3)
    return stats


def _seconds_until_closed(port: int, timeout: float) -> float:
    """Seconds until the server has no session and no render thread left (AssertionError after `timeout`)."""
    start = time.monotonic()
    while time.monotonic() - start < timeout:
        if _get(port, "/health") == {"sessions": 0, "render_threads": 0}:
            return time.monotonic() - start
        time.sleep(0.2)
    raise AssertionError(f"the session outlived its browser by {timeout} s: {_get(port, '/health')}")


def test_browser_receives_the_head_talking_with_its_microphone(browser_tools, small_export):
    port = free_port()
    server = _server(small_export.path, port)
    try:
        with Chromium(extra_flags=MEDIA_FLAGS) as browser:
            browser.navigate(f"http://127.0.0.1:{port}/?source=mic&autostart=1")
            stats = _wait_frames(browser, 100)
            session = _get(port, "/stats")
    finally:
        server.terminate()
        server.wait(timeout=30)
    print("page:", stats, "server:", session)
    assert not stats.get("error"), stats
    assert stats["frames"] >= 100, (stats, browser.console[-20:])
    assert (stats["width"], stats["height"]) == (SIZE, SIZE)
    # The page's frame clock (requestVideoFrameCallback) over 100 frames: 25 fps sent, within what a loaded
    # 2-core machine delivers (a frame held back or decoded late moves the mean a little, not by 30%).
    rate = (stats["frames"] - 1) / ((stats["lastFrameAt"] - stats["firstFrameAt"]) / 1000.0)
    assert 17.5 <= rate <= 32.5, rate
    assert stats["audioTracks"] >= 1 and stats["audioPeak"] > 0.01, stats  # the voice comes back with the face
    (summary,) = session
    assert summary["size"] == [SIZE, SIZE] and summary["speaking_frames"] > 25, summary
    # The mouth follows what the microphone sent: jaw against the loudness of each frame's audio.
    assert summary["jaw_loudness_r"] > 0.5 and summary["jaw_range_speaking"] > 0.05, summary


def _leave_mid_reply(small_export, leave) -> float:
    """Start the 10 s sample speech in a page, let `leave(browser, port, page)` end it after 25 frames, check that
    the server logged no error, and return the seconds `leave` measured."""
    _requirements()
    port = free_port()
    server = _server(small_export.path, port)
    page = f"http://127.0.0.1:{port}/?source=file&autostart=1"
    try:
        with Chromium(extra_flags=MEDIA_FLAGS) as browser:
            browser.navigate(page)
            assert _wait_frames(browser, 25).get("frames", 0) >= 25
            assert _get(port, "/health") == {"sessions": 1, "render_threads": 1}
            seconds = leave(browser, port, page)
    finally:
        server.terminate()
        log = server.communicate(timeout=30)[0]
    for sign in ("Traceback", "Error", "never retrieved"):
        assert sign not in log, log[-3000:]
    return seconds


@pytest.mark.slow
def test_a_page_that_leaves_mid_reply_ends_its_session(browser_tools, small_export):
    """Mid-reply (the sample speech still being pushed), a page that navigates away ends its session at once (its
    beacon), the session's render thread ends, the server logs no error and serves the next page."""

    def leave(browser: Chromium, port: int, page: str) -> float:
        browser.navigate("about:blank")
        # The page's beacon ends it: well under a second here, 5 s allows for a loaded machine.
        seconds = _seconds_until_closed(port, 5.0)
        browser.navigate(page)
        stats = _wait_frames(browser, 25)
        assert stats.get("frames", 0) >= 25 and not stats.get("error"), stats
        return seconds

    seconds = _leave_mid_reply(small_export, leave)
    print(f"closed {seconds:.2f} s after the page left")


@pytest.mark.heavy
def test_a_browser_killed_mid_reply_ends_its_session(browser_tools, small_export):
    """A browser killed outright says nothing: WebRTC's consent checks notice (~30 s, aioice's fixed schedule, so
    this case is `heavy`), and the session and its render thread end as cleanly as when a page leaves."""

    def leave(browser: Chromium, port: int, page: str) -> float:
        browser.process.kill()
        browser.process.wait()
        # aioice's consent checks give up after 6 missed checks 5 s apart: ~30 s, 60 s for a loaded machine.
        return _seconds_until_closed(port, 60.0)

    seconds = _leave_mid_reply(small_export, leave)
    print(f"closed {seconds:.1f} s after the browser was killed")


# gt-serve with failures injected by session, in the order the sessions start (FAILURES): a number N makes
# rendering raise from frame N on (0: the first frame), "start" makes the head's live session fail to be made (an
# error other than the SDK's own), None leaves the session alone.
FAILURES = (25, 0, "start", None)
FAILING_SERVER = f"""
import itertools, runpy, sys
from gaussiantalker.runtime.head import TalkingHead
plans, live = iter({FAILURES!r}), TalkingHead.live
def failing_live(self, **kwargs):
    plan = next(plans, None)
    if plan == "start":
        raise RuntimeError("injected start-up failure")
    if plan is not None:
        render, calls = self.render, itertools.count()
        def failing_render(*args, **kwargs):
            if next(calls) >= plan:
                raise RuntimeError(f"injected render failure from frame {{plan}}")
            return render(*args, **kwargs)
        self.render = failing_render
    return live(self, **kwargs)
TalkingHead.live = failing_live
sys.argv = ["gt-serve", *sys.argv[1:]]
runpy.run_module("gaussiantalker.cli.serve", run_name="__main__", alter_sys=True)
"""


def _wait_failed(browser: Chromium, timeout: float = 30.0) -> dict:
    """The page's liveStats once it has failed (or timed out)."""
    deadline, stats = time.monotonic() + timeout, {}
    while time.monotonic() < deadline:
        stats = browser.evaluate("window.liveStats") or {}
        if stats.get("state") == "failed":
            break
        time.sleep(0.2)
    return stats


def test_a_session_that_fails_is_logged_once_told_to_the_page_and_closed(browser_tools, small_export):
    """Rendering that raises mid-reply (frame 25) or on the first frame, and a head whose live session cannot be
    made: each is logged once with its traceback, the page is told in one line without the error's text (the data
    channel's error, or the offer's answer) and leaves, the session and its render thread are gone within 10 s, and
    the server then serves a page that works."""
    port = free_port()
    server = _server(small_export.path, port, ("-c", FAILING_SERVER))
    page = f"http://127.0.0.1:{port}/?source=file&autostart=1"
    messages = ["injected render failure from frame 25", "injected render failure from frame 0",
                "injected start-up failure"]
    told = ["the live session ended: rendering a frame raised (RuntimeError)"] * 2 \
        + ["the live session could not start (RuntimeError)"]
    try:
        with Chromium(extra_flags=MEDIA_FLAGS) as browser:
            for message in told:
                browser.navigate(page)
                stats = _wait_failed(browser)
                assert stats.get("state") == "failed" and stats.get("error") == message, (message, stats)
                # Told, the page leaves at once (its beacon); 10 s allows for a loaded machine.
                _seconds_until_closed(port, 10.0)
            browser.navigate(page)
            stats = _wait_frames(browser, 25)
            assert stats.get("frames", 0) >= 25 and not stats.get("error"), stats
    finally:
        server.terminate()
        log = server.communicate(timeout=30)[0]
    records = [line for line in log.splitlines() if " ERROR gaussiantalker.serve: " in line]
    for message in messages:
        assert sum(message in record for record in records) == 1, (message, log[-5000:])  # each failure once
    # Tracebacks of one place are logged once a minute (serve/logs.py): frame 0's repeats frame 25's.
    assert log.count("Traceback") == 2 and log.count("its traceback as logged before") == 1, log[-5000:]
    assert "never retrieved" not in log, log[-3000:]
