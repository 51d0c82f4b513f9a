"""The Pipecat adapter (runtime/pipecat_video.py, docs/live.md "Pipecat") in Pipecat's own test pipeline runner,
offline: text-to-speech audio frames in, the head's audio and image frames out in order and in sync. Skips when
the pipecat extra is not installed (`pip install ".[pipecat]"`), except in CI, whose set-up installs it.

Push back: a reply sent at once, 8 s against a session that refuses more than 2 s queued, with max_ahead_s=1, goes
out whole and in order with no ErrorFrame, at most 1 s queued after any push; an interruption or a cancel while a
chunk waits ends the run within 2.5 s of frames; a chunk over the session's bound is one ErrorFrame a reply and
passes on unchanged. Every run that can hang is bounded at RUN_TIMEOUT_S (60 s; they take 1-10 s)."""

from __future__ import annotations

import asyncio
import itertools
import threading
import time

import numpy as np
import pytest
from ci_tools import need_module

from gaussiantalker.sdk.audio import load_audio, resample

need_module("pipecat", "pipecat", module_level=True)  # skips the module; fails it where CI is set

from pipecat.frames.frames import (  # noqa: E402
    CancelFrame,
    ErrorFrame,
    InterruptionFrame,
    OutputAudioRawFrame,
    OutputImageRawFrame,
    TTSAudioRawFrame,
    TTSStartedFrame,
    TTSStoppedFrame,
)
from pipecat.tests.utils import SleepFrame, run_test  # noqa: E402

from gaussiantalker.runtime import IdleMotion, TalkingHead  # noqa: E402
from gaussiantalker.runtime.idle import IdleTrack  # noqa: E402
from gaussiantalker.runtime.pipecat_video import TalkingHeadVideo  # noqa: E402
from gaussiantalker.sdk.errors import LiveError  # noqa: E402

SIZE = 48
TTS_RATE = 24000


def _tts_frames(seconds: float) -> tuple[list, np.ndarray]:
    """The sample speech as a TTS service sends it: 20 ms int16 chunks at 24 kHz between started/stopped."""
    speech = resample(load_audio("samples/demo_speech.wav", 16000)[: int(seconds * 16000)], 16000, TTS_RATE)
    pcm = np.round(np.clip(speech, -1, 1) * 32767).astype(np.int16)
    step = TTS_RATE // 50
    chunks = [TTSAudioRawFrame(audio=pcm[i:i + step].tobytes(), sample_rate=TTS_RATE, num_channels=1)
              for i in range(0, pcm.shape[0], step)]
    return [TTSStartedFrame(), *chunks, TTSStoppedFrame()], pcm


def _outputs(frames) -> tuple[list, list]:
    audio = [f for f in frames if isinstance(f, OutputAudioRawFrame) and not isinstance(f, TTSAudioRawFrame)]
    images = [f for f in frames if isinstance(f, OutputImageRawFrame)]
    return audio, images


