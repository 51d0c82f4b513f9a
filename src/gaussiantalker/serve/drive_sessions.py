"""Client-render sessions: a live session on the shared Driver (drives, no image), its frames made by a DrivePool
thread when due and sent to the page as drive messages (WebRTC) or frame packets (WebSocket), through an outgoing
queue whose bound closes a page that does not read (docs/serve.md, docs/live.md "Live, rendered by the client")."""

from __future__ import annotations

import asyncio
import json
import threading
import time
from collections import deque
from collections.abc import Callable

import numpy as np

from gaussiantalker.runtime import LiveSession
from gaussiantalker.runtime.live_rows import make_rows
from gaussiantalker.runtime.live_steady import SteadyFrame, SteadyFrames
from gaussiantalker.runtime.translate_stream import StreamJob, run_stream_jobs

from .limits import ServeLimits, TokenBucket
from .metrics import ServeMetrics
from .voices import PacedVoice
from .wire import DRIVE_HEADER, PACKET_HEADER, encode_drive, encode_frame_packet, frame_packets

WEBRTC_AUDIO_RATE = 48000  # WebRTC's Opus clock


# Sessions' frame clocks start on multiples of half a frame period, so that the sessions of a pool thread fall due
# in two groups a frame and their streaming translator calls run together (docs/live.md, "Sessions batched
# together"); a session's first frame waits at most half a frame for it. One group a frame made the last session of
# each tick wait for all the others; a 20 ms grid under 30 fps frames made five groups of small calls.
def clock_grid_s(fps: float) -> float:
    """The live server's clock grid for a driver of `fps` frames a second: half a frame period."""
    return 0.5 / float(fps)


