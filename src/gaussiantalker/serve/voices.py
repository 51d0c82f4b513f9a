"""What a session speaks, from the page's start message: the server's sound file, text (text_speech.py), the page's
microphone, or nothing; and the pusher that feeds the server's own voice at real time."""

from __future__ import annotations

import asyncio
import math
import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gaussiantalker.runtime import LiveError
from gaussiantalker.sdk.audio import load_audio

from .limits import ServeLimits
from .sessions import read_json
from .text_speech import SpeechError, speak
from .wire import CHUNK_MS_RANGE, MIC_RATE_RANGE

DEFAULT_CHUNK_MS = 20.0  # a voice made as it is spoken: one translator call a frame


@dataclass
class Voice:
    """A start message read: `samples` at `rate` for the server to push in `chunk_s` chunks (None: the page's
    microphone at `mic_rate`, or no voice)."""

    source: str
    samples: np.ndarray | None
    rate: int
    chunk_s: float
    mic_rate: int | None = None


class VoiceFiles:
    """The server's sound file for the "file" source, read once and shared by every session."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._samples: np.ndarray | None = None

    async def samples(self) -> np.ndarray:
        if self._samples is None:
            self._samples = await asyncio.get_running_loop().run_in_executor(None, load_audio, self.path, 16000)
        return self._samples


async def voice_of(params: dict, sources: tuple[str, ...], files: VoiceFiles, limits: ServeLimits,
                   speech_gate: asyncio.Semaphore, *, mic_track: bool = False) -> Voice:
    """The voice a start message (or offer) asks for; ValueError with one line naming a bad field. `mic_track`:
    the microphone comes as a WebRTC track (its rate is the track's), not as PCM messages at mic_rate."""
    source = params.get("source", "file")
    if source not in sources:
        raise ValueError(f"source must be {', '.join(sources[:-1])} or {sources[-1]}, got {_shown(source)}")
    chunk_ms = params.get("chunk_ms", DEFAULT_CHUNK_MS)
    low, high = CHUNK_MS_RANGE
    if isinstance(chunk_ms, bool) or not (isinstance(chunk_ms, (int, float)) and low <= chunk_ms <= high):
        raise ValueError(f"chunk_ms must be a number of milliseconds in {low}..{high}, got {_shown(chunk_ms)}")
    chunk_s = chunk_ms / 1000
    if source == "file":
        return Voice(source, await files.samples(), 16000, chunk_s)
    if source == "text":
        try:
            samples, rate = await speak(params.get("text", "Hello."), max_chars=limits.max_text_chars,
                                        timeout_s=limits.speech_timeout_s, max_bytes=limits.max_speech_bytes,
                                        gate=speech_gate)
        except SpeechError as error:
            raise ValueError(str(error)) from None
        return Voice(source, samples, rate, chunk_s)
    if source == "mic" and not mic_track:
        mic_rate = params.get("mic_rate")
        low, high = MIC_RATE_RANGE
        if mic_rate is None:
            raise ValueError("source mic needs mic_rate, the sample rate of the PCM the page sends")
        if isinstance(mic_rate, bool) or not (isinstance(mic_rate, int) and low <= mic_rate <= high):
            raise ValueError(f"mic_rate must be a whole number of Hz in {low}..{high}, got {_shown(mic_rate)}")
        return Voice(source, None, 0, chunk_s, mic_rate)
    return Voice(source, None, 0, chunk_s)


async def read_offer(request, sources: tuple[str, ...], files: VoiceFiles, limits: ServeLimits,
                     speech_gate: asyncio.Semaphore, *, mic_track: bool = False) -> tuple[str, Voice]:
    """A WebRTC offer's SDP and the voice it asks for, from its JSON body; 400 (or 415, 413, 408) with one line."""
    from aiohttp import web

    params = await read_json(request)
    sdp, kind = params.get("sdp"), params.get("type")
    if not (isinstance(sdp, str) and kind == "offer"):
        raise web.HTTPBadRequest(text="an offer needs sdp (a string) and type \"offer\"")
    try:
        return sdp, await voice_of(params, sources, files, limits, speech_gate, mic_track=mic_track)
    except ValueError as error:
        raise web.HTTPBadRequest(text=str(error)) from None


def _shown(value: object) -> str:
    """A client's value as an error message quotes it: its repr, 40 characters at most."""
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


async def push_real_time(live, audio: np.ndarray, rate: int, chunk_s: float) -> None:
    """Push `audio` in `chunk_s` chunks at real time, as a voice that speaks as it is made, then flush. Stops
    quietly when the session closes (the page left); cancelling the task stops the voice (a barge-in)."""
    loop = asyncio.get_running_loop()
    pusher = _Pusher(live, audio, rate, chunk_s, loop)
    try:
        await pusher.done
    finally:
        pusher.stop()


class _Pusher:
    """Each chunk pushed by a timer callback at its time on the loop's clock: a hundred voices in 20 ms chunks are
    5,000 pushes a second, and a coroutine's sleep adds a future and a task's wake-up to each (docs/live.md,
    "Load")."""

    def __init__(self, live, audio: np.ndarray, rate: int, chunk_s: float, loop: asyncio.AbstractEventLoop) -> None:
        self.live, self.audio, self.rate, self.chunk_s, self.loop = live, audio, rate, chunk_s, loop
        self.step = max(1, int(rate * chunk_s))
        self.count = -(-audio.shape[0] // self.step)  # chunks
        self.start, self.next = loop.time(), 0
        self.done: asyncio.Future = loop.create_future()
        self.timer: asyncio.TimerHandle | asyncio.Handle = loop.call_soon(self._push)

    def _push(self) -> None:
        try:
            if self.next < self.count:
                first = self.next * self.step
                self.live.push(self.audio[first:first + self.step], self.rate)
                self.next += 1
            if self.next < self.count:
                self.timer = self.loop.call_at(self.start + self.next * self.chunk_s, self._push)
                return
            self.live.flush()
        except LiveError:
            pass
        except Exception as error:  # anything else is the task's to raise, as the coroutine's own push raised it
            if not self.done.done():
                self.done.set_exception(error)
            return
        if not self.done.done():
            self.done.set_result(None)

    def stop(self) -> None:
        self.timer.cancel()


class PacedVoice:
    """The server's own voice for a session whose frames a pool thread makes: chunk k of `chunk_s` becomes the
    session's at `start + k * chunk_s` (time.monotonic()), pushed by `feed` when the pool takes up the session (at
    each frame it makes, before planning it), then a flush; what a frame sees is what `push_real_time`'s timers
    would have pushed by then. A hundred voices in 20 ms chunks cost the event loop 5,000 timer callbacks and
    pushes a second; fed so, they cost one push a frame on the pool thread (docs/live.md, "The server's own voice
    fed by the pool thread").
    `cancel` (a barge-in, the session's end) stops it between two feeds: no chunk of it is pushed after."""

    def __init__(self, live, audio: np.ndarray, rate: int, chunk_s: float, start: float) -> None:
        self.live, self.audio, self.rate, self.chunk_s, self.start = live, audio, rate, chunk_s, start
        self.step = max(1, int(rate * chunk_s))
        self.count = -(-audio.shape[0] // self.step)  # chunks
        self.next = 0  # chunks pushed
        self.ended = False  # flushed, cancelled, or its session closed
        self._lock = threading.Lock()  # feed (the pool thread) against cancel (the event loop)

    def feed(self, now: float) -> None:
        """Push every chunk whose time has come by `now` and is not pushed yet, in one push; flush after the last.
        A closed session (LiveError) ends the voice quietly; other errors are the session's (its pool reports)."""
        with self._lock:
            if self.ended:
                return
            # chunk k has come once start + k * chunk_s <= now (1e-9 of a chunk's slack: the division's rounding)
            due = min(self.count, math.floor((now - self.start) / self.chunk_s + 1e-9) + 1)
            try:
                if due > self.next:
                    self.live.push(self.audio[self.next * self.step:due * self.step], self.rate)
                    self.next = due
                if self.next >= self.count:
                    self.live.flush()
                    self.ended = True
            except LiveError:
                self.ended = True

    def cancel(self) -> None:
        """Stop: nothing more is pushed, no flush (waits for a feed under way to end)."""
        with self._lock:
            self.ended = True


__all__ = ["DEFAULT_CHUNK_MS", "PacedVoice", "Voice", "VoiceFiles", "push_real_time", "voice_of"]
