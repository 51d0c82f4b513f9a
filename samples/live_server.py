"""Live sample: `python samples/live_server.py speaker.gtb [--port 8080]`, then open http://127.0.0.1:8080/.

Streams the talking head to a browser over WebRTC (aiortc; `pip install ".[live]"`). The page chooses what the
head says: a sound file on the server (`--audio`, default the sample speech), the browser's microphone (the head
mouths what it hears and sends it back in sync), or text spoken by `espeak-ng` when it is installed. Each
connection gets its own live session (docs/live.md) on a render thread of its own, which owns its TalkingHead and
its GL context; frames go to the connection's video and audio tracks with the session's clock as their
timestamps, so picture and voice stay in sync. `GET /stats` reports each session's counters, `GET /health` the
open sessions and render threads (the browser tests read both).

A browser that leaves ends its session at once: the page posts `/close` with its session id when it stops or
unloads. One that vanishes without a word (a crash, a dropped network) is noticed by WebRTC's consent checks,
which give up after about 30 s; the session then ends the same way. Either way the render thread stops and the
voice source stops pushing.

A session that fails is logged once and the page is told: a head that cannot start answers the offer with an error
(HTTP 500 and its message); a frame that raises mid-session ends the session, and the error goes to the page as
`{"error": ...}` on its "control" data channel, after which the page leaves (or the server closes the session
ERROR_GRACE_S later).

`--client-render`: the browser renders the head itself (samples/web/live.html with the web player, docs/web.md).
One Driver (`open_driver`: the bundle's graphs, no splatter, no GL) serves every session, and a DrivePool makes
their frames. Each session runs over one WebSocket (`GET /live`: a frame packet per frame, `encode_frame_packet`,
the drive and its audio together; the page's barge-ins and microphone the other way) or over WebRTC (`POST /offer`:
each drive on an unordered "drives" data channel in the binary format of `encode_drive`, stamped with its pts,
beside an audio track); docs/live.md, "Live, rendered by the client". `GET /bundle` serves the bundle to the page,
`POST /interrupt` (the session id) is a barge-in, `--batch-frames` trades each utterance's start for fewer
translator calls.
"""

from __future__ import annotations

import asyncio
import fractions
import json
import logging
import math
import os
import shutil
import struct
import subprocess
import threading
import time
import uuid
from collections.abc import Callable
from pathlib import Path

import numpy as np
import typer

from gaussiantalker.runtime import GaussianTalkerError, LiveError, LiveSession, TalkingHead, open_driver
from gaussiantalker.sdk.audio import load_audio, to_pcm16

try:
    from aiohttp import web
    from aiortc import MediaStreamTrack, RTCPeerConnection, RTCSessionDescription
    from aiortc.mediastreams import MediaStreamError
    from av import AudioFrame, VideoFrame
except ImportError as exc:  # the runtime alone does not install them
    raise SystemExit(f"live_server.py needs aiortc and aiohttp: pip install 'gaussiantalker-sdk[live]' ({exc})") \
        from None

PAGE = Path(__file__).with_name("live_page.html")
SPEECH = Path(__file__).with_name("demo_speech.wav")
AUDIO_RATE = 48000  # WebRTC's Opus clock
CHUNK_S = 0.02  # what a voice source pushes at a time
QUEUE_FRAMES = 50  # frames waiting for a track, at most (2 s): a reader that stalls loses the oldest
MAX_THREADS = 1 << 16  # a DrivePool of this many threads gives each session one of its own
START_TIMEOUT_S = 30.0  # a WebSocket page's start message must come this soon after it connects
MAX_MIC_MESSAGE_BYTES = 1 << 20  # a page's microphone message, at most (5 s at 96 kHz): larger ones close the socket
# A session whose rendering failed waits this long at most for its page to hear why and leave, then closes: long
# enough for a page whose first frame failed to finish connecting and open its control channel.
ERROR_GRACE_S = 10.0
log = logging.getLogger("live_server")
WEB_PAGE = Path(__file__).with_name("web") / "live.html"
WEB_ROOT = Path(__file__).resolve().parents[1] / "web"

# -- the drive wire format (client-render mode) ----------------------------------------------------------------
# One data-channel message per frame, little-endian: a 28-byte header, then `count` float32 values.
#   0  4s   magic b"GTLD"
#   4  u8   version (1)
#   5  u8   rig: 0 FLAME (values: expression[split], flame_pose[15], head_translation[3]),
#                1 ARKit (values: blendshapes[split] in ARKIT_BLENDSHAPES order, head_rotation[3], head_translation[3])
#   6  u8   flags: bit 0 speaking
#   7  u8   dtype: 0 float32 (the only one written)
#   8  u32  frame index
#   12 u32  epoch: barge-ins so far; drives of an older epoch at or past the first index of a newer one are stale
#   16 f64  pts (seconds on the session's audio clock, index / fps)
#   24 u16  count of values
#   26 u16  split: where the expression (FLAME) or the weights (ARKit) end; count - split is the pose (18 or 6)
# The small demo speaker (20 expression coefficients): 28 + 38 * 4 = 180 bytes a frame, 4.5 kB/s at 25 fps.
DRIVE_MAGIC = b"GTLD"
DRIVE_VERSION = 1
DRIVE_HEADER = struct.Struct("<4sBBBBIIdHH")
POSE_VALUES = {0: 18, 1: 6}  # values after `split`: FLAME flame_pose + translation, ARKit rotation + translation


class DriveFormatError(ValueError):
    """A drive message that is not one: truncated, lying about its count, or of an unknown kind."""