class DriveSession:
    """One page's client-render session on `driver` (shared by every session). transport "webrtc": each frame's
    drive goes to the page's "drives" data channel, its audio to `audio` (a FrameTrack the app attaches); "ws":
    each frame goes out as one frame packet through `outbox`, which `write_to` drains, JSON messages the same way
    and in order. `on_error(error)` is called on the event loop when making a frame raised; `on_overflow()` when
    the page has not read `limits.outbox_frames` queued messages (it is then closed with 1008)."""

    RECORDED = 1500  # the last drives kept for /drives
    THREAD_NAME = "gt-live-driver"

    def __init__(self, driver, lookahead_ms: float, loop: asyncio.AbstractEventLoop, pool: DrivePool,
                 limits: ServeLimits, metrics: ServeMetrics, *, on_error: Callable[[BaseException], None],
                 on_overflow: Callable[[], None], transport: str = "webrtc", batch_frames: int = 1,
                 context_ms: float = 1000.0, streaming: bool | None = None,
                 stream_delay_ms: float | None = None) -> None:
        self.driver, self._loop, self._on_error, self._on_overflow = driver, loop, on_error, on_overflow
        self.transport, self._limits, self._metrics = transport, limits, metrics
        # the labelled series each frame counts in, looked up once
        self._frame_seconds = metrics.frame_seconds.labels(mode="client-render")
        self._frames = metrics.frames.labels(mode="client-render")
        self.sample_rate = WEBRTC_AUDIO_RATE if transport == "webrtc" else driver.sample_rate
        self.live = LiveSession(driver, lookahead_ms=lookahead_ms, audio_rate=self.sample_rate, output=None,
                                min_batch_frames=batch_frames, context_ms=context_ms,
                                max_queued_s=limits.max_queued_s, streaming=streaming,
                                clock_grid_s=clock_grid_s(driver.fps), stream_delay_ms=stream_delay_ms)
        self.audio = None  # webrtc: the FrameTrack its audio goes to
        self.outbox: asyncio.Queue = asyncio.Queue()  # ws: frame packets (bytes) and JSON (str); None ends write_to
        self.closed = asyncio.Event()
        self.error: BaseException | None = None
        self.voice: PacedVoice | None = None  # what the server speaks (`speak`), cancelled by a barge-in
        self.stats: dict = {"frames": 0, "speaking_frames": 0, "sent": 0, "unsent": 0}
        self.recorded: deque[bytes] = deque(maxlen=self.RECORDED)
        self.start_time = 0.0  # time.monotonic() of frame 0's due time: the session's pts 0 on the wall clock
        self.done = threading.Event()  # set once its pool thread has let go of it: no frame is made after
        self.overflowed = False
        self.interrupts = TokenBucket(limits.interrupts_per_s, limits.interrupt_burst)  # barge-ins, by any route
        self._pool, self._last_epoch, self._late_counted = pool, 0, 0
        self._drives = None
        self.control = None  # webrtc: the page's control channel (webrtc.ControlChannel)

    def start(self) -> None:
        """Hand the session to its pool: frame 0 is due now."""
        self.start_time = time.monotonic()
        self._pool.add(self)

    def speak(self, audio, rate: int, chunk_s: float) -> None:
        """Speak `audio` (mono float, at `rate`) as a voice made as it is spoken, from now on in `chunk_s` chunks,
        each fed to the session by its pool thread once its time has come (`PacedVoice`)."""
        if self.voice is not None:
            self.voice.cancel()
        self.voice = PacedVoice(self.live, audio, rate, chunk_s, time.monotonic())

    def attach(self, channel) -> None:
        """webrtc: the page's "drives" or "control" data channel."""
        if channel.label == "drives":
            self._drives = channel
        elif channel.label == "control" and self.control is not None:
            self.control.attach(channel)

    def tell(self, message: dict) -> None:
        """Send the page `message` (JSON): on its WebSocket in order with the frames, or its control channel."""
        if self.transport == "ws":
            self._enqueue(json.dumps(message))
        elif self.control is not None:
            self.control.tell(message)

    def interrupt(self) -> dict:
        """Barge-in (on the event loop): the voice stops, the session drops what it queued and eases to idle."""
        if self.voice is not None:
            self.voice.cancel()
        self.live.interrupt()
        return {"epoch": self.live.stats.interrupts}

    def _enqueue(self, item) -> None:
        """ws: queue `item` for the page; a page that has let outbox_frames pile up is not reading: it is closed."""
        if self.overflowed:
            return
        if self.outbox.qsize() >= self._limits.outbox_frames:
            self.overflowed = True
            self._on_overflow()
            return
        self.outbox.put_nowait(item)

    async def write_to(self, socket) -> None:
        """ws: send the outbox to the page until None (the session ended) or the socket closes."""
        while (item := await self.outbox.get()) is not None:
            try:
                if isinstance(item, bytes):
                    await socket.send_bytes(item)
                else:
                    await socket.send_str(item)
            except ConnectionError:  # the page left; its handler closes the session
                return

    def feed(self) -> bool:
        """On its pool thread, first in a tick: the server's voice's chunks whose time has come, pushed. False when
        the session failed (next_plan() then reports it)."""
        if self.error is not None:
            return False
        try:
            self._feed_voice()
        except Exception as exc:
            self._failed(exc)
            return False
        return True

    def prepare(self) -> StreamJob | None:
        """On its pool thread, after feed(): the streaming translator call its frame due now needs, for the pool to
        run with the other sessions' (None: none needed, or the session failed, which next_plan() then reports)."""
        if self.error is not None:
            return None
        try:
            return self.live.stream_job()
        except Exception as exc:
            self._failed(exc)
            return None

    def next_plan(self, steady: SteadyFrames, planned: SteadyFrame | None) -> tuple | bool:
        """On its pool thread, after the tick's translator calls: (plan, due time, epoch on the wire) of its frame
        due now, a steady one's from `steady` (`SteadyFrames.take`), any other's from its session's step
        (`LiveSession.next_plan`); True when none is due, False once the session has ended (closed, or failed:
        on_error then hears why on the event loop)."""
        if self.error is not None:
            return False
        try:
            if planned is not None:  # a steady frame took its audio when planned: the next tick's feed pushes the rest
                taken = steady.take(planned)
                if taken is not None:
                    return (*taken, planned.interrupts)
            self._feed_voice()  # what came while the pool ran the translator calls (a timer would have pushed it)
            # The epoch is read before the frame is planned: a frame planned after an interrupt() has its epoch,
            # one planned before keeps the older one (interrupt() counts itself once it has cleared the queues).
            epoch = self.live.stats.interrupts
            taken = self.live.next_plan()
            if taken is None:
                return not self.live.finished
            return (*taken, epoch)
        except Exception as exc:
            self._failed(exc)
            return False

    def send(self, plan, due: float, epoch: int) -> bool:
        """On its pool thread: make the planned frame alone and send it (a WebRTC session's, or a drive made one at a
        time). False when making it failed."""
        try:
            began = time.perf_counter()
            frame = self.live.make_frame(plan)
            self.live.keep_pace(due)
            self._frame_seconds.observe(time.perf_counter() - began)
            self._emit(frame, epoch)
        except Exception as exc:
            self._failed(exc)
            return False
        return True

    def _feed_voice(self) -> None:
        """On its pool thread: the server's voice's chunks whose time has come, pushed (`PacedVoice`)."""
        voice = self.voice
        if voice is not None and not voice.ended:
            voice.feed(time.monotonic())

    def _failed(self, exc: BaseException) -> None:
        self.error = exc
        try:
            self._loop.call_soon_threadsafe(self._on_error, exc)
        except RuntimeError:  # the event loop has closed
            pass

    def _emit(self, frame, epoch: int) -> None:
        message = encode_drive(frame.index, frame.pts, frame.drive, frame.speaking, epoch)
        sent = message if self.transport == "webrtc" else encode_frame_packet(message, frame.audio)
        self._sent(frame.index, frame.speaking, message, sent, epoch)
        if self.audio is not None:
            self.audio.put(frame)

    def _sent(self, index: int, speaking: bool, message: bytes, sent: bytes, epoch: int) -> None:
        """A frame's drive `message` made and `sent` (its packet, or the message itself) handed to the event loop;
        its stats and metrics counted."""
        self.stats["frames"] += 1
        self.stats["speaking_frames"] += speaking
        self._frames.inc()
        late = self.live.stats.late_frames
        if late > self._late_counted:
            self._metrics.late_frames.labels(mode="client-render").inc(late - self._late_counted)
            self._late_counted = late
        self.recorded.append(message)
        told = None
        if epoch != self._last_epoch:
            self._last_epoch = epoch
            told = {"interrupt": {"epoch": epoch, "index": index}}
        batch = getattr(_tick, "deliveries", None)
        if batch is not None:  # a pool thread hands the event loop a tick's frames at once (_DriveWorker.run)
            batch.append((self, sent, told))
        else:
            _post([(self, sent, told)])

    def _deliver(self, message: bytes, told: dict | None) -> None:
        """On the event loop: a frame's message, and the new epoch's news with its first frame."""
        if self.transport == "ws":
            self._enqueue(message)
            self.stats["sent" if not self.overflowed else "unsent"] += 1
        else:
            channel = self._drives
            if channel is not None and channel.readyState == "open":
                channel.send(message)
                self.stats["sent"] += 1
            else:
                self.stats["unsent"] += 1
        if told is not None:
            self.tell(told)

    def ended(self) -> None:
        """On its pool thread, when it lets go of the session: the audio track ends; stop() may return."""
        if self.audio is not None:
            self.audio.put(None)
        self.done.set()

    def stop(self, timeout: float = 10.0) -> None:
        """End the session and wait for its pool thread to let go of it (blocking: run it in an executor)."""
        self.live.close()
        if self.start_time:
            self._pool.wake()
            self.done.wait(timeout)
        try:
            self._loop.call_soon_threadsafe(self.outbox.put_nowait, None)
        except RuntimeError:  # the event loop has closed
            pass

    def summary(self) -> dict:
        return {"mode": "client-render", "transport": self.transport, **self.stats, "fps": self.driver.fps,
                "late_frames": self.live.stats.late_frames, "deferrals": self.live.stats.deferrals,
                "interrupts": self.live.stats.interrupts}


