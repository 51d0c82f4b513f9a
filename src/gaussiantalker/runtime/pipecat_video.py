"""A Pipecat frame processor that gives a voice agent a face (docs/live.md, "Pipecat"):

    pipeline = Pipeline([transport.input(), stt, llm, tts, TalkingHeadVideo("speaker.gtb"), transport.output()])

Text-to-speech audio frames go into a live session instead of straight on; every frame of the session then goes
downstream as an OutputAudioRawFrame (the samples it shows, silence while idle) followed by an OutputImageRawFrame
queued with that audio (`sync_with_audio`), so the output transport plays voice and face together. The end of a
reply (TTSStoppedFrame) flushes the session, an interruption is a barge-in, and the face idles between turns.

Push back: a text-to-speech service faster than real time would fill the session faster than the face shows it, so
a chunk waits in process_frame (on the event loop, woken as each frame goes out) until the session's queued audio
leaves room for it within `max_ahead_s`; the frames behind it wait in Pipecat's queue, and an interruption or a
cancel ends the wait. A chunk the session still refuses (longer alone than its `max_queued_s`) passes on without
the face, reported once a reply as an ErrorFrame that leaves the processor usable (docs/live.md, "Pipecat").

The session runs on a render thread of its own, which owns the TalkingHead and its GL context; its frames reach
the pipeline's event loop through a queue drained by one task, so they keep their order. A session that fails (the
head cannot load, or a frame raises) ends: the error goes upstream once as an ErrorFrame that marks the processor
unusable (the pipeline worker's ProcessorUnusablePolicy decides what follows), the render thread exits, and
text-to-speech audio then passes on unchanged, the voice without the face (docs/live.md, "Pipecat").
"""

from __future__ import annotations

import asyncio
import math
import os
import threading

import numpy as np

try:
    from pipecat.frames.frames import (
        CancelFrame,
        EndFrame,
        InterruptionFrame,
        OutputAudioRawFrame,
        OutputImageRawFrame,
        StartFrame,
        TTSAudioRawFrame,
        TTSStoppedFrame,
    )
    from pipecat.processors.frame_processor import FrameDirection, FrameProcessor, FrameProcessorSetup
except ImportError as exc:  # an optional extra: the runtime does not need it
    raise ImportError(f"TalkingHeadVideo needs Pipecat: pip install 'gaussiantalker-sdk[pipecat]' ({exc})") from None

from gaussiantalker.sdk.audio import to_pcm16
from gaussiantalker.sdk.errors import LiveError

from .head import TalkingHead
from .live import MAX_QUEUED_S, LiveFrame, LiveSession