def encode_drive(index: int, pts: float, drive, speaking: bool, epoch: int = 0) -> bytes:
    """One frame's drive (a FrameDrive or BlendshapeDrive) as a drive message."""
    if hasattr(drive, "blendshapes"):
        rig, parts = 1, (drive.blendshapes, drive.head_rotation, drive.head_translation)
    else:
        rig, parts = 0, (drive.expression, drive.flame_pose, drive.head_translation)
    values = np.concatenate(parts).astype("<f4")
    header = DRIVE_HEADER.pack(DRIVE_MAGIC, DRIVE_VERSION, rig, int(bool(speaking)), 0, index, epoch, float(pts),
                               values.size, parts[0].size)
    return header + values.tobytes()


def decode_drive(message: bytes) -> dict:
    """A drive message -> {index, pts, epoch, speaking, rig ("flame"/"arkit"), values float32 [count], split};
    DriveFormatError naming what is wrong. Every count is checked against the bytes present."""
    data = bytes(message)
    if len(data) < DRIVE_HEADER.size:
        raise DriveFormatError(f"drive message truncated: {len(data)} bytes, the header alone is {DRIVE_HEADER.size}")
    magic, version, rig, flags, dtype, index, epoch, pts, count, split = DRIVE_HEADER.unpack_from(data)
    if magic != DRIVE_MAGIC:
        raise DriveFormatError(f"not a drive message (magic {magic!r}, expected {DRIVE_MAGIC!r})")
    if version != DRIVE_VERSION or dtype != 0:
        raise DriveFormatError(f"drive message version {version} dtype {dtype}: only version {DRIVE_VERSION} "
                               "float32 is read")
    if rig not in POSE_VALUES:
        raise DriveFormatError(f"drive message has unknown rig code {rig}")
    body = len(data) - DRIVE_HEADER.size
    if count * 4 != body:
        raise DriveFormatError(f"drive message claims {count} values ({count * 4} bytes) but carries {body} bytes")
    if split + POSE_VALUES[rig] != count:
        raise DriveFormatError(f"drive message splits {count} values at {split}: the pose needs {POSE_VALUES[rig]}")
    if not math.isfinite(pts) or pts < 0:
        raise DriveFormatError(f"drive message pts {pts} is not a finite time >= 0")
    values = np.frombuffer(data, "<f4", count, DRIVE_HEADER.size).astype(np.float32)
    if not np.isfinite(values).all():
        raise DriveFormatError("drive message has non-finite values")
    return {"index": index, "pts": pts, "epoch": epoch, "speaking": bool(flags & 1),
            "rig": "arkit" if rig else "flame", "values": values, "split": split}


# -- the frame packet (client-render over a WebSocket) ---------------------------------------------------------
# One binary WebSocket message per frame, little-endian: a 12-byte header, the frame's drive message, its audio.
#   0  4s   magic b"GTLF"
#   4  u8   version (1)
#   5  u8   audio dtype: 0 int16 PCM, mono, at the session's sample_rate (the only one written)
#   6  u16  reserved (0)
#   8  u32  drive_bytes: the length of the drive message that follows (encode_drive)
#   12      the drive message, then the frame's audio (what is left: whole int16 samples, zeros while idle)
# The small demo speaker at 25 fps and 16 kHz: 12 + 180 + 1280 bytes a frame, 37 kB/s.
PACKET_MAGIC = b"GTLF"
PACKET_VERSION = 1
PACKET_HEADER = struct.Struct("<4sBBHI")


def encode_frame_packet(drive_message: bytes, audio: np.ndarray) -> bytes:
    """A frame packet: a drive message and the frame's audio (float in [-1, 1] or int16), as int16 PCM."""
    if audio.dtype != np.int16:
        audio = to_pcm16(audio)
    return PACKET_HEADER.pack(PACKET_MAGIC, PACKET_VERSION, 0, 0, len(drive_message)) + drive_message \
        + audio.astype("<i2").tobytes()