# A pool thread's frames of one tick, delivered to the event loop in one call: a wake-up of the loop per frame (a
# self-pipe write and a callback each) was a large share of the server's CPU at a hundred sessions.
_tick = threading.local()


def _deliver_all(deliveries: list) -> None:
    """On the event loop: a tick's frames, each to its session, in order."""
    for session, message, told in deliveries:
        session._deliver(message, told)


def _post(deliveries: list) -> None:
    """Hand `deliveries` to their sessions' event loop(s); a closed loop closes its sessions."""
    by_loop: dict[int, tuple] = {}
    for item in deliveries:
        by_loop.setdefault(id(item[0]._loop), (item[0]._loop, []))[1].append(item)
    for loop, items in by_loop.values():
        try:
            loop.call_soon_threadsafe(_deliver_all, items)
        except RuntimeError:  # the event loop has closed: nobody reads these sessions any more
            for session, _, _ in items:
                session.live.close()


class DrivePool:
    """A few threads make the frames of every session (each session on the least busy one), instead of a thread
    per session: fifty threads each waking 25 times a second to run a little Python starve the event loop of the
    GIL (docs/live.md, "Load"). A thread starts with its first session and ends when it has none left."""

    def __init__(self, threads: int) -> None:
        self.threads = max(1, threads)
        self._lock = threading.Lock()
        self._workers: list[_DriveWorker] = []

    def add(self, session: DriveSession) -> None:
        with self._lock:
            self._workers = [w for w in self._workers if not w.ended]
            if len(self._workers) < self.threads:
                worker = _DriveWorker(self._lock)
                self._workers.append(worker)
                worker.sessions.append(session)
                worker.start()
                return
            worker = min(self._workers, key=lambda w: len(w.sessions))
            worker.sessions.append(session)
            worker.wake.set()

    def wake(self) -> None:
        """Have every thread look at its sessions now (one was closed)."""
        with self._lock:
            for worker in self._workers:
                worker.wake.set()


