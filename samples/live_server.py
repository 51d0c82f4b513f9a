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
"""

from __future__ import annotations

import asyncio
import fractions
import json
import logging
import shutil
import subprocess
import threading
import time
import uuid
from collections.abc import Callable
from pathlib import Path

import numpy as np
import typer

from gaussiantalker.runtime import GaussianTalkerError, LiveError, TalkingHead
from gaussiantalker.sdk.audio import load_audio

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
# A session whose rendering failed waits this long at most for its page to hear why and leave, then closes: long
# enough for a page whose first frame failed to finish connecting and open its control channel.
ERROR_GRACE_S = 10.0
log = logging.getLogger("live_server")


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
        pcm = np.clip(np.round(frame.audio * 32768.0), -32768, 32767).astype(np.int16)[None]
        out = AudioFrame.from_ndarray(pcm, format="s16", layout="mono")
        out.sample_rate = AUDIO_RATE
        out.pts, out.time_base = round(frame.index * AUDIO_RATE / self.fps), fractions.Fraction(1, AUDIO_RATE)
        return out


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
        self._channel = None  # the page's "control" data channel
        self._outbox: list[str] = []  # messages for the page until its channel is open
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
        self._channel = channel
        channel.on("open", self._send_outbox)
        self._send_outbox()

    def tell(self, message: dict) -> None:
        """Send the page `message` (JSON) on its control channel, now or as soon as the channel opens."""
        self._outbox.append(json.dumps(message))
        self._send_outbox()

    def _send_outbox(self) -> None:
        if self._channel is not None and self._channel.readyState == "open":
            while self._outbox:
                self._channel.send(self._outbox.pop(0))

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


async def push_real_time(live, audio: np.ndarray, rate: int) -> None:
    """Push `audio` in CHUNK_S chunks at real time, as a voice that speaks as it is made, then flush. Stops
    quietly when the session closes (the browser left)."""
    step = int(rate * CHUNK_S)
    start = time.monotonic()
    try:
        for k, first in enumerate(range(0, audio.shape[0], step)):
            await asyncio.sleep(max(0.0, start + k * CHUNK_S - time.monotonic()))
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


def make_app(bundle: Path, size: int, lookahead_ms: float, speech: Path, renderer: str = "auto") -> web.Application:
    app = web.Application()
    sessions: dict[RTCPeerConnection, Session] = {}
    connections: dict[str, RTCPeerConnection] = {}  # the id each page holds -> its connection
    tasks: set[asyncio.Task] = set()  # voice sources and failure handling: held until they end

    def background(coroutine) -> None:
        task = asyncio.ensure_future(coroutine)
        tasks.add(task)
        task.add_done_callback(tasks.discard)

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
                          on_error=lambda error: background(fail(pc, session_id, error)))
        sessions[pc] = session
        connections[session_id] = pc

        @pc.on("track")
        def on_track(track: MediaStreamTrack) -> None:
            if track.kind == "audio" and source == "mic":
                background(push_track(session.live, track))

        @pc.on("datachannel")
        def on_channel(channel) -> None:
            if channel.label == "control":
                session.attach(channel)

        @pc.on("connectionstatechange")
        async def on_state() -> None:
            if pc.connectionState in ("failed", "closed"):
                await close(pc)

        try:
            await loop.run_in_executor(None, session.start)
        except Exception as exc:  # logged once here; the page hears it as the offer's answer
            if isinstance(exc, GaussianTalkerError):
                log.error("live session %s could not start: %s", session_id, exc)
            else:
                log.error("live session %s could not start", session_id, exc_info=exc)
            await close(pc)
            return web.Response(status=500, text=f"the live session could not start: {type(exc).__name__}: {exc}")
        try:
            pc.addTrack(session.video)
            pc.addTrack(session.audio)
            await pc.setRemoteDescription(RTCSessionDescription(sdp=params["sdp"], type=params["type"]))
            await pc.setLocalDescription(await pc.createAnswer())
        except BaseException:
            await close(pc)
            raise
        if voice is not None:
            background(push_real_time(session.live, *voice))
        return web.json_response({"sdp": pc.localDescription.sdp, "type": pc.localDescription.type,
                                  "session": session_id})

    async def fail(pc: RTCPeerConnection, session_id: str, error: BaseException) -> None:
        """A frame raised, which ended the session: log it once, tell the page, and close the session when the
        page has left, ERROR_GRACE_S at most."""
        log.error("live session %s ended: rendering a frame raised", session_id, exc_info=error)
        session = sessions.get(pc)
        if session is None:  # already closed
            return
        session.tell({"error": f"the live session ended: {type(error).__name__}: {error}"})
        try:
            await asyncio.wait_for(session.closed.wait(), ERROR_GRACE_S)
        except asyncio.TimeoutError:  # not the builtin before Python 3.11
            pass
        await close(pc)

    async def close(pc: RTCPeerConnection) -> None:
        session = sessions.pop(pc, None)
        for key in [key for key, value in connections.items() if value is pc]:
            del connections[key]
        if session is not None:
            await asyncio.get_running_loop().run_in_executor(None, session.stop)
            session.closed.set()
        await pc.close()

    async def leave(request: web.Request) -> web.Response:
        """The page is leaving (its Stop button, or unload through sendBeacon): end its session now."""
        session_id = (await request.text()).strip()
        pc = connections.get(session_id)
        if pc is None:
            raise web.HTTPNotFound(text=f"no live session {session_id[:40]!r} (already closed?)")
        await close(pc)
        return web.Response(status=204)

    async def stats(request: web.Request) -> web.Response:
        return web.json_response([session.summary() for session in sessions.values()])

    async def health(request: web.Request) -> web.Response:
        """Open sessions and running render threads: both drop to 0 when every browser has left."""
        threads = sum(thread.name == Session.THREAD_NAME for thread in threading.enumerate())
        return web.json_response({"sessions": len(sessions), "render_threads": threads})

    async def on_shutdown(app: web.Application) -> None:
        await asyncio.gather(*(close(pc) for pc in list(sessions)))
        for task in list(tasks):
            task.cancel()

    app.router.add_get("/", index)
    app.router.add_post("/offer", offer)
    app.router.add_get("/stats", stats)
    app.router.add_get("/health", health)
    app.router.add_post("/close", leave)
    app.on_shutdown.append(on_shutdown)
    return app


def main(bundle: Path = typer.Argument(..., help="a speaker bundle with a translator (.gtb)"),
         port: int = typer.Option(8080, "--port", help="port on 127.0.0.1"),
         host: str = typer.Option("127.0.0.1", "--host", help="address to listen on"),
         size: int = typer.Option(256, "--size", min=16, help="square frame size"),
         lookahead_ms: float = typer.Option(160.0, "--lookahead-ms", min=0.0, help="the live session's lookahead"),
         audio: Path = typer.Option(SPEECH, "--audio", help="the sound file the page's 'file' source plays"),
         renderer: str = typer.Option("auto", "--renderer", help="what splats: gl, cpu or auto (cpu where the GL "
                                      "is a software rasterizer and numba is installed; docs/embedding.md)")) -> None:
    """Serve the live page and stream the talking head over WebRTC."""
    for path, hint in ((bundle, "BUNDLE"), (audio, "--audio")):
        if not path.is_file():
            raise typer.BadParameter(f"{path}: no such file", param_hint=hint)
    logging.basicConfig(format="%(levelname)s %(name)s: %(message)s")
    print(json.dumps({"url": f"http://{host}:{port}/", "bundle": str(bundle)}), flush=True)
    web.run_app(make_app(bundle, size, lookahead_ms, audio, renderer), host=host, port=port, print=None)


if __name__ == "__main__":
    typer.run(main)