def decode_frame_packet(message: bytes) -> dict:
    """A frame packet -> {"drive": decode_drive's dict, "audio": int16 samples}; DriveFormatError naming what is
    wrong. drive_bytes is checked against the bytes present before anything is read."""
    data = bytes(message)
    if len(data) < PACKET_HEADER.size:
        raise DriveFormatError(f"frame packet truncated: {len(data)} bytes, the header alone is {PACKET_HEADER.size}")
    magic, version, dtype, _, drive_bytes = PACKET_HEADER.unpack_from(data)
    if magic != PACKET_MAGIC:
        raise DriveFormatError("not a frame packet (bad magic)")
    if version != PACKET_VERSION or dtype != 0:
        raise DriveFormatError(f"frame packet version {version} audio dtype {dtype}: only version {PACKET_VERSION} "
                               "int16 is read")
    rest = len(data) - PACKET_HEADER.size
    if drive_bytes > rest:
        raise DriveFormatError(f"frame packet claims a {drive_bytes}-byte drive but carries {rest} bytes after its "
                               "header")
    audio_bytes = rest - drive_bytes
    if audio_bytes % 2:
        raise DriveFormatError(f"frame packet audio is {audio_bytes} bytes: not whole int16 samples")
    drive = decode_drive(data[PACKET_HEADER.size:PACKET_HEADER.size + drive_bytes])
    audio = np.frombuffer(data, "<i2", audio_bytes // 2, PACKET_HEADER.size + drive_bytes).astype(np.int16)
    return {"drive": drive, "audio": audio}


class FrameTrack(MediaStreamTrack):
    """A video or audio track fed by the render thread with the live session's frames (`put` from any thread)."""

    def __init__(self, kind: str, loop: asyncio.AbstractEventLoop) -> None:
        super().__init__()
        self.kind, self._loop, self.fps = kind, loop, 25
        self._queue: asyncio.Queue = asyncio.Queue(QUEUE_FRAMES)

    def put(self, frame) -> None:
        try:
            self._loop.call_soon_threadsafe(self._put, frame)
        except RuntimeError:  # the event loop has closed (the server shut down): nobody reads the track any more
            pass

    def _put(self, frame) -> None:
        if self._queue.full():
            self._queue.get_nowait()
        self._queue.put_nowait(frame)

    async def recv(self):
        frame = await self._queue.get()
        if frame is None:
            self.stop()
            raise MediaStreamError
        if self.kind == "video":
            out = VideoFrame.from_ndarray(frame.image, format="rgb24")
            out.pts, out.time_base = frame.index * 90000 // self.fps, fractions.Fraction(1, 90000)
            return out
        pcm = to_pcm16(frame.audio)[None]
        out = AudioFrame.from_ndarray(pcm, format="s16", layout="mono")
        out.sample_rate = AUDIO_RATE
        out.pts, out.time_base = round(frame.index * AUDIO_RATE / self.fps), fractions.Fraction(1, AUDIO_RATE)
        return out


class ControlChannel:
    """The page's "control" data channel: JSON messages for the page, kept until the channel is open."""

    def __init__(self) -> None:
        self._channel = None
        self._outbox: list[str] = []

    def attach(self, channel) -> None:
        """The channel the page opened: queued messages go out on it once it is open."""
        self._channel = channel
        channel.on("open", self._send_outbox)
        self._send_outbox()

    def tell(self, message: dict) -> None:
        """Send the page `message` (JSON) now, or as soon as the channel opens."""
        self._outbox.append(json.dumps(message))
        self._send_outbox()

    def _send_outbox(self) -> None:
        if self._channel is not None and self._channel.readyState == "open":
            while self._outbox:
                self._channel.send(self._outbox.pop(0))


class Session:
    """One connection's live session on a render thread of its own, with its counters for /stats.
    `on_error(error)` is called on the event loop when a frame raises (the session has then ended)."""

    THREAD_NAME = "gt-live-render"

    def __init__(self, bundle: Path, size: int, lookahead_ms: float, renderer: str,
                 loop: asyncio.AbstractEventLoop, on_error: Callable[[BaseException], None] | None = None) -> None:
        self.ready = threading.Event()
        self.closed = asyncio.Event()  # set once the server has closed the session
        self.stats: dict = {"frames": 0, "speaking_frames": 0, "jaw": [], "level": []}
        self._args = (bundle, size, lookahead_ms, renderer)
        self._loop, self._on_error = loop, on_error
        self.live = self.head = None
        self.error: BaseException | None = None  # what ended the session, if it failed
        self._started = False  # the head and its live session were made: an error after it is a frame's
        self.video, self.audio = FrameTrack("video", loop), FrameTrack("audio", loop)
        self._control = ControlChannel()
        self._thread = threading.Thread(target=self._run, name=self.THREAD_NAME, daemon=True)

    def start(self) -> None:
        """Load the head on the render thread and start its session (blocks until it is ready); raises what the
        render thread raised if it could not."""
        self._thread.start()
        self.ready.wait()
        if not self._started:  # (a frame that raises right after the start is on_error's, not start()'s)
            raise self.error or RuntimeError("the render thread ended before its live session started")

    def attach(self, channel) -> None:
        """The page's control data channel: messages go out on it once it is open."""
        self._control.attach(channel)

    def tell(self, message: dict) -> None:
        """Send the page `message` (JSON) on its control channel, now or as soon as the channel opens."""
        self._control.tell(message)

    def stop(self, timeout: float = 10.0) -> None:
        """End the live session and wait for its render thread, so no frame is drawn after the server shuts down."""
        if self._thread.ident is None:  # never started
            return
        self.ready.wait(timeout)
        if self.live is not None:
            self.live.close()
        self._thread.join(timeout)

    def _run(self) -> None:
        """Load the head, then feed the tracks the session's frames. Whatever ends it (the session closed, the
        head failed to load, a frame raised), `ready` is set and the tracks get their end."""
        bundle, size, lookahead_ms, renderer = self._args
        try:
            with TalkingHead(bundle, resolution=(size, size), composite=False, renderer=renderer) as head, \
                    head.live(lookahead_ms=lookahead_ms, audio_rate=AUDIO_RATE) as live:
                self.head, self.live, self._started = head, live, True
                self.video.fps = self.audio.fps = head.fps
                self.ready.set()
                for frame in live.frames():
                    self.stats["frames"] += 1
                    self.stats["speaking_frames"] += frame.speaking
                    pose = getattr(frame.drive, "flame_pose", None)  # an ARKit speaker's jaw: its jawOpen weight
                    self.stats["jaw"].append(float(pose[6]) if pose is not None
                                             else float(frame.drive.blendshapes[24]))
                    self.stats["level"].append(float(np.sqrt(np.mean(frame.audio ** 2))))
                    del self.stats["jaw"][:-1500], self.stats["level"][:-1500]  # the last minute
                    self.video.put(frame)
                    self.audio.put(frame)
        except Exception as exc:  # start() raises it, or the event loop hears of it (on_error)
            self.error = exc
            if self._started and self._on_error is not None:
                try:
                    self._loop.call_soon_threadsafe(self._on_error, exc)
                except RuntimeError:  # the event loop has closed (the server shut down)
                    pass
        finally:
            self.ready.set()
            self.video.put(None)
            self.audio.put(None)

    def summary(self) -> dict:
        jaw, level = np.array(self.stats["jaw"]), np.array(self.stats["level"])
        speaking = level > 1e-4
        corr = float(np.corrcoef(jaw, level)[0, 1]) if jaw.size > 2 and jaw.std() > 0 and level.std() > 0 else 0.0
        return {"frames": self.stats["frames"], "speaking_frames": self.stats["speaking_frames"],
                "jaw_range_speaking": float(np.ptp(jaw[speaking])) if speaking.any() else 0.0,
                "jaw_loudness_r": corr, "fps": self.head.fps if self.head else None,
                "size": list(self.head.frame_size) if self.head else None,
                "late_frames": self.live.stats.late_frames if self.live else 0,
                "renderer": self.head.renderer if self.head else None}


class DriveSession:
    """Client-render mode: one connection's live session on `driver` (shared by every session: a Driver alone
    makes drives, no image, so no GL is used), its frames made by a DrivePool thread when due (`advance`); the last
    RECORDED drives are kept for /drives.

    transport "webrtc": each frame's drive goes to the page's "drives" data channel (encode_drive), its audio to
    the audio track (48 kHz Opus). transport "ws": each frame goes out as one frame packet (encode_frame_packet:
    the drive and its audio as int16 at the speaker's rate) on the page's WebSocket, through `outbox`, which
    `write_to` drains; JSON messages for the page go the same way, in order."""

    RECORDED = 1500

    def __init__(self, driver, lookahead_ms: float, loop: asyncio.AbstractEventLoop, pool: DrivePool,
                 on_error: Callable[[BaseException], None] | None = None, transport: str = "webrtc",
                 batch_frames: int = 1, context_ms: float = 1000.0) -> None:
        self.driver, self._loop, self._on_error, self.transport = driver, loop, on_error, transport
        self.sample_rate = AUDIO_RATE if transport == "webrtc" else driver.sample_rate
        self.live = LiveSession(driver, lookahead_ms=lookahead_ms, audio_rate=self.sample_rate, output=None,
                                min_batch_frames=batch_frames, context_ms=context_ms)
        self.audio = FrameTrack("audio", loop) if transport == "webrtc" else None
        if self.audio is not None:
            self.audio.fps = driver.fps
        # ws: frame packets (bytes) and JSON messages (str) for the page, in order; None ends write_to.
        self.outbox: asyncio.Queue = asyncio.Queue()
        self.closed = asyncio.Event()
        self.error: BaseException | None = None
        self.voice: asyncio.Task | None = None  # what the server speaks, cancelled by a barge-in
        self.stats: dict = {"frames": 0, "speaking_frames": 0, "sent": 0, "unsent": 0}
        self.recorded: list[bytes] = []
        self.start_time = 0.0  # time.monotonic() of frame 0's due time: the session's pts 0 on the wall clock
        self.done = threading.Event()  # set once its pool thread has let go of it: no frame is made after
        self._pool, self._last_epoch = pool, 0
        self._drives = None
        self._control = ControlChannel()

    def start(self) -> None:
        """Hand the session to its pool: frame 0 is due now."""
        self.start_time = time.monotonic()
        self._pool.add(self)

    def attach(self, channel) -> None:
        if channel.label == "drives":
            self._drives = channel
        elif channel.label == "control":
            self._control.attach(channel)

    def tell(self, message: dict) -> None:
        """Send the page `message` (JSON): on its control channel (now or once it opens), or its WebSocket."""
        if self.transport == "ws":
            self.outbox.put_nowait(json.dumps(message))
        else:
            self._control.tell(message)

    def interrupt(self) -> dict:
        """Barge-in (on the event loop): the voice stops, the session drops what it queued and eases to idle. The
        page hears the new epoch in every later drive, and on its control channel with the epoch's first frame
        once the driver has made it."""
        if self.voice is not None:
            self.voice.cancel()
        self.live.interrupt()
        return {"epoch": self.live.stats.interrupts}

    def _send(self, message: bytes) -> None:
        if self.transport == "ws":
            if self.outbox.qsize() >= QUEUE_FRAMES:  # a page that stopped reading: it loses frames, not memory
                self.stats["unsent"] += 1
                return
            self.outbox.put_nowait(message)
            self.stats["sent"] += 1
            return
        channel = self._drives
        if channel is not None and channel.readyState == "open":
            channel.send(message)
            self.stats["sent"] += 1
        else:
            self.stats["unsent"] += 1

    async def write_to(self, socket: web.WebSocketResponse) -> None:
        """ws: send the outbox to the page until None (the session ended) or the socket closes."""
        while (item := await self.outbox.get()) is not None:
            try:
                if isinstance(item, bytes):
                    await socket.send_bytes(item)
                else:
                    await socket.send_str(item)
            except ConnectionError:  # the page left; its handler closes the session
                return

    def advance(self) -> bool:
        """On its pool thread: make and send every frame due now. False once the session has ended (closed, or
        failed: on_error then hears why on the event loop)."""
        try:
            while True:
                # The epoch is read before the frame is made: a frame planned after an interrupt() has its epoch,
                # one planned before keeps the older one (interrupt() counts itself once it has cleared the queues).
                epoch = self.live.stats.interrupts
                frame = self.live.step()
                if frame is None:
                    return not self.live.finished
                self._emit(frame, epoch)
        except Exception as exc:
            self.error = exc
            if self._on_error is not None:
                try:
                    self._loop.call_soon_threadsafe(self._on_error, exc)
                except RuntimeError:  # the event loop has closed
                    pass
            return False

    def _emit(self, frame, epoch: int) -> None:
        message = encode_drive(frame.index, frame.pts, frame.drive, frame.speaking, epoch)
        self.stats["frames"] += 1
        self.stats["speaking_frames"] += frame.speaking
        self.recorded.append(message)
        del self.recorded[:-self.RECORDED]
        sent = message if self.audio is not None else encode_frame_packet(message, frame.audio)
        told = None
        if epoch != self._last_epoch:
            self._last_epoch = epoch
            told = {"interrupt": {"epoch": epoch, "index": frame.index}}
        try:
            self._loop.call_soon_threadsafe(self._deliver, sent, told)
        except RuntimeError:  # the event loop has closed: nobody reads the session any more
            self.live.close()
            return
        if self.audio is not None:
            self.audio.put(frame)

    def _deliver(self, message: bytes, told: dict | None) -> None:
        """On the event loop: a frame's message, and the new epoch's news with its first frame."""
        self._send(message)
        if told is not None:
            self.tell(told)

    def ended(self) -> None:
        """On its pool thread, when it lets go of the session: the audio track ends; stop() may return."""
        if self.audio is not None:
            self.audio.put(None)
        self.done.set()

    def stop(self, timeout: float = 10.0) -> None:
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
                "late_frames": self.live.stats.late_frames, "interrupts": self.live.stats.interrupts}