class _DriveWorker(threading.Thread):
    """One DrivePool thread: advances its sessions, then sleeps until the next frame is due or it is woken."""

    def __init__(self, pool_lock: threading.Lock) -> None:
        super().__init__(name=DriveSession.THREAD_NAME, daemon=True)
        self.sessions: list[DriveSession] = []  # changed under pool_lock
        self.wake = threading.Event()
        self.ended = False
        self._pool_lock = pool_lock
        self._steady = SteadyFrames()  # its sessions' steady frames, made together

    def run(self) -> None:
        while True:
            began = time.thread_time()  # the tick's CPU, counted by part (`gt_serve_pool_cpu_seconds`)
            with self._pool_lock:
                # the sessions with a frame due now (the others' calls would return at once, at a lock and a clock
                # read each: half the sessions a pass on the half-frame grid); a failed one, to be let go of
                sessions = [session for session in self.sessions
                            if session.error is not None or session.live.due <= time.monotonic()]
            planned, translator_s = _translate_together(sessions, self._steady)
            _tick.deliveries, ended, due = [], [], []
            try:
                for session, steady in zip(sessions, planned, strict=True):
                    # One frame a session a pass: a session behind makes its next frame in the next pass, its
                    # translator call stacked with the others' (made alone in step() before, one call each).
                    got = session.next_plan(self._steady, steady)
                    if got is False:
                        ended.append(session)
                    elif got is not True:
                        due.append((session, *got))
                ended += _send_together(due)
                for session in ended:
                    with self._pool_lock:
                        self.sessions.remove(session)
                    self._steady.forget(session.live)
            finally:
                deliveries, _tick.deliveries = _tick.deliveries, None
                if deliveries:
                    _post(deliveries)
                for session in ended:  # after its last frames went to the loop: stop() may end its outbox now
                    session.ended()
            if sessions:
                pool_cpu = sessions[0]._metrics.pool_cpu
                pool_cpu.labels(part="translator").inc(translator_s)
                pool_cpu.labels(part="frames").inc(max(0.0, time.thread_time() - began - translator_s))
            with self._pool_lock:
                if not self.sessions:
                    self.ended = True
                    return
                due = min(session.live.due for session in self.sessions)
                self.wake.clear()
            self.wake.wait(max(0.0, due - time.monotonic()))


