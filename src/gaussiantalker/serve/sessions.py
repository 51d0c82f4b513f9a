"""The open sessions of one server (either mode): admission by client, the id each page holds, one log line per
session start and end, the background tasks, failure handling, drain, and the admin routes both modes share
(/close, /stats, /health)."""

from __future__ import annotations

import asyncio
import json
import threading
import time
import uuid
from dataclasses import dataclass, field

from aiohttp import web

from .keys import CLIENT, LIMITS
from .limits import Admission
from .logs import log
from .metrics import ServeMetrics
from .wire import CLOSE_GOING_AWAY

ERROR_GRACE_S = 10.0  # a failed session waits this long at most for its page to hear why and leave


@dataclass
class Entry:
    """One open session: its connection (a WebSocketResponse or an RTCPeerConnection), id, client and start."""

    connection: object
    session_id: str
    session: object
    client: str
    transport: str
    started: float = field(default_factory=time.monotonic)


class Sessions:
    """The server's sessions, by connection and by the id each page holds."""

    def __init__(self, mode: str, thread_name: str, threads_key: str, admission: Admission,
                 metrics: ServeMetrics) -> None:
        self.mode, self.thread_name, self.threads_key = mode, thread_name, threads_key
        self.admission, self.metrics = admission, metrics
        self.entries: dict[object, Entry] = {}
        self.by_id: dict[str, object] = {}
        self.tasks: set[asyncio.Task] = set()
        self.emptied = asyncio.Event()

    def background(self, coroutine) -> asyncio.Task:
        task = asyncio.ensure_future(coroutine)
        self.tasks.add(task)
        task.add_done_callback(self.tasks.discard)
        return task

    def admit(self, client: str) -> str | None:
        """None when `client` may open one more session (its place is then taken), else the reason it may not."""
        reason = self.admission.admit(client)
        if reason is not None:
            self.metrics.refuse("draining" if self.admission.draining else "capacity")
        return reason

    def admit_or_refuse(self, client: str) -> None:
        """admit, or raise 429 with the reason (an HTTP request's refusal)."""
        refused = self.admit(client)
        if refused is not None:
            raise web.HTTPTooManyRequests(text=refused)

    def add(self, connection, session, client: str, transport: str) -> str:
        """Register an admitted session; returns its id. One log line says it started."""
        session_id = uuid.uuid4().hex
        self.entries[connection] = Entry(connection, session_id, session, client, transport)
        self.by_id[session_id] = connection
        self.emptied.clear()
        self.metrics.sessions.labels(mode=self.mode).inc()
        self.metrics.sessions_started.labels(mode=self.mode).inc()
        log.info("session %s started: %s, %s, %s", session_id, self.mode, transport, client)
        return session_id

    def session_of(self, session_id: str):
        """The (connection, session) a page's id names; 404 when it is closed or was never open."""
        connection = self.by_id.get(session_id.strip()[:64])
        if connection is None or connection not in self.entries:
            raise web.HTTPNotFound(text="no such live session (already closed?)")
        return connection, self.entries[connection].session

    def own_session(self, request: web.Request, session_id: str):
        """session_of, for the requesting client only: another client's session is 404 as if it did not exist."""
        connection, session = self.session_of(session_id)
        if self.entries[connection].client != request[CLIENT].key:
            raise web.HTTPNotFound(text="no such live session (already closed?)")
        return connection, session

    async def fail(self, connection, error: BaseException, what: str) -> None:
        """Making a frame raised, which ended the session: log it once (with its traceback), tell the page in one
        line without the error's text, and close the session when the page has left, ERROR_GRACE_S at most."""
        entry = self.entries.get(connection)
        if entry is None:  # already closed
            return
        log.error("session %s ended: %s: %s: %s", entry.session_id, what, type(error).__name__, error, exc_info=error)
        entry.session.tell({"error": f"the live session ended: {what} ({type(error).__name__})"})
        try:
            await asyncio.wait_for(entry.session.closed.wait(), ERROR_GRACE_S)
        except asyncio.TimeoutError:  # not the builtin before Python 3.11
            pass
        await self.close(connection)

    async def close(self, connection, code: int = 1000, reason: str = "") -> None:
        """End a session (any number of times): its place is released, its end logged once, its connection closed."""
        entry = self.entries.pop(connection, None)
        if entry is not None:
            self.by_id.pop(entry.session_id, None)
            session = entry.session
            if getattr(session, "voice", None) is not None:
                session.voice.cancel()
            await asyncio.get_running_loop().run_in_executor(None, session.stop)
            session.closed.set()
            self.admission.release(entry.client)
            self.metrics.sessions.labels(mode=self.mode).dec()
            summary = session.summary()
            log.info("session %s ended after %.1f s: %d frames, %d late%s", entry.session_id,
                     time.monotonic() - entry.started, summary.get("frames", 0), summary.get("late_frames", 0),
                     f", {reason}" if reason else "")
            if not self.entries:
                self.emptied.set()
        if isinstance(connection, web.WebSocketResponse):
            if not connection.closed:
                await connection.close(code=code, message=reason[:120].encode())
        elif connection is not None:
            await connection.close()

    async def drain(self, seconds: float, hurry: asyncio.Event | None = None) -> None:
        """Refuse new sessions, let the open ones finish for up to `seconds` (or until `hurry` is set), then close
        them with 1001."""
        self.admission.draining = True
        self.metrics.draining.set(1)
        if self.entries:
            waits = [asyncio.ensure_future(self.emptied.wait())]
            if hurry is not None:
                waits.append(asyncio.ensure_future(hurry.wait()))
            await asyncio.wait(waits, timeout=seconds, return_when=asyncio.FIRST_COMPLETED)
            for wait in waits:
                wait.cancel()
        await asyncio.gather(*(self.close(c, CLOSE_GOING_AWAY, "the server is going away")
                               for c in list(self.entries)))

    # -- routes -------------------------------------------------------------------------------------------------
    async def leave(self, request: web.Request) -> web.Response:
        """POST /close: the page is leaving (its Stop button, or unload through sendBeacon)."""
        connection, _ = self.own_session(request, await read_text(request))
        await self.close(connection)
        return web.Response(status=204)

    async def stats(self, request: web.Request) -> web.Response:
        return web.json_response([{"session": entry.session_id, "transport": entry.transport,
                                   "seconds": round(time.monotonic() - entry.started, 3), **entry.session.summary()}
                                  for entry in self.entries.values()])

    async def health(self, request: web.Request) -> web.Response:
        """Sessions holding a place (until their threads have let go of them) and the threads running them: both
        drop to 0 when every page has left."""
        threads = sum(thread.name == self.thread_name for thread in threading.enumerate())
        return web.json_response({"sessions": self.admission.open, self.threads_key: threads})

    async def shutdown(self, app: web.Application) -> None:
        await asyncio.gather(*(self.close(c, CLOSE_GOING_AWAY, "the server is going away")
                               for c in list(self.entries)))
        for task in list(self.tasks):
            task.cancel()

    def route(self, app: web.Application) -> None:
        """The shared routes and the shutdown hook."""
        app.router.add_get("/stats", self.stats)
        app.router.add_get("/health", self.health)
        app.router.add_post("/close", self.leave)
        app.on_shutdown.append(self.shutdown)


