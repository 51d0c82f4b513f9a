"""The Pipecat adapter (runtime/pipecat_video.py, docs/live.md "Pipecat") in Pipecat's own test pipeline runner,
offline: text-to-speech audio frames in, the head's audio and image frames out in order and in sync. Skips when
the pipecat extra is not installed (`pip install ".[pipecat]"`), except in CI, whose set-up installs it."""

from __future__ import annotations

import asyncio
import importlib.util
import os

import numpy as np
import pytest

from gaussiantalker.sdk.audio import load_audio, resample

if importlib.util.find_spec("pipecat") is None:
    if os.environ.get("CI"):
        raise RuntimeError("CI must install the pipecat extra (.ci/install) so that the Pipecat adapter is tested")
    pytest.skip("the pipecat extra is not installed: pip install '.[pipecat]'", allow_module_level=True)

from pipecat.frames.frames import (  # noqa: E402
    InterruptionFrame,
    OutputAudioRawFrame,
    OutputImageRawFrame,
    TTSAudioRawFrame,
    TTSStartedFrame,
    TTSStoppedFrame,
)
from pipecat.tests.utils import SleepFrame, run_test  # noqa: E402

from gaussiantalker.runtime.pipecat_video import TalkingHeadVideo  # noqa: E402

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


def test_interruption_cuts_the_reply_and_eases_to_idle(small_export):
    sent, pcm = _tts_frames(3.0)
    processor = TalkingHeadVideo(small_export.path, resolution=(SIZE, SIZE), lookahead_ms=80)
    frames = [*sent[:-1], SleepFrame(1.0), InterruptionFrame(), SleepFrame(0.5)]
    down, _ = asyncio.run(run_test(processor, frames_to_send=frames, start_timeout=60.0))
    audio, images = _outputs(down)
    assert len(audio) == len(images)
    played = np.concatenate([np.frombuffer(f.audio, np.int16) for f in audio])
    spoken = np.count_nonzero(np.abs(played) > 0)
    assert 0 < spoken < np.count_nonzero(pcm)  # part of the reply was shown, the rest dropped
    assert not played[-(TTS_RATE // 5):].any()  # after the barge-in only silence goes out
