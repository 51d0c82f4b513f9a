"""Client-render mode's routes (docs/serve.md, docs/live.md "Live, rendered by the client"): one Driver serves
every session and the page draws the head with the web player; each session runs over one WebSocket (GET /live:
a frame packet per frame) or over WebRTC (POST /offer: drives on a data channel beside an audio track). Every
client is bounded: its sessions, the start message's time, its barge-ins and microphone rate, and the frames
queued for it."""

from __future__ import annotations

import asyncio
import contextlib
import json
import socket as socket_module
import struct
from pathlib import Path

import numpy as np
from aiohttp import web

from gaussiantalker.runtime import LiveError, open_driver
from gaussiantalker.runtime.live import session_stream_spec

from .drive_sessions import DrivePool, DriveSession
from .keys import CLIENT, DRIVER
from .limits import ServeLimits, TokenBucket
from .logs import log
from .metrics import ServeMetrics
from .sessions import Sessions, read_text
from .voices import VoiceFiles, read_offer, voice_of
from .wire import CLOSE_POLICY, CLOSE_TRY_AGAIN, INTERRUPT_MESSAGE, START_SOURCES, WIRE_VERSION

PAGE = Path(__file__).with_name("pages") / "client.html"
MAX_MIC_MESSAGE_BYTES = 256 * 1024  # one microphone message, at most (over a second at 96 kHz)
HEARTBEAT_S = 30.0  # a WebSocket whose peer answers no ping this long is closed
SEND_BUFFER_BYTES = 64 * 1024  # the kernel's buffer for a page's socket: 1.7 s of frames, 8x what 200 ms of RTT needs
STATIC_TYPES = {".js": "text/javascript", ".mjs": "text/javascript", ".wasm": "application/wasm"}


def default_web_root() -> Path:
    """The web player of the checkout this package runs from (web/, with its npm install)."""
    return Path(__file__).resolve().parents[3] / "web"