class DrivePool:
    """Client-render: a few threads make the frames of every session (each session on the least busy one), instead
    of a thread per session. Fifty threads each waking 25 times a second to run a little Python starve the event
    loop of the GIL, and it then sends drives and pushes voices late; a few threads do the same work in turns. A
    thread starts with its first session and ends when it has none left, so an idle server runs none."""

    THREAD_NAME = "gt-live-driver"

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
        super().__init__(name=DrivePool.THREAD_NAME, daemon=True)
        self.sessions: list[DriveSession] = []  # changed under pool_lock
        self.wake = threading.Event()
        self.ended = False
        self._pool_lock = pool_lock

    def run(self) -> None:
        while True:
            with self._pool_lock:
                sessions = list(self.sessions)
            for session in sessions:
                if not session.advance():
                    with self._pool_lock:
                        self.sessions.remove(session)
                    session.ended()
            with self._pool_lock:
                if not self.sessions:
                    self.ended = True
                    return
                due = min(session.live.due for session in self.sessions)
                self.wake.clear()
            self.wake.wait(max(0.0, due - time.monotonic()))


async def push_real_time(live, audio: np.ndarray, rate: int, chunk_s: float = CHUNK_S) -> None:
    """Push `audio` in `chunk_s` chunks at real time, as a voice that speaks as it is made, then flush. Stops
    quietly when the session closes (the browser left)."""
    step = int(rate * chunk_s)
    start = time.monotonic()
    try:
        for k, first in enumerate(range(0, audio.shape[0], step)):
            await asyncio.sleep(max(0.0, start + k * chunk_s - time.monotonic()))
            live.push(audio[first:first + step], rate)
        live.flush()
    except LiveError:
        return


