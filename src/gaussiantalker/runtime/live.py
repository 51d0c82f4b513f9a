"""Live sessions: audio arrives in chunks while frames leave, each as soon as its audio and lookahead are in.

    with TalkingHead("speaker.gtb") as head, head.live(lookahead_ms=160) as live:
        live.push(samples, sample_rate=24000)   # any chunk size, rate, int16 or float; returns at once
        for frame in live.frames():             # LiveFrame: index, pts, image, audio
            ...
        live.interrupt()                        # barge-in: drop queued audio, ease to the idle face
        live.end()                              # no more audio: the rest flushes, then frames() ends

The timeline (docs/live.md): frame n shows the samples [n, n + 1) / fps of a timeline made of the pushed audio and
of silent gaps where the face idled, so `pts` is the audio clock by construction. The translator sees a sliding
window: `context_ms` of the timeline's past, the frames it translates, and `lookahead_ms` of pushed audio ahead.
Paced mode gives frame n at start + n / fps on the wall clock (a frame whose lookahead is late goes out with what
has arrived; no audio at all means an idle frame); free-running mode gives frames as fast as they are ready and
idle frames only when no audio is queued.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

from gaussiantalker.sdk.audio import as_mono
from gaussiantalker.sdk.drive import BlendshapeDrive, FrameDrive
from gaussiantalker.sdk.errors import LiveError

from .idle import IdleMotion, IdleTrack, blink_vector
from .live_audio import ResampledQueue
from .translate import frame_start, silence_gain, silence_gain_of_sums
from .translate_stream import StreamJob, TranslatorStream, run_stream_jobs

# Frames translated per translator call at most when audio is queued ahead (a long push): bigger batches cost
# fewer calls but delay the first of them.
MAX_BATCH_FRAMES = 8
# Audio queued but not yet shown, at most (seconds): a push beyond it is refused (LiveError), so a consumer that
# stops reading cannot make memory grow.
MAX_QUEUED_S = 120.0
# Paced mode re-anchors its clock when it falls behind by more than this many frames (a renderer slower than real
# time): frames then come as fast as they are made instead of in a burst that tries to catch up.
MAX_LAG_FRAMES = 2
# Mid-utterance, a frame due before all of its lookahead has arrived is made with what is in (a late frame; a
# streaming translator makes its rows again once the audio is in). A session on a clock grid (a server's) first
# moves its clock one grid step later, to at most this many steps later than its phase: a voice whose chunks land
# just after the session's ticks then gets that slack once, instead of a late frame and a second translator call
# every tick. Idle frames take the steps back, one a frame, so a long session does not drift (docs/live.md,
# "A voice that lands late").
MAX_DEFERRALS = 2


@dataclass(frozen=True)
class LiveFrame:
    """One frame of a live session: `image` (the head's output mode; None for output=None), `audio` (float32 mono
    at `sample_rate`: the samples this frame shows, zeros while idle), `pts` = index / fps on the audio clock,
    `speaking` (False while idle or easing to idle) and the `drive` it was rendered from."""

    index: int
    pts: float
    image: np.ndarray | None
    audio: np.ndarray
    sample_rate: int
    speaking: bool
    drive: FrameDrive | BlendshapeDrive


@dataclass
class LiveStats:
    """Counts of a session so far (docs/live.md): what an app monitors to see a slow producer or consumer."""

    frames: int = 0
    speaking_frames: int = 0
    idle_frames: int = 0
    late_frames: int = 0  # paced: shown with less lookahead than asked (the producer fell behind)
    underruns: int = 0  # paced: idle frames put in while part of a frame's audio was queued
    deferrals: int = 0  # paced on a clock grid: grid steps the clock moved later for a lookahead still arriving
    translator_calls: int = 0
    dropped_s: float = 0.0  # audio dropped by interrupt()
    interrupts: int = 0


@dataclass
class _Translated:
    params: np.ndarray  # [D]
    out_audio: np.ndarray
    late: bool


@dataclass
class _Batch:
    """Frames [first, first + count) taken off the queues for one translator call: the windowed graph's `window`,
    or the stream's `job` (None when its rows are final already) and the batch's silence `gain`."""

    first: int
    count: int
    shown: list
    late: bool
    epoch: int
    window: np.ndarray | None = None
    job: StreamJob | None = None
    gain: float = 1.0


class _GateHistory:
    """Sum, sum of squares and length of each past frame's audio, the last `limit` samples' worth: the silence gate's
    view of a streaming session's context, which keeps no past audio (zeros at the start, as the windowed path's).
    Running totals (float64, rebuilt from the frames every REBUILD pushes so rounding cannot pile up)."""

    REBUILD = 256

    def __init__(self, limit: int) -> None:
        self.limit = limit
        self.reset()

    def reset(self) -> None:
        self.frames: deque[tuple[int, float, float]] = deque([(self.limit, 0.0, 0.0)])
        self.count, self.total, self.squares, self._pushes = self.limit, 0.0, 0.0, 0

    def push(self, samples: np.ndarray) -> None:
        values = samples.astype(np.float64)
        # np.add.reduce is what .sum() runs, bit for bit, without its Python wrapper (a call a frame)
        self._append((values.shape[0], float(np.add.reduce(values)), float(values @ values)))

    def push_silence(self, count: int) -> None:
        """`push` of `count` zeros (an idle frame), without making them."""
        self._append((count, 0.0, 0.0))

    def _append(self, entry: tuple[int, float, float]) -> None:
        self.frames.append(entry)
        self.count, self.total, self.squares = self.count + entry[0], self.total + entry[1], self.squares + entry[2]
        while len(self.frames) > 1 and self.count - self.frames[0][0] >= self.limit:
            n, t, q = self.frames.popleft()
            self.count, self.total, self.squares = self.count - n, self.total - t, self.squares - q
        self._pushes += 1
        if self._pushes % self.REBUILD == 0:
            self.total = sum(t for _, t, _ in self.frames)
            self.squares = sum(q for _, _, q in self.frames)

    def gain(self, ahead: np.ndarray, gate_dbfs: float | None) -> float:
        """The gate's gain over the past frames and `ahead` (the batch's audio and its lookahead)."""
        values = ahead.astype(np.float64)
        return silence_gain_of_sums(self.total + float(np.add.reduce(values)), self.squares + float(values @ values),
                                    self.count + values.shape[0], gate_dbfs)


@dataclass
class _Plan:
    params: np.ndarray | None  # None: idle
    out_audio: np.ndarray
    late: bool = False
    underrun: bool = False


@dataclass
class _Timeline:
    """Frame lengths in samples at one rate (a fractional samples-per-frame is rounded per frame)."""

    rate: int
    fps: float
    per_frame: float = field(init=False)

    def __post_init__(self) -> None:
        self.per_frame = self.rate / self.fps

    def span(self, first: int, last: int) -> int:
        """Samples of frames [first, last)."""
        return frame_start(last, self.per_frame) - frame_start(first, self.per_frame)


class LiveSession:
    """A live session on a TalkingHead (`TalkingHead.live`): push audio from any thread, read frames on the thread
    that owns the head's GL context. On a Driver alone (`LiveSession(head.driver, output=None)`) it makes each
    frame's drive and no pixels, as a server does that streams drives to a client that renders them."""

    def __init__(self, head, *, lookahead_ms: float = 160.0, paced: bool = True, context_ms: float = 1000.0,
                 output: str | None = "uint8", audio_rate: int | None = None, idle: IdleMotion | None = None,
                 max_queued_s: float = MAX_QUEUED_S, min_batch_frames: int = 1, streaming: bool | None = None,
                 clock_grid_s: float = 0.0) -> None:
        for name, value in (("lookahead_ms", lookahead_ms), ("context_ms", context_ms), ("max_queued_s", max_queued_s),
                            ("clock_grid_s", clock_grid_s)):
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0):
                raise LiveError(f"{name} must be a finite number >= 0, got {value!r}")
        if not (isinstance(min_batch_frames, int) and 1 <= min_batch_frames <= MAX_BATCH_FRAMES):
            raise LiveError(f"min_batch_frames must be a whole number in 1..{MAX_BATCH_FRAMES}, got "
                            f"{min_batch_frames!r}")
        driver = getattr(head, "driver", head)  # a TalkingHead, or a Driver alone (drives without pixels)
        if driver is head:
            head = None
            if output is not None:
                raise LiveError("a live session on a driver alone makes drives, not frames: give output=None, or "
                                "open it with head.live() to render them")
        if not driver.has_translator:
            driver.run_translator(np.zeros(1, np.float32))  # raises the error that says why and what instead
        has_stream = getattr(driver, "has_stream", False)  # a duck-typed driver (an evaluation's) may not say
        if streaming and not has_stream:
            raise LiveError("streaming=True, but this bundle's translator has no streaming graph (re-export it; "
                            "docs/live.md, \"Streaming translators\"); streaming=None uses one where present")
        self.head, self.driver, self.paced, self.output = head, driver, bool(paced), output
        self.fps = float(driver.fps)
        self.lookahead_frames = math.ceil(lookahead_ms * self.fps / 1000.0 - 1e-9)
        # An utterance starts once this many frames (and their lookahead) are in, so that the translator then runs
        # once per that many frames: fewer calls, each utterance later by min_batch_frames - 1 frames.
        self.min_batch_frames = min_batch_frames
        self.context_frames = math.ceil(context_ms * self.fps / 1000.0 - 1e-9)
        self.sample_rate = int(audio_rate) if audio_rate is not None else driver.sample_rate
        self._speech = _Timeline(driver.sample_rate, self.fps)
        self._out = _Timeline(self.sample_rate, self.fps)
        self._heard = ResampledQueue(driver.sample_rate)  # what the translator hears
        self._shown = ResampledQueue(self.sample_rate)  # what the frames carry
        self._history = np.zeros(self._speech.span(0, self.context_frames), np.float32)
        # Streaming (the bundle's translator_stream graph, by default where present): the stream's state replaces
        # the past audio, whose level the gate history keeps for the silence gate.
        self._stream = TranslatorStream(driver.stream_spec, self._speech.per_frame) \
            if (has_stream if streaming is None else streaming) else None
        self._gate = _GateHistory(self._history.shape[0])
        self._stream_epoch = 0
        self._inflight: _Batch | None = None  # taken by stream_job(), translated by the next step()
        self._max_queued = int(max_queued_s * driver.sample_rate)
        names = driver.param_names
        self._size = driver.param_count
        idle = idle or IdleMotion()
        self._idle = IdleTrack(idle, self.fps)
        self._blink = blink_vector(names, self._size, idle.blink)
        self._sway = driver.pose_track is None and (idle.sway_deg > 0 or idle.breath_mm > 0)
        self._translated: deque[_Translated] = deque()
        self._cond = threading.Condition()
        self._epoch = 0  # bumped by interrupt(): translator results of an older epoch are dropped
        self._flushed = False  # queued audio is complete: its last frames need no lookahead
        self._ended = self._closed = self._reading = False
        self._error: BaseException | None = None  # what frames() or poll() raised: the session stopped on it
        self._next_index = 0
        self._anchor: tuple[float, int] | None = None  # step(): (time, index) its pacing counts from
        # step()'s clock starts (and restarts after a lag) on multiples of this: sessions on one grid fall due
        # together, so a pool runs their translator calls as one (docs/live.md, "Streaming translators").
        self._clock_grid = float(clock_grid_s)
        self._finished = False
        self._deferrals = 0  # grid steps the clock now runs later than its phase (MAX_DEFERRALS)
        self._last_spoken: np.ndarray | None = None
        self._frames_since_speech = 0
        self.stats = LiveStats()

    # -- producer side (any thread) ------------------------------------------------------------------------------
    def push(self, samples, sample_rate: int) -> None:
        """Queue a chunk of speech (any size; int PCM or float; mono or [S, C]); returns at once. AudioError for
        bad audio, LiveError after end()/close() or when more than max_queued_s would be waiting."""
        mono, rate = as_mono(samples, sample_rate)
        with self._cond:
            if self._error is not None:
                raise LiveError(f"this live session stopped: making its frames raised {type(self._error).__name__}: "
                                f"{self._error}; open a new one with head.live()") from self._error
            if self._closed or self._ended:
                raise LiveError("this live session has " + ("been closed" if self._closed else "ended (end() was "
                                "called)") + ": open a new one with head.live() to push more audio")
            queued = len(self._heard.samples) + round(mono.shape[0] * self.driver.sample_rate / rate)
            if queued > self._max_queued:
                rate = self.driver.sample_rate
                raise LiveError(f"{queued / rate:.1f} s of audio would be waiting, more than "
                                f"max_queued_s={self._max_queued / rate:g}: the frames are not being "
                                "read (or not as fast as audio is pushed)")
            if mono.shape[0]:
                self._heard.push(mono, rate)
                self._shown.push(mono, rate)
                self._flushed = False
            self._cond.notify_all()

    def flush(self) -> None:
        """The queued audio is a complete utterance: its last frames go out without waiting for lookahead (the
        end of a text-to-speech reply). The session stays open for more."""
        with self._cond:
            self._heard.flush()
            self._shown.flush()
            self._flushed = True
            self._cond.notify_all()

    def end(self) -> None:
        """No more audio: the queued frames flush, then frames() ends."""
        self.flush()
        with self._cond:
            self._ended = True
            self._cond.notify_all()

    def interrupt(self) -> None:
        """Barge-in: drop the queued audio and frames not yet shown; the face eases to idle. The next push starts
        a new utterance with a clean context."""
        with self._cond:
            self.stats.dropped_s += self._queued_seconds()
            self.stats.interrupts += 1
            self._heard.clear()
            self._shown.clear()
            self._translated.clear()
            self._history[:] = 0.0
            self._gate.reset()
            self._inflight = None
            self._epoch += 1
            self._flushed = False
            self._cond.notify_all()

    def close(self) -> None:
        """Stop: frames() ends at its next frame; later pushes are refused."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()

    def __enter__(self) -> LiveSession:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def error(self) -> BaseException | None:
        """What frames() or poll() raised (a render or translator failure), which stopped the session; None while
        it runs or after a clean end."""
        return self._error

    def _fail(self, error: BaseException) -> None:
        """Making a frame raised: the session stops, so producers get a LiveError instead of queueing audio that
        no frame will show (docs/live.md, "Bad input and misuse")."""
        with self._cond:
            if self._error is None:
                self._error = error
            self._closed = True
            self._cond.notify_all()

    @property
    def queued_s(self) -> float:
        """Seconds of pushed audio not yet shown."""
        with self._cond:
            return self._queued_seconds()

    def _queued_seconds(self) -> float:
        """Under the lock: pushed audio not yet shown, queued or translated, in seconds."""
        return (len(self._heard.samples) + len(self._translated) * self._speech.per_frame) / self.driver.sample_rate

    # -- consumer side (the GL thread) ---------------------------------------------------------------------------
    def frames(self) -> Iterator[LiveFrame]:
        """Frames until end() has flushed or close(): paced at the frame rate, or free-running (docs/live.md)."""
        with self._cond:
            if self._reading:
                raise LiveError("frames() of this live session is already being read; read it once")
            self._reading = True
        try:
            anchor_time, anchor_index = time.monotonic(), self._next_index
            while True:
                plan = self._plan_or_fail(anchor_time + (self._next_index - anchor_index) / self.fps)
                if plan is None:
                    return
                frame = self._make(plan)
                if self.paced and time.monotonic() - anchor_time - (self._next_index - anchor_index) / self.fps \
                        > MAX_LAG_FRAMES / self.fps:
                    anchor_time, anchor_index = time.monotonic(), self._next_index
                yield frame
        finally:
            with self._cond:
                self._reading = False

    def step(self) -> LiveFrame | None:
        """Paced frames on an app's own scheduler (one thread serving many sessions, instead of a thread blocked in
        frames() for each): the next frame if it is due now, else None; call again at `due`. `finished` says when
        frames() would have ended."""
        with self._cond:
            if self._reading:
                raise LiveError("frames() of this live session is being read: read it with frames() or step(), "
                                "not both")
            if not self.paced:
                raise LiveError("step() gives frames at their due time: open the session with paced=True")
            if self._anchor is None:
                self._anchor = (self._on_grid(time.monotonic()), self._next_index)
            if self.due <= time.monotonic() and self._defer():
                return None
        due = self.due
        if due > time.monotonic():
            return None
        plan = self._plan_or_fail(due)  # due has come: it does not wait
        if plan is None:
            self._finished = True
            return None
        frame = self._make(plan)
        if time.monotonic() - due > MAX_LAG_FRAMES / self.fps:  # behind: re-anchor, as frames() does
            self._anchor = (self._on_grid(time.monotonic()), self._next_index)
            self._deferrals = 0
        return frame

    def _on_grid(self, moment: float) -> float:
        """`moment`, or the first multiple of the clock grid at or after it."""
        grid = self._clock_grid
        return math.ceil(moment / grid) * grid if grid > 0 else moment

    @property
    def due(self) -> float:
        """time.monotonic() at which step() gives the next frame (now, before the first step)."""
        if self._anchor is None:
            return time.monotonic()
        anchor_time, anchor_index = self._anchor
        return anchor_time + (self._next_index - anchor_index) / self.fps

    @property
    def _mid_utterance(self) -> bool:
        """The last frame spoke: an utterance is under way (its frames keep their cadence)."""
        return self._last_spoken is not None and self._frames_since_speech == 0

    @property
    def finished(self) -> bool:
        """step() gives no more frames: the session was closed, or ended and every frame went out."""
        return self._finished

    def poll(self) -> list[LiveFrame]:
        """The frames whose audio and lookahead are in now (no idle frames, no waiting): for apps that push and
        read on one thread or event loop."""
        frames = []
        while (plan := self._plan_or_fail(None)) is not None:  # _plan(None) neither waits nor idles
            frames.append(self._make(plan))
        return frames

    def _plan_or_fail(self, due: float | None) -> _Plan | None:
        """_plan, stopping the session if it raises (the translator failed)."""
        try:
            return self._plan(due)
        except Exception as error:
            self._fail(error)
            raise

    def _make(self, plan: _Plan) -> LiveFrame:
        """_render, stopping the session if it raises (the renderer failed)."""
        try:
            return self._render(plan)
        except Exception as error:
            self._fail(error)
            raise

    def _ready_batch(self) -> int:
        """Frames that can be translated now (their audio and lookahead queued, or flushed), 0 if none."""
        queued = len(self._heard.samples)
        first = self._next_index + len(self._translated)
        if queued == 0:
            return 0
        # frame k is ready when the queue reaches its lookahead's end (or, flushed, its own start): the span of
        # frames [first, e) is start(e) - start(first), one frame_start a bound rather than two spans' four
        per_frame, start = self._speech.per_frame, frame_start(first, self._speech.per_frame)
        count = 0
        while count < MAX_BATCH_FRAMES:
            if queued >= frame_start(first + count + 1 + self.lookahead_frames, per_frame) - start or (
                    self._flushed and queued > frame_start(first + count, per_frame) - start):
                count += 1
            else:
                break
        return count

    def _plan(self, due: float | None) -> _Plan | None:
        """The next frame's plan, translating a batch when one is ready; waits (paced: until `due`; free: until
        audio or end) when nothing can be shown. `due` None: never wait and never idle (poll)."""
        while True:
            with self._cond:
                if self._closed or (self._ended and not len(self._heard.samples) and not self._translated
                                    and self._inflight is None):
                    return None
                if due is not None and self.paced and due > time.monotonic():
                    self._cond.wait(due - time.monotonic())  # paced: nothing goes out before its time
                    continue
                if self._translated:
                    item = self._translated.popleft()
                    return _Plan(item.params, item.out_audio, late=item.late)
                count, late, mid_utterance = (0, False, False) if self._inflight is not None else \
                    self._batch_size(due)
                if self._inflight is not None:  # taken by stream_job(); a pool may have run its call
                    job, self._inflight = self._inflight, None
                elif count:
                    job = self._take_batch(count, late)
                elif due is None:
                    return None
                elif not self.paced and len(self._heard.samples):
                    self._cond.wait()
                    continue
                else:
                    underrun = mid_utterance and bool(len(self._heard.samples))
                    self._place_idle(self._next_index)
                    return _Plan(None, np.zeros(self._out.span(self._next_index, self._next_index + 1), np.float32),
                                 underrun=underrun)
            self._translate(job)

    def _defer(self, ready: int | None = None) -> bool:
        """Under the lock, the next frame due: whether its clock moved one grid step later instead of making it late
        (MAX_DEFERRALS): mid-utterance, its own audio in and its lookahead not, on a clock grid, not yet the most
        steps later. `ready`: `_ready_batch()` if the caller has it."""
        if self._clock_grid <= 0 or self._anchor is None or self._deferrals >= MAX_DEFERRALS or self._flushed \
                or self._translated or self._inflight is not None:
            return False
        own = self._speech.span(self._next_index, self._next_index + 1)
        if not self._mid_utterance or len(self._heard.samples) < own or (
                self._ready_batch() if ready is None else ready):
            return False
        anchor_time, anchor_index = self._anchor
        self._anchor = (anchor_time + self._clock_grid, anchor_index)
        self._deferrals += 1
        self.stats.deferrals += 1
        return True

    def _batch_size(self, due: float | None, ready: int | None = None) -> tuple[int, bool, bool]:
        """Under the lock: (frames to translate now, whether late, whether mid-utterance); `ready` as `_defer`'s."""
        count = self._ready_batch() if ready is None else ready
        late = False
        mid_utterance = self._mid_utterance
        if count < self.min_batch_frames and not self._flushed and not (mid_utterance and self.paced
                                                                         and due is not None):
            count = 0  # a batch fills before an utterance starts; mid-utterance, what is ready goes now
        if count == 0 and due is not None and self.paced and mid_utterance \
                and len(self._heard.samples) >= self._speech.span(self._next_index, self._next_index + 1):
            # Mid-utterance, its own audio is in but its lookahead is late: show it with what is in. (An
            # utterance starts only once its first frame's lookahead is in, which gives later frames slack.)
            count, late = 1, True
        return count, late, mid_utterance

    def stream_job(self) -> StreamJob | None:
        """The streaming translator call that the frame due now needs, planned but not run (paced sessions, on the
        thread that reads them): a pool gathers these from every session with a frame due and runs them as one
        call (`run_stream_jobs`), then `step()` makes each frame from its rows. None when no call is needed."""
        with self._cond:
            if self._stream is None or self._inflight is not None or self._translated or self._closed \
                    or not self.paced or (self._anchor is not None and self.due > time.monotonic()):
                return None
            ready = self._ready_batch()  # the queue does not change under the lock: counted once for both
            if self._defer(ready):
                return None
            count, late, _ = self._batch_size(self.due, ready)
            if not count:
                return None
            self._inflight = self._take_batch(count, late)
            return self._inflight.job

    def _take_batch(self, count: int, late: bool) -> _Batch:
        """Under the lock: cut `count` frames' audio off the queues and build the translator window (windowed), or
        hand the stream what is known of the timeline and plan its call (streaming)."""
        first = self._next_index + len(self._translated)
        own = self._speech.span(first, first + count)
        ahead = self._speech.span(first + count, first + count + self.lookahead_frames)
        queued = min(own + ahead, len(self._heard.samples))  # the rest is unknown (flushed: silence)
        known = self._heard.samples.peek(own + ahead)
        speech = self._heard.samples.take(own)
        shown = [self._shown.samples.take(self._out.span(index, index + 1)) for index in range(first, first + count)]
        batch = _Batch(first, count, shown, late, self._epoch)
        if self._stream is None:
            batch.window = np.concatenate([self._history, known])
        else:
            batch.gain = self._gate.gain(known, self.driver.silence_gate_dbfs)
            self._synced_stream(first).offer(frame_start(first, self._speech.per_frame), known[:queued])
            batch.job = self._stream.plan(range(first, first + count))
        self._place(speech, first, count)
        return batch

    def _synced_stream(self, index: int) -> TranslatorStream:
        """Under the lock: the stream, restarted at frame `index` if an interrupt() cleared the context since."""
        if self._stream_epoch != self._epoch:
            self._stream.reset(frame_start(index, self._speech.per_frame))
            self._stream_epoch = self._epoch
        return self._stream

    def _place(self, speech: np.ndarray, first: int, count: int = 1) -> None:
        """Frames [first, first + count)'s shown speech-rate samples join the translator's past context (a sliding
        window; streaming: the gate's history)."""
        if self._stream is None:
            if self._history.shape[0]:
                self._history = np.concatenate([self._history, speech])[-self._history.shape[0]:]
            return
        start = frame_start(first, self._speech.per_frame)
        for index in range(first, first + count):
            lo, hi = frame_start(index, self._speech.per_frame) - start, frame_start(index + 1, self._speech.per_frame)
            self._gate.push(speech[lo:hi - start])

    def _place_idle(self, index: int) -> None:
        """Idle frame `index`'s silence joins the translator's past context: zeros in the sliding window; streaming,
        the gate counts them without making them and the stream idles over the gap."""
        span = self._speech.span(index, index + 1)
        if self._stream is None:
            self._place(np.zeros(span, np.float32), index)
            return
        self._gate.push_silence(span)
        start = frame_start(index, self._speech.per_frame)
        self._synced_stream(index).idle(start, start + span)

    def _translate(self, batch: _Batch) -> None:
        """Run the translator outside the lock (windowed: on the batch's window; streaming: the stream's call,
        unless a pool ran it); keep the batch's frames unless interrupted meanwhile."""
        if batch.window is not None:
            frames = self.context_frames + batch.count + self.lookahead_frames
            params = self.driver.params_of(self.driver.run_translator(batch.window), frames) * np.float32(
                silence_gain(batch.window, self.driver.silence_gate_dbfs))
            rows = params[self.context_frames:self.context_frames + batch.count]
        else:
            job = batch.job
            if job is not None and job.rows is None:
                run_stream_jobs([job], self.driver.run_stream, self.driver.stream_rows)
            with self._cond:
                if batch.epoch != self._epoch:
                    return
            if job is not None:
                self._stream.finish(job)
            gain = np.float32(batch.gain)
            rows = [self._stream.params(index) * gain for index in range(batch.first, batch.first + batch.count)]
        with self._cond:
            self.stats.translator_calls += batch.window is not None or batch.job is not None
            if batch.epoch != self._epoch:
                return
            for row, audio in zip(rows, batch.shown, strict=True):
                self._translated.append(_Translated(np.asarray(row, np.float32), audio, batch.late))

    def _render(self, plan: _Plan) -> LiveFrame:
        """The plan's drive (idle motion added) rendered; bookkeeping of the ease and the stats."""
        index = self._next_index
        speaking = plan.params is not None
        if speaking:
            params, self._last_spoken, self._frames_since_speech = plan.params, plan.params, 0
        else:
            self._frames_since_speech += 1
            if self._deferrals and self._anchor is not None:  # idle: the clock takes back a step it deferred
                self._anchor = (self._anchor[0] - self._clock_grid, self._anchor[1])
                self._deferrals -= 1
            ease = 0.0 if self._last_spoken is None else self._idle.ease_weight(self._frames_since_speech)
            params = self._last_spoken * np.float32(ease) if ease > 0 else np.zeros(self._size, np.float32)
        blink = self._idle.blink_weight(index, idle=not speaking)
        if blink:
            params = params + np.float32(blink) * self._blink
        drive = self._drive(params, index)
        image = None
        if self.output is not None:
            image = self.head.render(drive, self.output,
                                     reference_frame=index if self.head.compositor is not None else None)
        stats = self.stats
        stats.frames += 1
        stats.speaking_frames += speaking
        stats.idle_frames += not speaking
        stats.late_frames += plan.late
        stats.underruns += plan.underrun
        self._next_index += 1
        return LiveFrame(index, index / self.fps, image, plan.out_audio, self.sample_rate, speaking, drive)

    def _drive(self, params: np.ndarray, index: int) -> FrameDrive | BlendshapeDrive:
        pose = self._idle.sway(index) if self._sway else self.driver.head_pose(index)
        return self.driver.drive_from_params(self.driver.clamp_params(params), pose)


__all__ = ["LiveSession", "LiveFrame", "LiveStats", "IdleMotion"]