def add_client_render_routes(app: web.Application, bundle: Path, sessions: Sessions, limits: ServeLimits,
                             metrics: ServeMetrics, files: VoiceFiles, *, lookahead_ms: float, batch_frames: int,
                             context_ms: float, web_root: Path | None = None, streaming: bool = True,
                             stream_delay_ms: float | None = None, drive_threads: int = 1) -> None:
    """The page and the web player's modules, the bundle, /live, /offer, /interrupt and /drives."""
    # One intra-op thread: the sessions' pool threads are the parallelism.
    driver = open_driver(bundle, threads=1)
    driver.open_stream()
    if stream_delay_ms is not None:  # a stream the bundle lacks is refused now, not at the first session
        if not (streaming and driver.has_stream):
            raise LiveError("--stream-delay-ms picks one of the translator's streams, but this server's sessions "
                            "translate windows (--no-stream, or a bundle without a streaming graph)")
        session_stream_spec(driver, stream_delay_ms)
    web_root = (web_root or default_web_root()).resolve()
    # WebSocket sessions share `drive_threads` threads (one by default: a frame's work is Python under the
    # interpreter lock, and a second thread measured more CPU a session and more late frames, as the two contend for
    # it and split the sessions' translator calls in two: docs/live.md, "Load"); WebRTC sessions keep a thread each
    # (aiortc's work on the event loop is their bottleneck), bounded by the session cap.
    pool, webrtc_pool = DrivePool(drive_threads), DrivePool(limits.session_cap(pixel=False))
    speech_gate = asyncio.Semaphore(limits.speech_processes)
    app[DRIVER] = driver

    def new_session(loop, transport: str, on_error, on_overflow) -> DriveSession:
        return DriveSession(driver, lookahead_ms, loop, webrtc_pool if transport == "webrtc" else pool, limits,
                            metrics, on_error=on_error, on_overflow=on_overflow, transport=transport,
                            batch_frames=batch_frames, context_ms=context_ms,
                            streaming=None if streaming else False, stream_delay_ms=stream_delay_ms)

    async def page(request: web.Request) -> web.Response:
        return web.Response(text=PAGE.read_text(encoding="utf-8"), content_type="text/html",
                            headers={"Cache-Control": "no-store"})

    async def static(request: web.Request) -> web.StreamResponse:
        """web/src and the npm installs the page's import map names (onnxruntime-web, fflate), nothing else."""
        path = (web_root / request.match_info["path"]).resolve()
        modules = web_root / "node_modules"
        allowed = (web_root / "src", modules / "onnxruntime-web" / "dist", modules / "fflate" / "esm")
        if not any(path.is_relative_to(root) for root in allowed) or not path.is_file():
            raise web.HTTPNotFound(text="not found")
        return web.FileResponse(path, headers={"Content-Type": STATIC_TYPES.get(path.suffix,
                                                                                 "application/octet-stream"),
                                               "Cache-Control": "no-store"})

    async def serve_bundle(request: web.Request) -> web.FileResponse:
        return web.FileResponse(bundle, headers={"Content-Type": "application/octet-stream"})

    async def offer(request: web.Request) -> web.Response:
        from aiortc import RTCPeerConnection

        from .webrtc import ControlChannel, FrameTrack, answer_offer, watch

        sdp, voice = await read_offer(request, ("file", "text", "none"), files, limits, speech_gate)
        client = request[CLIENT].key
        sessions.admit_or_refuse(client)
        loop = asyncio.get_running_loop()
        pc = RTCPeerConnection()
        session = new_session(
            loop, "webrtc", on_error=lambda error: sessions.background(sessions.fail(pc, error, "its driver raised")),
            on_overflow=lambda: None)
        session.audio = FrameTrack("audio", loop, driver.fps)
        session.control = ControlChannel(lambda message: _control_message(sessions, pc, session, message))
        session_id = sessions.add(pc, session, client, "webrtc")
        pc.on("datachannel", session.attach)
        watch(pc, lambda: sessions.close(pc), limits.offer_connect_s,
              lambda: metrics.refuse("offer_not_connected"))
        await answer_offer(pc, sdp, [session.audio], lambda: sessions.close(pc))
        session.start()
        if voice.samples is not None:
            session.speak(voice.samples, voice.rate, voice.chunk_s)
        # start_time: time.monotonic() when frame 0 was due (a load client on this machine compares arrivals).
        return web.json_response({"sdp": pc.localDescription.sdp, "type": pc.localDescription.type,
                                  "session": session_id, "fps": driver.fps, "start_time": session.start_time,
                                  "wire": WIRE_VERSION})

    async def live_socket(request: web.Request) -> web.WebSocketResponse:
        """One session on one WebSocket: the page's start message, the answer, then a frame packet per frame;
        the page's barge-ins (text) and microphone (binary), each within its rate."""
        # No permessage-deflate, which browsers ask for: a frame packet (int16 audio and float32 drives) compresses
        # poorly for a zlib pass a frame, each socket would hold a compressor's and a decompressor's state, and a
        # page's compressed messages would be inflated by the server (docs/serve.md, "Limits").
        socket = web.WebSocketResponse(max_msg_size=MAX_MIC_MESSAGE_BYTES, heartbeat=HEARTBEAT_S, compress=False)
        await socket.prepare(request)
        _bound_send_buffer(request)
        client = request[CLIENT].key
        refused = sessions.admit(client)
        if refused is not None:
            await socket.send_json({"error": refused})
            await socket.close(code=CLOSE_TRY_AGAIN, message=refused[:120].encode())
            return socket
        admitted = True
        try:
            try:
                first = await socket.receive(timeout=limits.start_message_s)
                params = _json_or_none(first.data) if first.type == web.WSMsgType.TEXT else None
                if not isinstance(params, dict):
                    raise ValueError("the first message must be the start message, a JSON object")
                voice = await voice_of(params, START_SOURCES, files, limits, speech_gate)
            except (ValueError, asyncio.TimeoutError, TypeError) as error:
                reason = f"no start message within {limits.start_message_s:g} s" \
                    if isinstance(error, asyncio.TimeoutError) else str(error)
                if not socket.closed:
                    await socket.send_json({"error": f"bad start message: {reason}"})
                    await socket.close(code=CLOSE_POLICY, message=b"bad start message")
                return socket
            loop = asyncio.get_running_loop()
            session = new_session(
                loop, "ws",
                on_error=lambda error: sessions.background(sessions.fail(socket, error, "its driver raised")),
                on_overflow=lambda: sessions.background(
                    sessions.close(socket, CLOSE_POLICY, "the client does not read its frames")))
            session_id = sessions.add(socket, session, client, "ws")
            admitted = False  # released by sessions.close from here on
        finally:
            if admitted:
                sessions.admission.release(client)
        writer = None
        mic_rate = voice.mic_rate
        if mic_rate is not None:
            mic_samples = TokenBucket(limits.mic_realtime_factor * mic_rate, limits.mic_burst_s * mic_rate)
            mic_messages = TokenBucket(limits.mic_messages_per_s, 2 * limits.mic_messages_per_s)
        try:
            session.start()
            await socket.send_json({"session": session_id, "fps": driver.fps, "sample_rate": session.sample_rate,
                                    "start_time": session.start_time, "rig": driver.rig, "wire": WIRE_VERSION})
            writer = sessions.background(session.write_to(socket))
            if voice.samples is not None:
                session.speak(voice.samples, voice.rate, voice.chunk_s)
            async for message in socket:
                if message.type == web.WSMsgType.BINARY and mic_rate is not None:
                    if len(message.data) % 2:
                        raise ValueError(f"a microphone message of {len(message.data)} bytes: not whole int16 "
                                         "samples")
                    if not (mic_messages.take() and mic_samples.take(len(message.data) // 2)):
                        raise _TooFast(f"microphone audio faster than {limits.mic_realtime_factor:g}x real time")
                    session.live.push(np.frombuffer(message.data, "<i2"), mic_rate)
                elif message.type == web.WSMsgType.TEXT and _json_or_none(message.data) == INTERRUPT_MESSAGE:
                    if not session.interrupts.take():
                        raise _TooFast(f"more than {limits.interrupts_per_s:g} interrupts a second")
                    session.tell({"interrupted": session.interrupt()})
                elif message.type in (web.WSMsgType.TEXT, web.WSMsgType.BINARY):
                    raise ValueError("the page may send {\"interrupt\": true} or, with source mic, int16 PCM; got "
                                     f"a {message.type.name.lower()} message of {len(message.data)} bytes")
        except _TooFast as error:
            metrics.refuse("rate")
            await _tell_and_close(socket, sessions, str(error))
        except (ValueError, LiveError) as error:  # the page's mistake (or its session ended): told, then closed
            await _tell_and_close(socket, sessions, str(error))
        finally:
            if writer is not None:
                writer.cancel()
            await sessions.close(socket)
        return socket

    async def interrupt(request: web.Request) -> web.Response:
        connection, session = sessions.own_session(request, await read_text(request))
        if not session.interrupts.take():
            metrics.refuse("rate")
            raise web.HTTPTooManyRequests(text=f"more than {limits.interrupts_per_s:g} interrupts a second")
        return web.json_response(session.interrupt())

    async def drives(request: web.Request) -> web.Response:
        """The session's recorded drive messages, concatenated, each preceded by its length (u16)."""
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


def _bound_send_buffer(request: web.Request) -> None:
    """Fix the socket's kernel send buffer at SEND_BUFFER_BYTES (Linux would grow it to megabytes for a peer that
    does not read), so that a page that stops reading fills its outbox, and is closed, within seconds."""
    sock = request.transport.get_extra_info("socket") if request.transport is not None else None
    if sock is not None:
        with contextlib.suppress(OSError):
            sock.setsockopt(socket_module.SOL_SOCKET, socket_module.SO_SNDBUF, SEND_BUFFER_BYTES)


class _TooFast(ValueError):
    """A client sent faster than its rate allows."""


async def _tell_and_close(socket: web.WebSocketResponse, sessions: Sessions, reason: str) -> None:
    """Tell the page `reason` as {"error"} and close its socket with 1008."""
    if not socket.closed:
        try:
            await socket.send_json({"error": reason})
        except ConnectionError:
            pass
    await sessions.close(socket, CLOSE_POLICY, reason)


def _control_message(sessions: Sessions, connection, session, message: dict) -> None:
    """A WebRTC page's control channel message: a barge-in (within its rate) or its leaving."""
    if message == INTERRUPT_MESSAGE:
        if session.interrupts.take():
            session.tell({"interrupted": session.interrupt()})
        else:
            log.info("a page's interrupts came faster than allowed; one was ignored")
    elif message == {"close": True}:
        sessions.background(sessions.close(connection))


def _json_or_none(text: str):
    """`text` parsed as JSON, or None where it is not JSON."""
    try:
        return json.loads(text)
    except ValueError:
        return None


__all__ = ["MAX_MIC_MESSAGE_BYTES", "add_client_render_routes", "default_web_root"]