async def push_track(live, track: MediaStreamTrack) -> None:
    """Push what the browser's microphone sends, as it arrives, until the track or the session ends."""
    while True:
        try:
            frame = await track.recv()
        except MediaStreamError:
            return
        samples = frame.to_ndarray()  # s16, [channels or 1, samples] (interleaved for packed stereo)
        channels = len(frame.layout.channels)
        mono = samples.reshape(-1, channels) if samples.shape[0] == 1 else samples.T
        try:
            live.push(mono, frame.sample_rate)
        except LiveError:
            return


def _json_or_none(text: str):
    """`text` parsed as JSON, or None where it is not JSON."""
    try:
        return json.loads(text)
    except ValueError:
        return None


def spoken_text(text: str) -> tuple[np.ndarray, int]:
    """`text` spoken by espeak-ng (a wav on stdout): mono samples and rate."""
    exe = shutil.which("espeak-ng") or shutil.which("espeak")
    if exe is None:
        raise web.HTTPBadRequest(text="text-to-speech needs espeak-ng on the server (apt-get install espeak-ng)")
    wav = subprocess.run([exe, "--stdout", text[:2000]], capture_output=True, check=True).stdout
    path = Path(f"/tmp/gt-live-{threading.get_ident()}.wav")
    path.write_bytes(wav)
    try:
        return load_audio(path, 16000), 16000
    finally:
        path.unlink(missing_ok=True)