class TalkingHeadVideo(FrameProcessor):
    """Text-to-speech audio in; the talking head's frames and the same audio out, in sync (paced at the frame rate,
    idling between turns). `bundle`: a speaker bundle with a translator; `resolution`, `lookahead_ms` and `idle` as
    for TalkingHead and TalkingHead.live; `max_ahead_s`: seconds of audio queued ahead of the face at most, beyond
    which text-to-speech audio waits (push back; up to the session's max_queued_s, 120 s)."""

    def __init__(self, bundle: str | os.PathLike, *, resolution: tuple[int, int] | None = None,
                 lookahead_ms: float = 160.0, idle=None, max_ahead_s: float = 30.0, **kwargs) -> None:
        if not (isinstance(max_ahead_s, (int, float)) and math.isfinite(max_ahead_s)
                and 0 < max_ahead_s <= MAX_QUEUED_S):
            raise LiveError(f"max_ahead_s must be a number in (0, {MAX_QUEUED_S:g}] (the session's max_queued_s), "
                            f"got {max_ahead_s!r}")
        super().__init__(**kwargs)
        self._bundle, self._resolution, self._lookahead_ms, self._idle = bundle, resolution, lookahead_ms, idle
        self._max_ahead_s = float(max_ahead_s)
        self._live: LiveSession | None = None
        self._failed = False  # the session failed and its error went upstream: frames pass on unchanged
        self._refused = False  # this reply had a chunk refused, reported upstream: later refusals pass quietly
        self._room = asyncio.Event()  # set as frames go out (the queue shrank) and when the session stops
        self._audio_rate = 16000
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._thread: threading.Thread | None = None
        self._queue: asyncio.Queue | None = None
        self._sender: asyncio.Task | None = None
        self._sent = 0  # frames of the session pushed downstream (the next frame's index)

    # -- the pipeline's side -------------------------------------------------------------------------------------
    async def setup(self, setup: FrameProcessorSetup) -> None:
        await super().setup(setup)
        self._audio_rate = setup.audio_out_sample_rate  # the transport's output rate: the frames' audio comes at it

    async def process_frame(self, frame, direction: FrameDirection) -> None:
        await super().process_frame(frame, direction)
        if isinstance(frame, StartFrame):
            await self.push_frame(frame, direction)
            await self._start(self._audio_rate)
            return
        live = None if self._failed else self._live
        if isinstance(frame, TTSAudioRawFrame) and live is not None:
            pcm = np.frombuffer(frame.audio, np.int16).reshape(-1, frame.num_channels)
            await self._wait_for_room(live, pcm.shape[0] / frame.sample_rate if frame.sample_rate > 0 else 0.0)
            if self._live is live:  # else the session stopped while the chunk waited (a CancelFrame)
                try:
                    live.push(pcm, frame.sample_rate)
                    return  # its samples go on with the frames that show them
                except LiveError as error:
                    if live.error is None:  # refused while the session runs: too long alone
                        await self._report_refused(error)
                        live.flush()  # the audio before this chunk is shown in full before it goes on, in order
                        await self._wait_until_sent(live)
                    # Else the session has just failed and its error is on its way upstream. Either way the voice
                    # goes on without a face.
        elif isinstance(frame, TTSStoppedFrame) and live is not None:
            live.flush()
            self._refused = False
        elif isinstance(frame, InterruptionFrame) and live is not None:
            live.interrupt()
            self._refused = False
            self._room.set()  # the queue is empty now
        elif isinstance(frame, (EndFrame, CancelFrame)):
            await self._stop(drain=isinstance(frame, EndFrame))
        await self.push_frame(frame, direction)

    async def _start(self, audio_rate: int) -> None:
        loop = asyncio.get_running_loop()
        self._queue = asyncio.Queue()
        self._thread = threading.Thread(target=self._render, args=(loop, audio_rate), name="gt-pipecat-render",
                                        daemon=True)
        self._thread.start()
        await loop.run_in_executor(None, self._ready.wait)
        if self._error is not None:
            await self._report(self._error, "its live session could not start")
            return
        self._sender = self.create_task(self._send())

    async def _stop(self, drain: bool) -> None:
        """EndFrame: the session ends, its last frames go out first. CancelFrame: close at once."""
        if self._live is None or self._sender is None:
            return
        if drain:
            self._live.end()
        else:
            self._live.close()
        await asyncio.get_running_loop().run_in_executor(None, self._thread.join)
        if drain:
            await self._sender  # every frame the session made is pushed before the EndFrame (the thread's end
            # marker, queued however it ended, lets it return)
        else:
            await self.cancel_task(self._sender)
        self._live = self._sender = None
        self._room.set()  # a chunk still waiting for room stops waiting

    async def _wait_for_room(self, live: LiveSession, seconds: float, held: float | None = None) -> None:
        """Push back: return once `seconds` more fit within max_ahead_s of queued audio, or the queue is down to
        `held` (by default what the session may hold back for lookahead: a chunk longer than the bound then goes in
        alone), or the session has stopped. Waits on the event loop, woken by each frame that goes out
        (docs/live.md, "Pipecat")."""
        if held is None:
            # Queued audio the session may hold without making frames until more comes (an utterance starts once
            # its first frames and their lookahead are in): waiting for less could wait for ever.
            held = (live.lookahead_frames + live.min_batch_frames + 1) / live.fps
        while self._live is live and live.error is None:
            self._room.clear()
            queued = live.queued_s
            if queued + seconds <= self._max_ahead_s or queued <= held:
                return
            await self._room.wait()

    async def _wait_until_sent(self, live: LiveSession) -> None:
        """Return once every frame showing audio queued so far has gone downstream (or the session stopped), so a
        chunk passed on without the face follows the audio before it. The queue empties when its last frame is
        planned, while that frame may still be rendering or on its way here: it is the frame numbered
        `stats.frames` at most, so wait for that one to be sent (an idle frame, if it was already out)."""
        await self._wait_for_room(live, math.inf, held=0.0)
        last = live.stats.frames
        while self._live is live and live.error is None and self._sent <= last:
            self._room.clear()
            await self._room.wait()

    async def _report_refused(self, error: LiveError) -> None:
        """The running session refused a chunk (longer alone than its max_queued_s): tell the pipeline once a reply
        (an ErrorFrame upstream that leaves the processor usable); the chunk passes on without the face."""
        if self._refused:
            return
        self._refused = True
        await self.push_error(f"text-to-speech audio passes on without the face: {error}", exception=error,
                              force_treat_as_permanent=False)

    async def _report(self, error: BaseException, what: str) -> None:
        """The session failed: tell the pipeline once (an ErrorFrame upstream, which Pipecat logs), and let the
        frames that follow pass on unchanged."""
        if self._failed:
            return
        self._failed = True
        await self.push_error(f"{what}: {type(error).__name__}: {error}", exception=error,
                              force_treat_as_permanent=True)

    async def _send(self) -> None:
        """Push the session's frames downstream in order: the audio they show, then the picture, queued with it."""
        while True:
            frame: LiveFrame | BaseException | None = await self._queue.get()
            if frame is None:
                self._room.set()  # the session ended: nothing waits on it any more
                return
            if isinstance(frame, BaseException):
                self._room.set()
                await self._report(frame, "its live session ended: rendering a frame raised")
                continue
            pcm = to_pcm16(frame.audio).tobytes()  # int16 exact
            await self.push_frame(OutputAudioRawFrame(audio=pcm, sample_rate=frame.sample_rate, num_channels=1))
            height, width = frame.image.shape[:2]
            image = OutputImageRawFrame(image=frame.image.tobytes(), size=(width, height), format="RGB")
            image.sync_with_audio = True
            image.pts = round(frame.pts * 1e9)  # Pipecat's presentation times are nanoseconds
            await self.push_frame(image)
            self._sent = frame.index + 1
            self._room.set()  # a frame went out, so the session's queue shrank

    # -- the render thread ---------------------------------------------------------------------------------------
    def _render(self, loop: asyncio.AbstractEventLoop, audio_rate: int) -> None:
        """Load the head, then queue the session's frames; a failure is queued for the pipeline's side to report,
        and the end marker always follows, so draining at EndFrame never waits on a thread that died."""
        started = False
        try:
            with TalkingHead(self._bundle, resolution=self._resolution, composite=False) as head, \
                    head.live(lookahead_ms=self._lookahead_ms, audio_rate=audio_rate, idle=self._idle) as live:
                self._live, started = live, True
                self._ready.set()
                for frame in live.frames():
                    self._queue_from_thread(loop, frame)
        except Exception as exc:
            if started:  # a frame raised: the session has stopped (LiveSession.error)
                self._queue_from_thread(loop, exc)
            else:  # the head or its session could not be made: reported by _start
                self._error = exc
        finally:
            self._ready.set()
            if started:
                self._queue_from_thread(loop, None)

    def _queue_from_thread(self, loop: asyncio.AbstractEventLoop, item) -> None:
        try:
            loop.call_soon_threadsafe(self._queue.put_nowait, item)
        except RuntimeError:  # the pipeline's loop has closed: nobody drains the queue any more
            pass


__all__ = ["TalkingHeadVideo"]