def _send_together(due: list[tuple]) -> list[DriveSession]:
    """Make and send the frames of `due` ((session, plan, due time, epoch) each): the WebSocket sessions' of each
    driver made together (`make_rows`) and their packets written as one array (`frame_packets`), the others' one at a
    time. Returns the sessions that failed."""
    failed, together = [], {}
    for item in due:
        session = item[0]
        if session.transport == "ws" and session.audio is None:
            together.setdefault(id(session.driver), []).append(item)
        elif not session.send(*item[1:]):
            failed.append(session)
    for items in together.values():
        began = time.perf_counter()
        rows = make_rows([item[0].live for item in items], [item[1] for item in items])
        values = rows.values()
        for k, error in rows.errors.items():
            items[k][0]._failed(error)
            failed.append(items[k][0])
        by_length: dict[int, list[int]] = {}  # a 30 fps rig's frames carry 533 or 534 samples at 16 kHz
        for k, audio in enumerate(rows.audio):
            if k in rows.errors:
                continue
            if values is None:  # drives one at a time (or one failed its check, which its frame names)
                try:
                    frame = rows.frame(k)
                    items[k][0].live.keep_pace(items[k][2])
                    items[k][0]._emit(frame, items[k][3])
                except Exception as exc:
                    items[k][0]._failed(exc)
                    failed.append(items[k][0])
            else:
                by_length.setdefault(audio.shape[0], []).append(k)
        for group in by_length.values():
            packets = frame_packets(items[0][0].driver.rig, rows.indices[group], rows.pts[group], values[group],
                                    rows.speaking[group], np.array([items[k][3] for k in group], np.int64),
                                    np.stack([rows.audio[k] for k in group]))
            message_end = PACKET_HEADER.size + DRIVE_HEADER.size + 4 * values.shape[1]
            for k, packet in zip(group, packets, strict=True):
                session, _, due_time, epoch = items[k]
                session.live.keep_pace(due_time)
                session._sent(int(rows.indices[k]), bool(rows.speaking[k]),
                              packet[PACKET_HEADER.size:message_end].tobytes(), packet.tobytes(), epoch)
        spent = (time.perf_counter() - began) / len(items)
        for item in items:
            item[0]._frame_seconds.observe(spent)
    return failed


def _translate_together(sessions: list[DriveSession], steady: SteadyFrames) -> tuple[list, float]:
    """One streaming translator call for every session with a frame due now (per driver): the steady frames planned
    together (`SteadyFrames`), the others' calls by each session's stream_job(), whose step() then finds its rows
    made. A failed call leaves each job to run alone in its session, which reports its error. Returns each session's
    planned steady frame (None: its own) and the CPU seconds this thread spent in the calls."""
    spent = 0.0
    fed = [session for session in sessions if session.feed()]
    planned_of = dict(zip(map(id, fed), steady.plan([session.live for session in fed], time.monotonic()),
                          strict=True))
    planned = [planned_of.get(id(session)) for session in sessions]
    by_driver: dict[int, tuple[object, list[StreamJob]]] = {}
    for session, mine in zip(sessions, planned, strict=True):
        job = session.prepare() if mine is None else mine.job
        if job is not None:
            by_driver.setdefault(id(session.driver), (session.driver, []))[1].append(job)
    for driver, jobs in by_driver.values():
        began = time.thread_time()
        try:
            calls = run_stream_jobs(jobs, driver.run_stream, driver.stream_rows)
        except Exception:  # each session runs its own call again and fails on its own
            calls = None
            for job in jobs:
                job.rows = job.state = job.state_row = None
        spent += time.thread_time() - began
        if calls is not None:
            metrics = sessions[0]._metrics
            for count in calls:
                metrics.translator_batch.observe(count)
            committed = sum(job.keep for job in jobs)
            metrics.translator_rows.labels(kind="committed").inc(committed)
            metrics.translator_rows.labels(kind="provisional").inc(sum(job.audio.shape[0] for job in jobs) - committed)
    return planned, spent


__all__ = ["DrivePool", "DriveSession", "WEBRTC_AUDIO_RATE", "clock_grid_s"]