class Sessions:
    """The open sessions of one app (either kind), by connection and by the id each page holds; the background
    tasks (voice sources, failure handling), held until they end; and the routes both kinds share: close, stats,
    health and shutdown."""

    def __init__(self, thread_name: str, threads_key: str, failed: str) -> None:
        self.by_connection: dict[RTCPeerConnection, Session | DriveSession] = {}
        self.by_id: dict[str, RTCPeerConnection] = {}
        self.tasks: set[asyncio.Task] = set()
        self.thread_name, self.threads_key, self.failed = thread_name, threads_key, failed

    def background(self, coroutine) -> asyncio.Task:
        task = asyncio.ensure_future(coroutine)
        self.tasks.add(task)
        task.add_done_callback(self.tasks.discard)
        return task

    def add(self, pc: RTCPeerConnection, session_id: str, session) -> None:
        self.by_connection[pc] = session
        self.by_id[session_id] = pc

    def session_of(self, session_id: str) -> tuple[RTCPeerConnection, Session | DriveSession]:
        """The connection and session a page's id names; 404 when it is closed or was never open."""
        pc = self.by_id.get(session_id.strip())
        if pc is None or pc not in self.by_connection:
            raise web.HTTPNotFound(text=f"no live session {session_id.strip()[:40]!r} (already closed?)")
        return pc, self.by_connection[pc]

    async def fail(self, pc: RTCPeerConnection, session_id: str, error: BaseException) -> None:
        """A frame (or drive) raised, which ended the session: log it once, tell the page, and close the session
        when the page has left, ERROR_GRACE_S at most."""
        log.error("live session %s ended: %s", session_id, self.failed, exc_info=error)
        session = self.by_connection.get(pc)
        if session is None:  # already closed
            return
        session.tell({"error": f"the live session ended: {type(error).__name__}: {error}"})
        try:
            await asyncio.wait_for(session.closed.wait(), ERROR_GRACE_S)
        except asyncio.TimeoutError:  # not the builtin before Python 3.11
            pass
        await self.close(pc)

    async def close(self, pc: RTCPeerConnection) -> None:
        session = self.by_connection.pop(pc, None)
        for key in [key for key, value in self.by_id.items() if value is pc]:
            del self.by_id[key]
        if session is not None:
            if getattr(session, "voice", None) is not None:
                session.voice.cancel()
            await asyncio.get_running_loop().run_in_executor(None, session.stop)
            session.closed.set()
        await pc.close()

    def watch(self, pc: RTCPeerConnection) -> None:
        """Close the session when its connection fails or closes."""
        @pc.on("connectionstatechange")
        async def on_state() -> None:
            if pc.connectionState in ("failed", "closed"):
                await self.close(pc)

    async def leave(self, request: web.Request) -> web.Response:
        """The page is leaving (its Stop button, or unload through sendBeacon): end its session now."""
        pc, _ = self.session_of(await request.text())
        await self.close(pc)
        return web.Response(status=204)

    async def stats(self, request: web.Request) -> web.Response:
        return web.json_response([session.summary() for session in self.by_connection.values()])

    async def health(self, request: web.Request) -> web.Response:
        """Open sessions and their running threads: both drop to 0 when every browser has left."""
        threads = sum(thread.name == self.thread_name for thread in threading.enumerate())
        return web.json_response({"sessions": len(self.by_connection), self.threads_key: threads})

    async def shutdown(self, app: web.Application) -> None:
        await asyncio.gather(*(self.close(pc) for pc in list(self.by_connection)))
        for task in list(self.tasks):
            task.cancel()

    def route(self, app: web.Application) -> None:
        """The shared routes and the shutdown hook."""
        app.router.add_get("/stats", self.stats)
        app.router.add_get("/health", self.health)
        app.router.add_post("/close", self.leave)
        app.on_shutdown.append(self.shutdown)


def make_app(bundle: Path, size: int, lookahead_ms: float, speech: Path, renderer: str = "auto",
             client_render: bool = False, batch_frames: int = 1, context_ms: float = 1000.0) -> web.Application:
    app = web.Application()
    if client_render:
        return make_client_render_app(app, bundle, lookahead_ms, speech, batch_frames, context_ms)
    sessions = Sessions(Session.THREAD_NAME, "render_threads", "rendering a frame raised")

    async def index(request: web.Request) -> web.Response:
        return web.Response(text=PAGE.read_text(), content_type="text/html")

    async def offer(request: web.Request) -> web.Response:
        params = await request.json()
        source = params.get("source", "file")
        if source not in ("file", "mic", "text"):
            raise web.HTTPBadRequest(text=f"source must be file, mic or text, got {source!r}")
        loop = asyncio.get_running_loop()
        voice = None  # what the server speaks: made before the session, so that its failure leaves none behind
        if source == "file":
            voice = load_audio(speech, 16000), 16000
        elif source == "text":
            voice = await loop.run_in_executor(None, spoken_text, str(params.get("text", "Hello.")))
        pc = RTCPeerConnection()
        session_id = uuid.uuid4().hex
        session = Session(bundle, size, lookahead_ms, renderer, loop,
                          on_error=lambda error: sessions.background(sessions.fail(pc, session_id, error)))
        sessions.add(pc, session_id, session)

        @pc.on("track")
        def on_track(track: MediaStreamTrack) -> None:
            if track.kind == "audio" and source == "mic":
                sessions.background(push_track(session.live, track))

        @pc.on("datachannel")
        def on_channel(channel) -> None:
            if channel.label == "control":
                session.attach(channel)

        sessions.watch(pc)

        try:
            await loop.run_in_executor(None, session.start)
        except Exception as exc:  # logged once here; the page hears it as the offer's answer
            if isinstance(exc, GaussianTalkerError):
                log.error("live session %s could not start: %s", session_id, exc)
            else:
                log.error("live session %s could not start", session_id, exc_info=exc)
            await sessions.close(pc)
            return web.Response(status=500, text=f"the live session could not start: {type(exc).__name__}: {exc}")
        try:
            pc.addTrack(session.video)
            pc.addTrack(session.audio)
            await pc.setRemoteDescription(RTCSessionDescription(sdp=params["sdp"], type=params["type"]))
            await pc.setLocalDescription(await pc.createAnswer())
        except BaseException:
            await sessions.close(pc)
            raise
        if voice is not None:
            sessions.background(push_real_time(session.live, *voice))
        return web.json_response({"sdp": pc.localDescription.sdp, "type": pc.localDescription.type,
                                  "session": session_id})

    app.router.add_get("/", index)
    app.router.add_post("/offer", offer)
    sessions.route(app)
    return app