def test_tts_audio_becomes_frames_with_the_same_audio_in_sync(small_export):
    sent, pcm = _tts_frames(2.0)
    processor = TalkingHeadVideo(small_export.path, resolution=(SIZE, SIZE), lookahead_ms=80)
    down, _ = asyncio.run(run_test(processor, frames_to_send=[SleepFrame(0.3), *sent, SleepFrame(0.5)],
                                   start_timeout=60.0))
    assert not [f for f in down if isinstance(f, TTSAudioRawFrame)]  # consumed: their samples go on with frames
    audio, images = _outputs(down)
    media = [f for f in down if isinstance(f, (OutputAudioRawFrame, OutputImageRawFrame))]
    # Each frame's audio, then its picture queued with it: strictly alternating, one of each per video frame.
    assert [type(f) for f in media] == [OutputAudioRawFrame, OutputImageRawFrame] * len(images)
    assert all(f.size == (SIZE, SIZE) and f.format == "RGB" and f.sync_with_audio for f in images)
    assert all(f.sample_rate == TTS_RATE and f.num_channels == 1 for f in audio)
    assert {len(f.audio) for f in audio} == {2 * TTS_RATE // 25}  # 40 ms of int16 per 25 fps frame
    played = np.concatenate([np.frombuffer(f.audio, np.int16) for f in audio])
    start = int(np.flatnonzero(played)[0])  # the idle frames before the reply carry silence
    assert start % (TTS_RATE // 25) == 0  # the reply starts on a frame boundary
    np.testing.assert_array_equal(played[start:start + pcm.shape[0]], pcm)  # the voice passes unchanged
    first = start // (TTS_RATE // 25)
    pictures = [np.frombuffer(f.image, np.uint8) for f in images]
    idle_change = max(np.abs(p.astype(int) - pictures[0]).max() for p in pictures[1:first]) if first > 1 else 0
    speech_change = max(np.abs(p.astype(int) - pictures[first]).max() for p in pictures[first:first + 50])
    assert speech_change > idle_change + 20, (idle_change, speech_change)  # the mouth moves with the reply


def test_a_lam_bundle_speaks_through_the_builtin_voice(lam_voice_bundle):
    """An imported LAM avatar with the built-in voice driver (30 fps) in the adapter: TTS audio in, one 1/30 s
    audio frame per picture out, the voice unchanged, and the mouth moving with the reply."""
    sent, pcm = _tts_frames(2.0)
    processor = TalkingHeadVideo(lam_voice_bundle, resolution=(SIZE, SIZE), lookahead_ms=160)
    down, _ = asyncio.run(run_test(processor, frames_to_send=[SleepFrame(0.3), *sent, SleepFrame(0.5)],
                                   start_timeout=60.0))
    audio, images = _outputs(down)
    assert len(audio) == len(images) > 60
    assert {len(f.audio) for f in audio} == {2 * TTS_RATE // 30}  # 1/30 s of int16 per frame
    played = np.concatenate([np.frombuffer(f.audio, np.int16) for f in audio])
    start = int(np.flatnonzero(played)[0])
    np.testing.assert_array_equal(played[start:start + pcm.shape[0]], pcm)
    first = start // (TTS_RATE // 30)
    pictures = [np.frombuffer(f.image, np.uint8).astype(int) for f in images]
    speech_change = max(np.abs(p - pictures[first]).max() for p in pictures[first:first + 60])
    assert speech_change > 20, speech_change


def test_interruption_cuts_the_reply_and_eases_to_idle(small_export):
    """A barge-in drops the rest of the reply; the pictures ease from the last spoken face to the idle one over
    IdleMotion.ease_ms (strictly closer to it each frame), then are exactly the idle face a session draws for
    those frames (blinks off, so idle is the neutral face on the speaker's pose track)."""
    sent, pcm = _tts_frames(3.0)
    idle = IdleMotion(blink_ms=0)
    processor = TalkingHeadVideo(small_export.path, resolution=(SIZE, SIZE), lookahead_ms=80, idle=idle)
    frames = [*sent[:-1], SleepFrame(1.0), InterruptionFrame(), SleepFrame(0.5)]
    down, _ = asyncio.run(run_test(processor, frames_to_send=frames, start_timeout=60.0))
    audio, images = _outputs(down)
    assert len(audio) == len(images)
    played = np.concatenate([np.frombuffer(f.audio, np.int16) for f in audio])
    spoken = np.count_nonzero(np.abs(played) > 0)
    assert 0 < spoken < np.count_nonzero(pcm)  # part of the reply was shown, the rest dropped
    assert not played[-(TTS_RATE // 5):].any()  # after the barge-in only silence goes out
    # The last frame carrying voice is the last spoken one (no 40 ms of the sample speech is digital silence).
    last = max(index for index, f in enumerate(audio) if np.frombuffer(f.audio, np.int16).any())
    with TalkingHead(small_export.path, resolution=(SIZE, SIZE), composite=False) as head, \
            head.live(paced=False, idle=idle) as reference:  # no audio: idle frames, frame by frame
        neutral = [f.image for f in itertools.islice(reference.frames(), len(images))]
        fps = head.fps
    ease = IdleTrack(idle, fps).ease_frames
    assert ease == 3 and len(images) >= last + ease + 2, (last, len(images))  # 120 ms at 25 fps
    assert [f.pts for f in images] == [round(index / fps * 1e9) for index in range(len(images))]
    pictures = [np.frombuffer(f.image, np.uint8).reshape(SIZE, SIZE, 3) for f in images]
    distance = [float(np.abs(pictures[i].astype(int) - neutral[i]).mean()) for i in range(last, len(images))]
    # distance[k]: k frames after the last spoken one. Closer each frame, no snap, idle from the ease's end on.
    assert all(distance[k] > distance[k + 1] > 0 for k in range(ease - 1)), distance
    for index in range(last + ease, len(images)):
        np.testing.assert_array_equal(pictures[index], neutral[index], err_msg=f"frame {index} is not idle")


# -- a session that fails (docs/live.md, "Pipecat") ---------------------------------------------------------------
RENDER_THREAD = "gt-pipecat-render"
RUN_TIMEOUT_S = 60.0  # a whole pipeline run at most: the runs take ~2 s (the push-back runs up to ~10 s)


def _fail_render(monkeypatch, after: int) -> str:
    """Make TalkingHead.render raise from its (after + 1)-th call on; returns the error's message."""
    from gaussiantalker.runtime.head import TalkingHead

    original, calls = TalkingHead.render, itertools.count()
    message = f"injected render failure after {after} frames"

    def render(self, *args, **kwargs):
        if next(calls) >= after:
            raise RuntimeError(message)
        return original(self, *args, **kwargs)

    monkeypatch.setattr(TalkingHead, "render", render)
    return message


def _run_logged(processor, frames: list) -> tuple[list, list, list[str]]:
    """run_test with its EndFrame, bounded (a hang fails the test instead of stalling the run); returns the frames
    down and up and the messages Pipecat logged at ERROR or above."""
    from loguru import logger

    errors: list[str] = []
    sink = logger.add(lambda message: errors.append(message.record["message"]), level="ERROR")
    try:
        down, up = _run_bounded(run_test(processor, frames_to_send=frames, start_timeout=60.0), RUN_TIMEOUT_S)
    finally:
        logger.remove(sink)
    return list(down), list(up), errors


def _run_bounded(coroutine, timeout: float):
    """Run `coroutine` on a fresh event loop for at most `timeout` s. Not asyncio.run(wait_for(...)): a pipeline
    whose processor hangs at its EndFrame never finishes cancelling either, and would stall the test run."""
    loop = asyncio.new_event_loop()
    task = loop.create_task(coroutine)
    done, _ = loop.run_until_complete(asyncio.wait({task}, timeout=timeout))
    if not done:
        task.cancel()  # not awaited, for the same reason
        raise AssertionError(f"the pipeline did not end within {timeout:g} s: the EndFrame hangs")
    loop.run_until_complete(loop.shutdown_default_executor())
    loop.close()
    return task.result()


def _assert_failed_once(processor, up: list, errors: list[str], message: str) -> None:
    reported = [f for f in up if isinstance(f, ErrorFrame)]
    assert len(reported) == 1 and message in reported[0].error, up  # the pipeline is told once, upstream
    assert reported[0].processor is processor and not processor.is_usable
    assert sum(message in line for line in errors) == 1, errors  # logged once (by push_error)
    assert not [t for t in threading.enumerate() if t.name == RENDER_THREAD]  # the render thread has ended


@pytest.mark.parametrize("after", [0, 10], ids=["first-frame", "after-10-frames"])
def test_a_render_error_ends_the_session_once_and_end_frame_passes(small_export, monkeypatch, after):
    """A frame that raises (the first, or the 11th mid-reply) ends the session: one ErrorFrame upstream, logged
    once, the render thread gone, the EndFrame through in bounded time; the voice then passes on unchanged."""
    message = _fail_render(monkeypatch, after)
    sent, _ = _tts_frames(1.0)
    processor = TalkingHeadVideo(small_export.path, resolution=(SIZE, SIZE), lookahead_ms=80)
    down, up, errors = _run_logged(processor, [SleepFrame(0.3), *sent, SleepFrame(1.0), *sent, SleepFrame(0.2)])
    _assert_failed_once(processor, up, errors, message)
    _, images = _outputs(down)
    assert len(images) == after  # the frames made before the failure went out, none after
    passed = [f for f in down if isinstance(f, TTSAudioRawFrame)]
    assert len(passed) >= len(sent) - 2  # the second reply (at least) reached the transport as it came


def test_a_session_that_cannot_start_reports_once_and_passes_audio_on(small_export, monkeypatch):
    """A head whose live session cannot be made (an error other than the SDK's own) is reported once at the
    StartFrame; no render thread stays, and text-to-speech audio passes on unchanged."""
    from gaussiantalker.runtime.head import TalkingHead

    message = "injected start-up failure"

    def live(self, **kwargs):
        raise RuntimeError(message)

    monkeypatch.setattr(TalkingHead, "live", live)
    sent, _ = _tts_frames(0.5)
    processor = TalkingHeadVideo(small_export.path, resolution=(SIZE, SIZE), lookahead_ms=80)
    down, up, errors = _run_logged(processor, [*sent, SleepFrame(0.2)])
    _assert_failed_once(processor, up, errors, message)
    assert [f for f in down if isinstance(f, TTSAudioRawFrame)] == [f for f in sent if isinstance(f, TTSAudioRawFrame)]
    assert not _outputs(down)[1]


# -- push back (docs/live.md, "Pipecat") ----------------------------------------------------------------------------
SESSION_MAX_QUEUED_S = 2.0  # the sessions' own bound in these tests: a push beyond it is refused
MAX_AHEAD_S = 1.0
FRAME_SAMPLES = TTS_RATE // 25  # one 25 fps frame of the small speaker at 24 kHz


def _small_sessions(monkeypatch) -> list[float]:
    """Open the adapter's sessions with max_queued_s=SESSION_MAX_QUEUED_S, so that a longer reply sent at once
    would be refused without push back; returns the seconds queued after each accepted push, as they happen."""
    from gaussiantalker.runtime.live import LiveSession

    original_live, original_push, queued = TalkingHead.live, LiveSession.push, []

    def live(self, **kwargs):
        return original_live(self, **{**kwargs, "max_queued_s": SESSION_MAX_QUEUED_S})

    def push(self, samples, sample_rate):
        original_push(self, samples, sample_rate)
        queued.append(self.queued_s)

    monkeypatch.setattr(TalkingHead, "live", live)
    monkeypatch.setattr(LiveSession, "push", push)
    return queued


def _voiced(audio: list) -> np.ndarray:
    """The samples of the audio frames that carry voice (idle frames are silent; no 40 ms of the speech is)."""
    chunks = [np.frombuffer(f.audio, np.int16) for f in audio]
    return np.concatenate([c for c in chunks if c.any()] or [np.zeros(0, np.int16)])


def test_a_reply_faster_than_real_time_is_held_back_not_refused(small_export, monkeypatch):
    """8 s of speech sent at once as 20 ms chunks, four times what the session would take: each chunk waits for
    room, so no ErrorFrame, at most max_ahead_s (+ 20 ms) queued after any push, every sample out once and in order, and
    the reply's TTSStoppedFrame goes on only once most of the reply has been shown (the reply was held back)."""
    queued = _small_sessions(monkeypatch)
    sent, pcm = _tts_frames(8.0)
    processor = TalkingHeadVideo(small_export.path, resolution=(SIZE, SIZE), lookahead_ms=80,
                                 max_ahead_s=MAX_AHEAD_S)
    down, up, errors = _run_logged(processor, [SleepFrame(0.3), *sent, SleepFrame(0.5)])
    assert not [f for f in up if isinstance(f, ErrorFrame)] and not errors, (up, errors)
    assert processor.is_usable
    # At most the bound, plus what the resampler had held back and releases with a push (its filter delay, a few
    # ms: docs/live.md, "The timeline and the audio clock"), under one 20 ms chunk.
    assert len(queued) == len(sent) - 2 and max(queued) <= MAX_AHEAD_S + 0.02, max(queued)
    assert not [f for f in down if isinstance(f, TTSAudioRawFrame)]  # every chunk went into the face
    audio, images = _outputs(down)
    assert len(audio) == len(images)
    played = np.concatenate([np.frombuffer(f.audio, np.int16) for f in audio])
    start = int(np.flatnonzero(played)[0])
    assert start % FRAME_SAMPLES == 0
    np.testing.assert_array_equal(played[start:start + pcm.shape[0]], pcm)  # whole, in order, no gap
    assert not played[start + pcm.shape[0]:].any()  # and nothing twice
    stopped = next(i for i, f in enumerate(down) if isinstance(f, TTSStoppedFrame))
    shown = sum(np.frombuffer(f.audio, np.int16).any() for f in down[:stopped] if f in audio)
    assert shown >= (8.0 - MAX_AHEAD_S - 0.5) * 25, shown  # 25 fps; 0.5 s for the lookahead and resampler


@pytest.mark.parametrize("stop", [InterruptionFrame, CancelFrame], ids=["interruption", "cancel"])
def test_an_interruption_or_cancel_ends_the_wait_for_room(small_export, monkeypatch, stop):
    """A chunk waiting for room when the user barges in (or the pipeline is cancelled) stops waiting: the rest of
    the reply is dropped, no ErrorFrame, the run ends (bounded) after about 1.5 s of frames, not the reply's 8 s."""
    queued = _small_sessions(monkeypatch)
    sent, pcm = _tts_frames(8.0)
    processor = TalkingHeadVideo(small_export.path, resolution=(SIZE, SIZE), lookahead_ms=80,
                                 max_ahead_s=MAX_AHEAD_S)
    frames = [SleepFrame(0.3), *sent[:-1], SleepFrame(1.0), stop()]
    if stop is InterruptionFrame:
        frames.append(SleepFrame(0.5))  # then run_test's EndFrame, which lets the session's last frames out
    from loguru import logger

    errors: list[str] = []
    sink = logger.add(lambda message: errors.append(message.record["message"]), level="ERROR")
    try:
        down, up = _run_bounded(run_test(processor, frames_to_send=frames, start_timeout=60.0,
                                         send_end_frame=stop is InterruptionFrame), RUN_TIMEOUT_S)
    finally:
        logger.remove(sink)
    assert not [f for f in up if isinstance(f, ErrorFrame)] and not errors, (up, errors)
    assert 0 < len(queued) < len(sent) - 2  # chunks were waiting for room when it came, and were dropped
    audio, images = _outputs(down)
    assert len(images) < 2.5 * 25, len(images)  # the run ended instead of showing the 8 s reply
    played = np.concatenate([np.frombuffer(f.audio, np.int16) for f in audio])
    assert 0 < np.count_nonzero(played) < np.count_nonzero(pcm) // 4
    if stop is InterruptionFrame:
        assert not played[-(TTS_RATE // 5):].any()  # after the barge-in only silence goes out
    assert not [t for t in threading.enumerate() if t.name == RENDER_THREAD]


@pytest.mark.parametrize("render_s", [0.0, 0.025], ids=["render-as-is", "render-slow"])
def test_a_chunk_longer_than_the_session_takes_is_one_error_a_reply_and_passes_on(small_export, monkeypatch,
                                                                                   render_s):
    """Chunks longer alone than the session's max_queued_s, twice in one reply and once in the next: one ErrorFrame
    a reply, logged once each, the processor still usable; those chunks pass on unchanged, in place (the face's
    queue drained first), and the reply's other chunks are shown by the face, whole and in order. A slow render
    (25 ms of the 40 ms a frame) widens the time between a frame taking the last queued audio and its going out,
    which a chunk passed on must not overtake."""
    _small_sessions(monkeypatch)
    if render_s:
        original_render = TalkingHead.render

        def slow_render(self, *args, **kwargs):
            time.sleep(render_s)
            return original_render(self, *args, **kwargs)

        monkeypatch.setattr(TalkingHead, "render", slow_render)
    _, pcm = _tts_frames(0.8)
    step = TTS_RATE // 50

    def chunks(samples: np.ndarray) -> list:
        return [TTSAudioRawFrame(audio=samples[i:i + step].tobytes(), sample_rate=TTS_RATE, num_channels=1)
                for i in range(0, samples.shape[0], step)]

    tone = np.round(8000 * np.sin(np.arange(3 * TTS_RATE) * 2 * np.pi * 440 / TTS_RATE)).astype(np.int16)
    longs = [TTSAudioRawFrame(audio=tone.tobytes(), sample_rate=TTS_RATE, num_channels=1) for _ in range(3)]
    half = pcm.shape[0] // 2  # 0.4 s: whole frames
    first = [TTSStartedFrame(), *chunks(pcm[:half]), longs[0], longs[1], *chunks(pcm[half:]), TTSStoppedFrame()]
    second = [TTSStartedFrame(), longs[2], TTSStoppedFrame()]
    processor = TalkingHeadVideo(small_export.path, resolution=(SIZE, SIZE), lookahead_ms=80,
                                 max_ahead_s=MAX_AHEAD_S)
    down, up, errors = _run_logged(processor, [SleepFrame(0.3), *first, SleepFrame(1.0), *second, SleepFrame(0.3)])
    reported = [f for f in up if isinstance(f, ErrorFrame)]
    assert len(reported) == 2 and all("max_queued_s=2" in f.error for f in reported), up
    assert all(f.processor is processor for f in reported) and processor.is_usable
    assert sum("max_queued_s=2" in line for line in errors) == 2, errors
    passed = [f for f in down if isinstance(f, TTSAudioRawFrame)]
    assert len(passed) == 3 and all(a is b for a, b in zip(passed, longs, strict=True))
    audio, images = _outputs(down)
    assert len(audio) == len(images)
    voiced = _voiced(audio)
    np.testing.assert_array_equal(voiced[:pcm.shape[0]], pcm)  # the other chunks, whole and in order
    assert not voiced[pcm.shape[0]:].any()
    # The first long chunk went on once the face had shown all the audio before it: in order at the transport.
    at = next(i for i, f in enumerate(down) if f is longs[0])
    assert _voiced([f for f in down[:at] if f in audio]).shape[0] == half


@pytest.mark.parametrize("bad", [0, -1.0, float("nan"), float("inf"), 121.0, "30"])
def test_max_ahead_s_is_checked(small_export, bad):
    """max_ahead_s must be a number in (0, 120]: the session refuses more than 120 s queued anyway."""
    with pytest.raises(LiveError, match="max_ahead_s"):
        TalkingHeadVideo(small_export.path, max_ahead_s=bad)
