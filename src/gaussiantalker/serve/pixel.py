"""Pixel mode (docs/serve.md, docs/live.md "WebRTC sample"): each page gets its own live session on a render
thread that owns its TalkingHead and GL context, streamed as WebRTC video and audio tracks on the session's one
clock. Its pages choose a voice (the server's file, text, the browser microphone) with POST /offer; every
session is admitted by client and an offer whose peer never connects expires."""

from __future__ import annotations

import asyncio
import threading
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path

import numpy as np
from aiohttp import web

from gaussiantalker.runtime import TalkingHead

from .drive_sessions import WEBRTC_AUDIO_RATE
from .keys import CLIENT
from .limits import ServeLimits, TokenBucket
from .metrics import ServeMetrics
from .sessions import Sessions
from .voices import VoiceFiles, push_real_time, read_offer
from .wire import WIRE_VERSION

PAGE = Path(__file__).with_name("pages") / "pixel.html"
STATS_FRAMES = 1500  # the last minute of frames /stats summarises


class PixelSession:
    """One page's live session on a render thread of its own, with its counters for /stats. `on_error(error)` is
    called on the event loop when a frame raises (the session has then ended)."""

    THREAD_NAME = "gt-live-render"

    def __init__(self, bundle: Path, size: int, lookahead_ms: float, renderer: str, limits: ServeLimits,
                 metrics: ServeMetrics, loop: asyncio.AbstractEventLoop,
                 on_error: Callable[[BaseException], None] | None = None) -> None:
        from .webrtc import ControlChannel, FrameTrack

        self.ready = threading.Event()
        self.closed = asyncio.Event()  # set once the server has closed the session
        self.stats: dict = {"frames": 0, "speaking_frames": 0}
        self.jaw: deque[float] = deque(maxlen=STATS_FRAMES)
        self.level: deque[float] = deque(maxlen=STATS_FRAMES)
        self._args = (bundle, size, lookahead_ms, renderer, limits.max_queued_s)
        self._loop, self._on_error, self._metrics = loop, on_error, metrics
        self.live = self.head = None
        self.voice: asyncio.Task | None = None
        self.error: BaseException | None = None  # what ended the session, if it failed
        self._started = False  # the head and its live session were made: an error after it is a frame's
        self.video, self.audio = FrameTrack("video", loop), FrameTrack("audio", loop)
        self.interrupts = TokenBucket(limits.interrupts_per_s, limits.interrupt_burst)
        self.control = ControlChannel(self._control_message)
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
        if channel.label == "control":
            self.control.attach(channel)

    def tell(self, message: dict) -> None:
        """Send the page `message` (JSON) on its control channel, now or as soon as the channel opens."""
        self.control.tell(message)

    def _control_message(self, message: dict) -> None:
        if message == {"interrupt": True} and self.live is not None and self.interrupts.take():
            if self.voice is not None:
                self.voice.cancel()
            self.live.interrupt()
            self.tell({"interrupted": {"epoch": self.live.stats.interrupts}})

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
        bundle, size, lookahead_ms, renderer, max_queued_s = self._args
        frame_seconds = self._metrics.frame_seconds.labels(mode="pixel")
        frames, late = self._metrics.frames.labels(mode="pixel"), self._metrics.late_frames.labels(mode="pixel")
        try:
            with TalkingHead(bundle, resolution=(size, size), composite=False, renderer=renderer) as head, \
                    head.live(lookahead_ms=lookahead_ms, audio_rate=WEBRTC_AUDIO_RATE,
                              max_queued_s=max_queued_s) as live:
                self.head, self.live, self._started = head, live, True
                self.video.fps = self.audio.fps = head.fps
                self.ready.set()
                began, late_counted = time.perf_counter(), 0
                for frame in live.frames():
                    frame_seconds.observe(time.perf_counter() - began)  # the wait for its due time included
                    frames.inc()
                    if live.stats.late_frames > late_counted:
                        late.inc(live.stats.late_frames - late_counted)
                        late_counted = live.stats.late_frames
                    self.stats["frames"] += 1
                    self.stats["speaking_frames"] += frame.speaking
                    pose = getattr(frame.drive, "flame_pose", None)  # an ARKit speaker's jaw: its jawOpen weight
                    self.jaw.append(float(pose[6]) if pose is not None else float(frame.drive.blendshapes[24]))
                    self.level.append(float(np.sqrt(np.mean(frame.audio ** 2))))
                    self.video.put(frame)
                    self.audio.put(frame)
                    began = time.perf_counter()
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
        jaw, level = np.array(self.jaw), np.array(self.level)
        speaking = level > 1e-4
        corr = float(np.corrcoef(jaw, level)[0, 1]) if jaw.size > 2 and jaw.std() > 0 and level.std() > 0 else 0.0
        return {"mode": "pixel", "frames": self.stats["frames"], "speaking_frames": self.stats["speaking_frames"],
                "jaw_range_speaking": float(np.ptp(jaw[speaking])) if speaking.any() else 0.0,
                "jaw_loudness_r": corr, "fps": self.head.fps if self.head else None,
                "size": list(self.head.frame_size) if self.head else None,
                "late_frames": self.live.stats.late_frames if self.live else 0,
                "renderer": self.head.renderer if self.head else None}


