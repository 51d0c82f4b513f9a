"""A live session whose frames raise (runtime/live.py, docs/live.md "Bad input and misuse"): the error reaches the
reader once, the session stops, and a producer on another thread gets a LiveError naming it instead of queueing
audio that no frame will show. Free-running, 32² frames: each case takes well under a second."""

from __future__ import annotations

import itertools
import threading

import numpy as np
import pytest

from gaussiantalker.runtime import LiveError, TalkingHead
from gaussiantalker.sdk.audio import load_audio


@pytest.fixture(scope="module")
def head(small_export):
    with TalkingHead(small_export.path, resolution=(32, 32), composite=False) as talking_head:
        yield talking_head


def _fail_render(monkeypatch, head, after: int) -> RuntimeError:
    """Make `head.render` raise from its (after + 1)-th call on; returns the error it raises."""
    error = RuntimeError(f"injected render failure after {after} frames")
    original, calls = head.render, itertools.count()

    def render(*args, **kwargs):
        if next(calls) >= after:
            raise error
        return original(*args, **kwargs)

    monkeypatch.setattr(head, "render", render)
    return error


@pytest.mark.parametrize("reader", ["frames", "poll"])
def test_a_render_error_stops_the_session_and_its_producers(head, monkeypatch, reader):
    speech = load_audio("samples/demo_speech.wav", head.sample_rate)[: head.sample_rate]
    error = _fail_render(monkeypatch, head, after=3)
    with head.live(paced=False) as live:
        live.push(speech, head.sample_rate)
        live.flush()
        shown = []
        with pytest.raises(RuntimeError) as raised:
            if reader == "frames":
                shown.extend(live.frames())
            else:
                shown.extend(live.poll())
        assert raised.value is error and live.error is error
        assert len(shown) == (3 if reader == "frames" else 0)  # poll() raises instead of returning what it made
        # A producer on another thread is refused, with the cause, instead of queueing audio nobody shows.
        refused: list[BaseException] = []

        def produce() -> None:
            try:
                live.push(np.zeros(320, np.float32), head.sample_rate)
            except LiveError as exc:
                refused.append(exc)

        producer = threading.Thread(target=produce)
        producer.start()
        producer.join(10)
        assert not producer.is_alive() and len(refused) == 1, refused
        assert "injected render failure" in str(refused[0]) and refused[0].__cause__ is error
        assert list(live.frames()) == [] and live.poll() == []  # stopped: nothing more is made
        assert live.stats.frames == 3


def test_a_clean_end_leaves_no_error(head):
    with head.live(paced=False, output=None) as live:
        live.push(np.zeros(head.sample_rate // 5, np.float32), head.sample_rate)
        live.end()
        assert list(live.frames()) and live.error is None