async def read_body(request: web.Request, limit: int, timeout_s: float) -> bytes:
    """The request's body, `limit` bytes at most, arriving within `timeout_s`; 413 or 408 with one line."""
    if request.content_length is not None and request.content_length > limit:
        raise web.HTTPRequestEntityTooLarge(max_size=limit, actual_size=request.content_length,
                                            text=f"the body is larger than {limit} bytes")
    try:
        body = await asyncio.wait_for(_read_up_to(request, limit + 1), timeout_s)
    except asyncio.TimeoutError:  # not the builtin before Python 3.11
        raise web.HTTPRequestTimeout(text=f"the body did not arrive within {timeout_s:g} s") from None
    if len(body) > limit:
        raise web.HTTPRequestEntityTooLarge(max_size=limit, actual_size=len(body),
                                            text=f"the body is larger than {limit} bytes")
    return body


async def _read_up_to(request: web.Request, size: int) -> bytes:
    """The body until its end or `size` bytes, whichever comes first."""
    chunks, have = [], 0
    while have < size and (chunk := await request.content.read(size - have)):
        chunks.append(chunk)
        have += len(chunk)
    return b"".join(chunks)


async def read_text(request: web.Request) -> str:
    """A small text body (a session id), bounded as read_body is; 400 where it is not UTF-8."""
    limits = request.app[LIMITS]
    body = await read_body(request, min(limits.max_body_bytes, 1024), limits.body_timeout_s)
    try:
        return body.decode("utf-8")
    except UnicodeDecodeError:
        raise web.HTTPBadRequest(text="the body must be UTF-8 text") from None


async def read_json(request: web.Request) -> dict:
    """An application/json body holding an object, bounded as read_body is; 415 or 400 with one line."""
    if request.content_type != "application/json":
        raise web.HTTPUnsupportedMediaType(text="the body must be application/json")
    limits = request.app[LIMITS]
    body = await read_body(request, limits.max_body_bytes, limits.body_timeout_s)
    try:
        value = json.loads(body)
    except (ValueError, UnicodeDecodeError):
        raise web.HTTPBadRequest(text="the body is not JSON") from None
    if not isinstance(value, dict):
        raise web.HTTPBadRequest(text="the body must be a JSON object")
    return value


__all__ = ["ERROR_GRACE_S", "Entry", "Sessions", "read_body", "read_json", "read_text"]