def make_client_render_app(app: web.Application, bundle: Path, lookahead_ms: float, speech: Path,
                           batch_frames: int = 1, context_ms: float = 1000.0) -> web.Application:
    """Client-render mode's routes: the page and the web player's modules, the bundle, the offer (audio track and
    drive channel), barge-in, close, stats, the recorded drives and health."""
    # Its driver only (the translator; no frame is drawn). One intra-op thread: the sessions' threads are the
    # parallelism, and onnxruntime's spinning worker threads would only compete with them.
    driver = open_driver(bundle, threads=1)
    sessions = Sessions(DrivePool.THREAD_NAME, "driver_threads", "its driver raised")
    # WebSocket sessions share a thread per core. WebRTC sessions keep a thread each: aiortc's work on the event loop
    # (Opus, SRTP, SCTP) is their bottleneck, and measured, two shared threads made their drives later (16 sessions:
    # 42% of the drives late against 22%, docs/live.md "Load").
    pool, webrtc_pool = DrivePool(os.cpu_count() or 2), DrivePool(MAX_THREADS)

    async def page(request: web.Request) -> web.Response:
        return web.Response(text=WEB_PAGE.read_text(), content_type="text/html")

    async def static(request: web.Request) -> web.StreamResponse:
        """web/src and the npm installs the page's import map names (onnxruntime-web, fflate): the player's modules,
        served as JavaScript and wasm."""
        path = (WEB_ROOT / request.match_info["path"]).resolve()
        modules = WEB_ROOT / "node_modules"
        allowed = (WEB_ROOT / "src", modules / "onnxruntime-web" / "dist", modules / "fflate" / "esm")
        if not any(path.is_relative_to(root) for root in allowed) or not path.is_file():
            raise web.HTTPNotFound()
        types = {".js": "text/javascript", ".mjs": "text/javascript", ".wasm": "application/wasm"}
        return web.FileResponse(path, headers={"Content-Type": types.get(path.suffix, "application/octet-stream"),
                                               "Cache-Control": "no-store"})

    async def serve_bundle(request: web.Request) -> web.FileResponse:
        return web.FileResponse(bundle, headers={"Content-Type": "application/octet-stream"})

    spoken: list[np.ndarray] = []  # the --audio file's samples, once read

    async def voice_of(params: dict, sources: tuple[str, ...]) -> tuple[tuple | None, float]:
        """What the server speaks for a page's start parameters, and the chunk length it is pushed in;
        ValueError naming a bad parameter."""
        source = params.get("source", "file")
        if source not in sources:
            raise ValueError(f"source must be {', '.join(sources[:-1])} or {sources[-1]}, got {source!r}")
        # How the voice arrives: chunks of chunk_ms at real time (20: a voice made as it is spoken, one translator
        # call a frame; a text-to-speech engine faster than real time sends more at a time).
        chunk_ms = params.get("chunk_ms", CHUNK_S * 1000)
        if not (isinstance(chunk_ms, (int, float)) and 10 <= chunk_ms <= 10000):
            raise ValueError(f"chunk_ms must be a number of milliseconds in 10..10000, got {chunk_ms!r}")
        if source == "file":
            if not spoken:  # read once: every session that plays the file shares its samples
                spoken.append(await asyncio.get_running_loop().run_in_executor(None, load_audio, speech, 16000))
            return (spoken[0], 16000), chunk_ms / 1000
        if source == "text":
            text = str(params.get("text", "Hello."))
            return await asyncio.get_running_loop().run_in_executor(None, spoken_text, text), chunk_ms / 1000
        return None, chunk_ms / 1000

    async def offer(request: web.Request) -> web.Response:
        params = await request.json()
        try:
            voice, chunk_s = await voice_of(params, ("file", "text", "none"))
        except ValueError as error:
            raise web.HTTPBadRequest(text=str(error)) from None
        loop = asyncio.get_running_loop()
        pc = RTCPeerConnection()
        session_id = uuid.uuid4().hex
        session = DriveSession(driver, lookahead_ms, loop, webrtc_pool, batch_frames=batch_frames,
                               context_ms=context_ms,
                               on_error=lambda error: sessions.background(sessions.fail(pc, session_id, error)))
        sessions.add(pc, session_id, session)
        pc.on("datachannel", session.attach)
        sessions.watch(pc)
        try:
            pc.addTrack(session.audio)
            await pc.setRemoteDescription(RTCSessionDescription(sdp=params["sdp"], type=params["type"]))
            await pc.setLocalDescription(await pc.createAnswer())
        except BaseException:
            await sessions.close(pc)
            raise
        session.start()
        if voice is not None:
            session.voice = sessions.background(push_real_time(session.live, *voice, chunk_s=chunk_s))
        # start_time: time.monotonic() when frame 0 was due (a load client on this machine compares arrivals).
        return web.json_response({"sdp": pc.localDescription.sdp, "type": pc.localDescription.type,
                                  "session": session_id, "fps": driver.fps, "start_time": session.start_time})

    async def live_socket(request: web.Request) -> web.WebSocketResponse:
        """One client-render session on one WebSocket (docs/live.md, "One WebSocket a session"): the page's start
        message, the answer, then a frame packet per frame; the page's barge-ins (text) and microphone (binary)."""
        socket = web.WebSocketResponse(max_msg_size=MAX_MIC_MESSAGE_BYTES, heartbeat=30.0)
        await socket.prepare(request)
        try:
            first = await socket.receive(timeout=START_TIMEOUT_S)
            params = _json_or_none(first.data) if first.type == web.WSMsgType.TEXT else None
            if not isinstance(params, dict):
                raise ValueError("the first message must be the start message, a JSON object")
            voice, chunk_s = await voice_of(params, ("file", "text", "none", "mic"))
            mic_rate = params.get("mic_rate") if params.get("source") == "mic" else None
            if mic_rate is not None and not (isinstance(mic_rate, int) and 8000 <= mic_rate <= 192000):
                raise ValueError(f"mic_rate must be a whole number of Hz in 8000..192000, got {mic_rate!r}")
            if params.get("source") == "mic" and mic_rate is None:
                raise ValueError("source mic needs mic_rate, the sample rate of the PCM the page sends")
        except (ValueError, asyncio.TimeoutError, TypeError) as error:
            reason = f"no start message within {START_TIMEOUT_S:g} s" if isinstance(error, asyncio.TimeoutError) \
                else str(error)
            if not socket.closed:
                await socket.send_json({"error": f"bad start message: {reason}"})
                await socket.close()
            return socket
        loop = asyncio.get_running_loop()
        session_id = uuid.uuid4().hex
        session = DriveSession(driver, lookahead_ms, loop, pool, transport="ws", batch_frames=batch_frames,
                               context_ms=context_ms,
                               on_error=lambda error: sessions.background(sessions.fail(socket, session_id, error)))
        sessions.add(socket, session_id, session)
        writer = None
        try:
            session.start()
            await socket.send_json({"session": session_id, "fps": driver.fps, "sample_rate": session.sample_rate,
                                    "start_time": session.start_time, "rig": driver.rig})
            writer = sessions.background(session.write_to(socket))
            if voice is not None:
                session.voice = sessions.background(push_real_time(session.live, *voice, chunk_s=chunk_s))
            async for message in socket:
                if message.type == web.WSMsgType.BINARY and mic_rate is not None:
                    if len(message.data) % 2:
                        raise ValueError(f"a microphone message of {len(message.data)} bytes: not whole int16 "
                                         "samples")
                    session.live.push(np.frombuffer(message.data, "<i2"), mic_rate)
                elif message.type == web.WSMsgType.TEXT and _json_or_none(message.data) == {"interrupt": True}:
                    session.outbox.put_nowait(json.dumps({"interrupted": session.interrupt()}))
                elif message.type in (web.WSMsgType.TEXT, web.WSMsgType.BINARY):
                    raise ValueError("the page may send {\"interrupt\": true} or, with source mic, int16 PCM; got "
                                     f"a {message.type.name.lower()} message of {len(message.data)} bytes")
        except (ValueError, LiveError) as error:  # the page's mistake (or its session ended): told, then closed
            if not socket.closed:
                await socket.send_json({"error": str(error)})
        finally:
            if writer is not None:
                writer.cancel()
            await sessions.close(socket)
        return socket

    async def interrupt(request: web.Request) -> web.Response:
        _, session = sessions.session_of(await request.text())
        return web.json_response(session.interrupt())

    async def drives(request: web.Request) -> web.Response:
        """The session's recorded drive messages (the last DriveSession.RECORDED), concatenated, each preceded by
        its length (u16): what the tests compare the page's received drives with."""
        _, session = sessions.session_of(request.query.get("session", ""))
        body = b"".join(struct.pack("<H", len(m)) + m for m in list(session.recorded))
        return web.Response(body=body, content_type="application/octet-stream")

    app.router.add_get("/", page)
    app.router.add_get("/web/{path:.+}", static)
    app.router.add_get("/bundle", serve_bundle)
    app.router.add_post("/offer", offer)
    app.router.add_post("/interrupt", interrupt)
    app.router.add_get("/live", live_socket)
    app.router.add_get("/drives", drives)
    sessions.route(app)
    return app


