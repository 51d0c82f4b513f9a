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
from .translate_stream import StreamJob, StreamSpec, TranslatorStream, run_stream_jobs

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
# The silence gate's running totals are summed again from its frames every this many frames (float64 rounding does
# not pile up over a long session).
GATE_REBUILD = 256


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


def frame_sums(frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each row's sum and sum of squares, in float64, of frames [n, F] (a frame a row, zero-padded to the longest):
    what the silence gate keeps of a frame. Reductions along the rows, as runtime/live_steady.py's over many
    sessions' frames at once: the same bits for the same row."""
    values = frames.astype(np.float64)
    return np.add.reduce(values, axis=1), np.add.reduce(values * values, axis=1)


class _GateHistory:
    """(samples, sum, sum of squares) of each of the last `len(rest)` frames (`frame_sums`): the silence gate's view
    of a streaming session's context, which keeps no past audio (silent frames of the `rest` spans at the start, as
    the windowed path's zeros). Running totals (float64, rebuilt from the frames every GATE_REBUILD pushes so
    rounding cannot pile up)."""

    def __init__(self, rest: tuple[int, ...]) -> None:
        self.rest = tuple(rest)
        self.reset()

    def reset(self) -> None:
        self.frames: deque[tuple[int, float, float]] = deque(((n, 0.0, 0.0) for n in self.rest),
                                                               maxlen=len(self.rest))
        self.count, self.total, self.squares, self.pushes = sum(self.rest), 0.0, 0.0, 0

    def push(self, entry: tuple[int, float, float]) -> None:
        """A frame's (samples, sum, sum of squares) joins the context; the oldest frame leaves it."""
        if not self.rest:
            return
        oldest = self.frames[0]
        self.frames.append(entry)
        self.count = self.count + entry[0] - oldest[0]
        self.total = self.total + entry[1] - oldest[1]
        self.squares = self.squares + entry[2] - oldest[2]
        self.pushes += 1
        if self.pushes % GATE_REBUILD == 0:
            self.total = sum(t for _, t, _ in self.frames)
            self.squares = sum(q for _, _, q in self.frames)

    def push_silence(self, count: int) -> None:
        """`push` of a frame of `count` zeros (an idle frame), without making them."""
        self.push((count, 0.0, 0.0))

    def gain(self, ahead: list[tuple[int, float, float]], gate_dbfs: float | None) -> float:
        """The gate's gain over the past frames and the frames `ahead` (the batch's and its lookahead's, each as
        `push` takes it), added one frame at a time in order."""
        count, total, squares = self.count, self.total, self.squares
        for n, t, q in ahead:
            count, total, squares = count + n, total + t, squares + q
        return silence_gain_of_sums(total, squares, count, gate_dbfs)


@dataclass
class FramePlan:
    """A frame planned, not yet made (`next_plan`): its parameters and audio."""

    params: np.ndarray | None  # None: idle
    out_audio: np.ndarray
    late: bool = False
    underrun: bool = False


@dataclass
class SteadyState:
    """What a pool's steady table (runtime/live_steady.py) holds of a session while its frames are steady: its silence
    gate (the ring of the last frames' (samples, sum, sum of squares), oldest first, and the running totals) and its
    stream as the last call left it."""

    gate: list[tuple[int, float, float]]
    count: int
    total: float
    squares: float
    pushes: int
    powers: np.ndarray  # the committed frames' mean squares (the loudness gate's)
    made: np.ndarray  # the loudness the last frames' features were made at (the loudness gate's)
    committed: int
    quiet: int
    state: np.ndarray
    state_row: tuple[np.ndarray, int] | None
    ahead: np.ndarray | None = None  # entering: this frame's and its lookahead's samples but the newest [L, F]
    final: dict[int, np.ndarray] | None = None  # leaving: the last frame's row, by stream row index


@dataclass
class SteadyTake:
    """A steady frame taken off a session's queues (`take_steady`)."""

    index: int
    epoch: int  # the session's epoch: a barge-in since makes it another
    interrupts: int  # stats.interrupts: the frame's epoch on the wire
    due: float
    out_audio: np.ndarray
    entry: SteadyState | None  # the session entering the table: what it holds of it


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


def session_stream_spec(driver, delay_ms: float | None) -> StreamSpec:
    """The stream a session runs: the driver's main one, or the one whose rows lag the audio by `delay_ms` (a trained
    speaker's short stream: docs/live.md, "A stream for a short lookahead"); LiveError naming the delays the driver's
    streams have where none lags so."""
    if delay_ms is None:
        return driver.stream_spec
    specs = getattr(driver, "stream_specs", (driver.stream_spec,))  # a duck-typed driver: its one stream
    delays = [spec.delay_ms(driver.sample_rate) for spec in specs]
    for spec, delay in zip(specs, delays, strict=True):
        if abs(delay - delay_ms) < 0.5:
            return spec
    have = ", ".join(f"{delay:g} ms" for delay in delays)
    raise LiveError(f"this bundle's translator has no stream whose rows lag {delay_ms:g} ms (its streams: {have}); "
                    "a trained speaker exported by this SDK also has an 80 ms one (re-export it)")


class LiveSession:
    """A live session on a TalkingHead (`TalkingHead.live`): push audio from any thread, read frames on the thread
    that owns the head's GL context. On a Driver alone (`LiveSession(head.driver, output=None)`) it makes each
    frame's drive and no pixels, as a server does that streams drives to a client that renders them."""

    def __init__(self, head, *, lookahead_ms: float = 160.0, paced: bool = True, context_ms: float = 1000.0,
                 output: str | None = "uint8", audio_rate: int | None = None, idle: IdleMotion | None = None,
                 max_queued_s: float = MAX_QUEUED_S, min_batch_frames: int = 1, streaming: bool | None = None,
                 clock_grid_s: float = 0.0, stream_delay_ms: float | None = None) -> None:
        for name, value in (("lookahead_ms", lookahead_ms), ("context_ms", context_ms), ("max_queued_s", max_queued_s),
                            ("clock_grid_s", clock_grid_s), ("stream_delay_ms", stream_delay_ms)):
            if name == "stream_delay_ms" and value is None:
                continue
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
        # A frame goes out once its audio and lookahead_ms past its end are in (exactly, in the translator's
        # samples); the window and the silence gate cover the whole frames that lookahead reaches into, the unknown
        # rest zeros (docs/live.md, "Lookahead on a 30 fps avatar").
        self.lookahead_samples = round(lookahead_ms * driver.sample_rate / 1000.0)
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
        self._stream = None
        if has_stream if streaming is None else streaming:
            self._stream = TranslatorStream(session_stream_spec(driver, stream_delay_ms), self._speech.per_frame)
        elif stream_delay_ms is not None:
            raise LiveError("stream_delay_ms picks one of the translator's streams, but this session translates "
                            "windows (streaming=False, or a bundle without a streaming graph)")
        self._gate = _GateHistory(tuple(self._speech.span(k, k + 1) for k in range(self.context_frames)))
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
        planned = self.next_plan()
        if planned is None:
            return None
        frame = self._make(planned[0])
        self.keep_pace(planned[1])
        return frame

    def next_plan(self) -> tuple[FramePlan, float] | None:
        """step() but the making of the frame: the plan of the frame due now and its due time (None: none due), for
        a pool that makes many sessions' frames together (it then calls `keep_pace`)."""
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
        return plan, due

    def keep_pace(self, due: float) -> None:
        """After step() made the frame that was due at `due`: a clock behind by more than MAX_LAG_FRAMES re-anchors
        now, as frames() does."""
        if time.monotonic() - due > MAX_LAG_FRAMES / self.fps:
            self._anchor = (self._on_grid(time.monotonic()), self._next_index)
            self._deferrals = 0

    def _on_grid(self, moment: float) -> float:
        """`moment`, or the first multiple of the clock grid at or after it."""
        grid = self._clock_grid
        return math.ceil(moment / grid) * grid if grid > 0 else moment

    # -- a pool's interface: many sessions' frames planned and made together (runtime/live_steady.py, live_rows.py) --
    def make_frame(self, plan: FramePlan) -> LiveFrame:
        """The frame of `plan` (`next_plan`'s) made alone; stops the session if it raises."""
        return self._make(plan)

    def fail(self, error: BaseException) -> None:
        """Making this session's frame failed elsewhere (a pool's arrays): the session stops, as `_make` stops it."""
        self._fail(error)

    @property
    def sways(self) -> bool:
        """The head pose is the idle sway (no pose track), a frame at a time (`pose`)."""
        return self._sway

    @property
    def stream_spec(self) -> StreamSpec | None:
        """The spec of the stream this session runs (None: it translates windows)."""
        return None if self._stream is None else self._stream.spec

    def steady_key(self) -> tuple | None:
        """Which steady table this session's steady frames go to (sessions of one driver, lookahead and context), or
        None when its frames are never steady: windowed, rendering, free-running, a rig whose frames are not the
        stream's (a 30 fps avatar on the 25 fps voice interpolates between rows), rows lagging past the lookahead,
        or a lookahead of part of a frame."""
        stream = self._stream
        if stream is None or self.output is not None or not self.paced or not stream.aligned \
                or self._speech.per_frame != stream.spec.frame_samples or stream.spec.delay > self.lookahead_frames \
                or self.lookahead_samples != self.lookahead_frames * stream.spec.frame_samples:
            return None
        return id(self.driver), self.lookahead_frames, self.context_frames

    def take_steady(self, now: float, entered: int | None, newest: np.ndarray, call: np.ndarray) -> SteadyTake | None:
        """If the frame due by `now` is a steady one (docs/live.md, "Steady frames made together"), take it off the
        queues: its newest lookahead frame's samples into `newest`, its call's frame's into `call`; None when it is
        not (the frame, if any, is `stream_job`'s and `next_plan`'s). `entered`: the epoch at which the session
        entered the table, None when it is not in it (then it enters: `SteadyTake.entry`)."""
        with self._cond:
            if not self._steady_due(now, entered):
                return None
            size, lookahead = self._stream.spec.frame_samples, self.lookahead_frames
            head = self._heard.samples.head((lookahead + 1) * size)
            entry = None if entered is not None else self._steady_entry(head[:lookahead * size])
            newest[:] = head[lookahead * size:]
            delay = self._stream.spec.delay
            call[:] = head[delay * size:(delay + 1) * size]
            self._heard.samples.skip(size)  # the frame's own audio leaves the queue
            index = self._next_index
            return SteadyTake(index, self._epoch, self.stats.interrupts, self.due,
                              self._shown.samples.take(self._out.span(index, index + 1)), entry)

    def _steady_due(self, now: float, entered: int | None) -> bool:
        """Under the lock: whether the frame due by `now` is steady: mid-utterance, exactly its audio and lookahead
        queued (`_ready_batch`), and its stream's call one committed frame whose row is this frame's (in the table
        since epoch `entered`, the table keeps it so)."""
        if self._anchor is None or self._closed or self._ended or self._flushed or self._inflight is not None \
                or self._translated or self._error is not None or self._reading or not self._mid_utterance \
                or self.due > now:
            return False
        stream, lookahead = self._stream, self.lookahead_frames
        size, index = stream.spec.frame_samples, self._next_index
        if not (lookahead + 1) * size <= len(self._heard.samples) < (lookahead + 2) * size:
            return False
        if entered is not None:
            return entered == self._epoch
        return self._stream_epoch == self._epoch and stream.origin % size == 0 \
            and stream.committed - stream.spec.delay == index - stream.origin // size \
            and stream.known_end == (index + lookahead) * size and len(self._gate.frames) == self.context_frames

    def _steady_entry(self, ahead: np.ndarray) -> SteadyState:
        """Under the lock: the gate and stream as the table takes them up; `ahead` this frame's and its lookahead's
        samples but the newest."""
        gate, stream, size = self._gate, self._stream, self._stream.spec.frame_samples
        return SteadyState(list(gate.frames), gate.count, gate.total, gate.squares, gate.pushes, stream.powers,
                           stream.made, stream.committed, stream.quiet, stream.state, stream.state_row,
                           ahead=ahead.reshape(-1, size).copy())

    def leave_steady(self, entered: int, state: SteadyState) -> None:
        """The table gives the session's gate and stream back (`state`: as its last steady frame left them). After a
        barge-in since epoch `entered` it does not: interrupt() reset the gate, and the stream restarts at its next
        call."""
        with self._cond:
            if entered != self._epoch:
                return
            gate, stream = self._gate, self._stream
            gate.frames.clear()
            gate.frames.extend(state.gate)
            gate.count, gate.total, gate.squares, gate.pushes = state.count, state.total, state.squares, state.pushes
            # what the stream knows past its committed frames: the lookahead offered with the last frame, still queued
            first = stream.origin + state.committed * stream.spec.frame_samples \
                - frame_start(self._next_index, self._speech.per_frame)
            known = self._heard.samples.peek(self.lookahead_frames * stream.spec.frame_samples)[first:]
            stream.resume(state.committed, state.state, state.state_row, state.quiet, state.powers,
                          state.made, state.final or {}, known)

    def steady_plan(self, epoch: int, params: np.ndarray, out_audio: np.ndarray) -> FramePlan | None:
        """The plan of a steady frame taken at `epoch` whose call has run (`params`: its row times its gain); None
        when the session was barged in on or closed since (its frame, if any, is `next_plan`'s)."""
        with self._cond:
            if self._epoch != epoch or self._closed or self._error is not None:
                return None
            self.stats.translator_calls += 1
        return FramePlan(params, out_audio)

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

    def _plan_or_fail(self, due: float | None) -> FramePlan | None:
        """_plan, stopping the session if it raises (the translator failed)."""
        try:
            return self._plan(due)
        except Exception as error:
            self._fail(error)
            raise

    def _make(self, plan: FramePlan) -> LiveFrame:
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
        lookahead = self.lookahead_samples - start
        count = 0
        while count < MAX_BATCH_FRAMES:
            if queued >= frame_start(first + count + 1, per_frame) + lookahead or (
                    self._flushed and queued > frame_start(first + count, per_frame) - start):
                count += 1
            else:
                break
        return count

    def _plan(self, due: float | None) -> FramePlan | None:
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
                    return FramePlan(item.params, item.out_audio, late=item.late)
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
                    return FramePlan(None, np.zeros(self._out.span(self._next_index, self._next_index + 1), np.float32),
                                     underrun=underrun)
            self._translate(job)

    def _defer(self, ready: int | None = None) -> bool:
        """Under the lock, the next frame due: whether its clock moved one grid step later instead of making it late
        (MAX_DEFERRALS): mid-utterance, its own audio in and its lookahead not, on a clock grid, not yet the most
        steps later. `ready`: `_ready_batch()` if the caller has it."""
        if self._clock_grid <= 0 or self._anchor is None or self._deferrals >= MAX_DEFERRALS or self._flushed \
                or self._translated or self._inflight is not None or self._closed:
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
        self._heard.samples.skip(own)  # the batch's own samples: known's first `own`
        shown = [self._shown.samples.take(self._out.span(index, index + 1)) for index in range(first, first + count)]
        batch = _Batch(first, count, shown, late, self._epoch)
        if self._stream is None:
            batch.window = np.concatenate([self._history, known])
            self._place(known[:own])
        else:
            start = frame_start(first, self._speech.per_frame)
            sums = self._window_sums(known, first, count + self.lookahead_frames)
            batch.gain = self._gate.gain(sums, self.driver.silence_gate_dbfs)
            self._synced_stream(first).offer(start, known[:queued])
            batch.job = self._stream.plan(range(first, first + count))
            for entry in sums[:count]:  # the batch's frames (known's first `own` samples) join the gate's context
                self._gate.push(entry)
        return batch

    def _window_sums(self, known: np.ndarray, first: int, count: int) -> list[tuple[int, float, float]]:
        """(samples, sum, sum of squares) of each of the `count` frames from `first` whose speech-rate samples
        `known` holds, in order."""
        per_frame = self._speech.per_frame
        edges = [frame_start(index, per_frame) for index in range(first, first + count + 1)]
        spans = [hi - lo for lo, hi in zip(edges, edges[1:], strict=False)]
        width = max(spans)
        if width * count == known.shape[0]:  # frames of one length: the window itself, a frame a row
            frames = known.reshape(count, width)
        else:
            frames = np.zeros((count, width), np.float32)
            for row, (lo, hi) in enumerate(zip(edges, edges[1:], strict=False)):
                frames[row, :hi - lo] = known[lo - edges[0]:hi - edges[0]]
        totals, squares = frame_sums(frames)
        return list(zip(spans, totals.tolist(), squares.tolist(), strict=True))

    def _synced_stream(self, index: int) -> TranslatorStream:
        """Under the lock: the stream, restarted at frame `index` if an interrupt() cleared the context since."""
        if self._stream_epoch != self._epoch:
            self._stream.reset(frame_start(index, self._speech.per_frame))
            self._stream_epoch = self._epoch
        return self._stream

    def _place(self, speech: np.ndarray) -> None:
        """Windowed: the next frames' shown speech-rate samples join the translator's past context (a sliding
        window)."""
        if self._history.shape[0]:
            self._history = np.concatenate([self._history, speech])[-self._history.shape[0]:]

    def _place_idle(self, index: int) -> None:
        """Idle frame `index`'s silence joins the translator's past context: zeros in the sliding window; streaming,
        the gate counts them without making them and the stream idles over the gap."""
        span = self._speech.span(index, index + 1)
        if self._stream is None:
            self._place(np.zeros(span, np.float32))
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

    def _render(self, plan: FramePlan) -> LiveFrame:
        """The plan's drive (idle motion added) rendered."""
        index, params, speaking = self.frame_params(plan)
        drive = self.drive_of(params, index)
        image = None
        if self.output is not None:
            image = self.head.render(drive, self.output,
                                     reference_frame=index if self.head.compositor is not None else None)
        self.count_frame(plan)
        return LiveFrame(index, index / self.fps, image, plan.out_audio, self.sample_rate, speaking, drive)

    def frame_params(self, plan: FramePlan) -> tuple[int, np.ndarray, bool]:
        """The next frame's index, parameters (the plan's, or the ease to idle; a blink added) and whether it speaks,
        the ease's bookkeeping done: all of making a frame but its drive and `count_frame`."""
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
        return index, params, speaking

    def count_frame(self, plan: FramePlan) -> None:
        """The frame of `plan` made: counted, and the next one's index is next."""
        stats = self.stats
        speaking = plan.params is not None
        stats.frames += 1
        stats.speaking_frames += speaking
        stats.idle_frames += not speaking
        stats.late_frames += plan.late
        stats.underruns += plan.underrun
        self._next_index += 1

    def pose(self, index: int):
        """Frame `index`'s head pose: the idle sway, or the driver's (its pose track's)."""
        return self._idle.sway(index) if self._sway else self.driver.head_pose(index)

    def drive_of(self, params: np.ndarray, index: int) -> FrameDrive | BlendshapeDrive:
        return self.driver.drive_from_params(self.driver.clamp_params(params), self.pose(index))


__all__ = ["FramePlan", "GATE_REBUILD", "IdleMotion", "LiveFrame", "LiveSession", "LiveStats", "SteadyState",
           "SteadyTake", "frame_sums", "session_stream_spec"]