def add_pixel_routes(app: web.Application, bundle: Path, sessions: Sessions, limits: ServeLimits,
                     metrics: ServeMetrics, files: VoiceFiles, *, size: int, lookahead_ms: float,
                     renderer: str) -> None:
    """The page and POST /offer."""
    speech_gate = asyncio.Semaphore(limits.speech_processes)

    async def index(request: web.Request) -> web.Response:
        return web.Response(text=PAGE.read_text(encoding="utf-8"), content_type="text/html",
                            headers={"Cache-Control": "no-store"})

    async def offer(request: web.Request) -> web.Response:
        from aiortc import RTCPeerConnection

        from .webrtc import answer_offer, push_track, watch

        sdp, voice = await read_offer(request, ("file", "mic", "text"), files, limits, speech_gate, mic_track=True)
        client = request[CLIENT].key
        sessions.admit_or_refuse(client)
        loop = asyncio.get_running_loop()
        pc = RTCPeerConnection()
        session = PixelSession(bundle, size, lookahead_ms, renderer, limits, metrics, loop,
                               on_error=lambda error: sessions.background(
                                   sessions.fail(pc, error, "rendering a frame raised")))
        session_id = sessions.add(pc, session, client, "webrtc")

        @pc.on("track")
        def on_track(track) -> None:
            if track.kind == "audio" and voice.source == "mic":
                sessions.background(push_track(session.live, track))

        pc.on("datachannel", session.attach)
        watch(pc, lambda: sessions.close(pc), limits.offer_connect_s,
              lambda: metrics.refuse("offer_not_connected"))
        try:
            await loop.run_in_executor(None, session.start)
        except Exception as error:  # logged once here, with its traceback; the page hears one line
            from .logs import log

            log.error("session %s could not start: %s: %s", session_id, type(error).__name__, error, exc_info=error)
            await sessions.close(pc)
            raise web.HTTPServiceUnavailable(
                text=f"the live session could not start ({type(error).__name__})") from None
        await answer_offer(pc, sdp, [session.video, session.audio], lambda: sessions.close(pc))
        if voice.samples is not None:
            session.voice = sessions.background(push_real_time(session.live, voice.samples, voice.rate,
                                                               voice.chunk_s))
        return web.json_response({"sdp": pc.localDescription.sdp, "type": pc.localDescription.type,
                                  "session": session_id, "wire": WIRE_VERSION})

    app.router.add_get("/", index)
    app.router.add_post("/offer", offer)


__all__ = ["PixelSession", "add_pixel_routes"]