def main(bundle: Path = typer.Argument(..., help="a speaker bundle with a translator (.gtb)"),
         port: int = typer.Option(8080, "--port", help="port on 127.0.0.1"),
         host: str = typer.Option("127.0.0.1", "--host", help="address to listen on"),
         size: int = typer.Option(256, "--size", min=16, help="square frame size"),
         lookahead_ms: float = typer.Option(160.0, "--lookahead-ms", min=0.0, help="the live session's lookahead"),
         audio: Path = typer.Option(SPEECH, "--audio", help="the sound file the page's 'file' source plays"),
         renderer: str = typer.Option("auto", "--renderer", help="what splats: gl, cpu or auto (cpu where the GL "
                                      "is a software rasterizer and numba is installed; docs/embedding.md)"),
         client_render: bool = typer.Option(False, "--client-render", help="stream drives, not pixels: the page "
                                            "renders the head with the web player (samples/web/live.html)"),
         batch_frames: int = typer.Option(1, "--batch-frames", min=1, max=8, help="client-render: frames per "
                                          "translator call at least; each utterance starts (batch_frames - 1) "
                                          "frames later, and the server's CPU per session falls"),
         context_ms: float = typer.Option(1000.0, "--context-ms", min=0.0, help="client-render: the past audio "
                                          "the translator sees (shorter: cheaper calls, drives a little further "
                                          "from the offline ones; docs/live.md)")) -> None:
    """Serve the live page and stream the talking head over WebRTC."""
    for path, hint in ((bundle, "BUNDLE"), (audio, "--audio")):
        if not path.is_file():
            raise typer.BadParameter(f"{path}: no such file", param_hint=hint)
    logging.basicConfig(format="%(levelname)s %(name)s: %(message)s")
    print(json.dumps({"url": f"http://{host}:{port}/", "bundle": str(bundle)}), flush=True)
    web.run_app(make_app(bundle, size, lookahead_ms, audio, renderer, client_render, batch_frames, context_ms),
                host=host, port=port, print=None)


if __name__ == "__main__":
    typer.run(main)
