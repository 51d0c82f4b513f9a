"""What both modes' WebRTC transports share (aiortc): the media tracks fed from a session's frames, the page's
"control" data channel, the browser microphone as a voice, and the expiry of offers whose peer never connects."""

from __future__ import annotations

import asyncio
import fractions
import json
from collections.abc import Awaitable, Callable

from aiohttp import web
from aiortc import MediaStreamTrack, RTCPeerConnection, RTCSessionDescription
from aiortc.mediastreams import MediaStreamError
from av import AudioFrame, VideoFrame

from gaussiantalker.runtime import LiveError
from gaussiantalker.sdk.audio import to_pcm16

from .drive_sessions import WEBRTC_AUDIO_RATE

QUEUE_FRAMES = 50  # frames waiting for a track, at most (2 s): a reader that stalls loses the oldest
MAX_CONTROL_MESSAGES = 64  # messages kept for a control channel that is not open yet


class FrameTrack(MediaStreamTrack):
    """A video or audio track fed with a live session's frames (`put` from any thread; None ends it)."""

    def __init__(self, kind: str, loop: asyncio.AbstractEventLoop, fps: float = 25.0) -> None:
        super().__init__()
        self.kind, self._loop, self.fps = kind, loop, fps
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
            out.pts, out.time_base = round(frame.index * 90000 / self.fps), fractions.Fraction(1, 90000)
            return out
        pcm = to_pcm16(frame.audio)[None]
        out = AudioFrame.from_ndarray(pcm, format="s16", layout="mono")
        out.sample_rate = WEBRTC_AUDIO_RATE
        out.pts, out.time_base = round(frame.index * WEBRTC_AUDIO_RATE / self.fps), \
            fractions.Fraction(1, WEBRTC_AUDIO_RATE)
        return out


class ControlChannel:
    """The page's "control" data channel: JSON messages for the page, kept (a bounded number) until it is open.
    A message from the page, {"interrupt": true} or {"close": true}, goes to `on_message`."""

    def __init__(self, on_message: Callable[[dict], None] | None = None) -> None:
        self._channel = None
        self._outbox: list[str] = []
        self._on_message = on_message

    def attach(self, channel) -> None:
        """The channel the page opened: queued messages go out on it once it is open."""
        self._channel = channel
        channel.on("open", self._send_outbox)
        if self._on_message is not None:
            channel.on("message", self._received)
        self._send_outbox()

    def _received(self, message) -> None:
        try:
            value = json.loads(message) if isinstance(message, str) and len(message) < 1024 else None
        except ValueError:
            value = None
        if isinstance(value, dict) and self._on_message is not None:
            self._on_message(value)

    def tell(self, message: dict) -> None:
        """Send the page `message` (JSON) now, or as soon as the channel opens."""
        if len(self._outbox) < MAX_CONTROL_MESSAGES:
            self._outbox.append(json.dumps(message))
        self._send_outbox()

    def _send_outbox(self) -> None:
        if self._channel is not None and self._channel.readyState == "open":
            while self._outbox:
                self._channel.send(self._outbox.pop(0))


async def push_track(live, track: MediaStreamTrack) -> None:
    """Push what the browser's microphone sends, as it arrives, until the track or the session ends. (Its pace is
    the peer's RTP clock: aiortc's jitter buffer bounds how much arrives at once.)"""
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


async def answer_offer(pc: RTCPeerConnection, sdp: str, tracks: list, close: Callable[[], Awaitable[None]]) -> None:
    """Add the server's `tracks`, take the page's offer and make the answer; where aiortc cannot (its errors name
    its internals) the session is closed and the page gets 400 with one line."""
    try:
        for track in tracks:
            pc.addTrack(track)
        await pc.setRemoteDescription(RTCSessionDescription(sdp=sdp, type="offer"))
        await pc.setLocalDescription(await pc.createAnswer())
    except Exception:
        await close()
        raise web.HTTPBadRequest(text="the offer's SDP could not be used") from None


def watch(pc: RTCPeerConnection, close: Callable[[], Awaitable[None]], connect_s: float,
          on_expired: Callable[[], None]) -> None:
    """Close the session when its peer connection fails or closes, or has not connected within `connect_s`
    (an offer whose peer never sends its candidates would otherwise hold a session for ever)."""

    @pc.on("connectionstatechange")
    async def on_state() -> None:
        if pc.connectionState in ("failed", "closed"):
            await close()

    async def expire() -> None:
        await asyncio.sleep(connect_s)
        if pc.connectionState not in ("connected", "closed"):
            on_expired()
            await close()

    task = asyncio.ensure_future(expire())
    pc.on("connectionstatechange", lambda: task.cancel() if pc.connectionState == "connected" else None)


__all__ = ["ControlChannel", "FrameTrack", "MAX_CONTROL_MESSAGES", "QUEUE_FRAMES", "answer_offer", "push_track",
           "watch"]
