"""Running a `gt-serve` app: the listener with its connection cap and idle/header time-out, and the drain on
SIGTERM or SIGINT (refuse new sessions, let open ones finish up to drain_s, close the rest with 1001; a second
signal closes them at once)."""

from __future__ import annotations

import asyncio
import signal
from collections.abc import Callable

from aiohttp import web

from .keys import LIMITS, METRICS, SESSIONS
from .logs import log

CLOSE_REFUSED = (b"HTTP/1.1 503 Service Unavailable\r\nConnection: close\r\nContent-Length: 22\r\n\r\n"
                 b"too many connections\r\n")


class _Refused(asyncio.Protocol):
    """A connection past the cap: answered 503 and closed at once, before anything is read."""

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        transport.write(CLOSE_REFUSED)  # type: ignore[attr-defined]
        transport.close()


async def serve_app(app: web.Application, host: str, port: int, *,
                    on_listening: Callable[[int], None] | None = None, stop: asyncio.Event | None = None) -> None:
    """Serve `app` on host:port until SIGTERM/SIGINT (or `stop` is set), then drain. `on_listening(port)` is
    called once the socket listens (port 0 picks a free one)."""
    limits, sessions, metrics = app[LIMITS], app[SESSIONS], app[METRICS]
    # keepalive_timeout closes a connection that has not sent a whole request head this long after it opened or
    # after its last answer: slow headers and idle keep-alives alike (aiohttp arms it at the connection's start).
    runner = web.AppRunner(app, keepalive_timeout=limits.idle_timeout_s, access_log=None)
    await runner.setup()
    server = runner.server
    metrics.connections.set_function(lambda: len(server.connections))

    def protocol() -> asyncio.Protocol:
        if len(server.connections) >= limits.max_connections:
            metrics.refuse("connections")
            return _Refused()
        return server()

    loop = asyncio.get_running_loop()
    listener = await loop.create_server(protocol, host, port, reuse_address=True, backlog=256)
    stop = stop or asyncio.Event()
    hurry = asyncio.Event()  # a second signal: close what is left at once

    def on_signal() -> None:
        (hurry if stop.is_set() else stop).set()

    for signum in (signal.SIGTERM, signal.SIGINT):
        try:
            loop.add_signal_handler(signum, on_signal)
        except (NotImplementedError, RuntimeError):  # not the main thread, or no signals on this platform
            pass
    bound = listener.sockets[0].getsockname()[1]
    if on_listening is not None:
        on_listening(bound)
    try:
        await stop.wait()
        log.info("stopping: draining %d sessions (up to %g s)", len(sessions.entries), limits.drain_s)
        await sessions.drain(limits.drain_s, hurry)
    finally:
        listener.close()
        await runner.cleanup()


def run(app: web.Application, host: str, port: int, on_listening: Callable[[int], None] | None = None) -> None:
    """serve_app in a fresh event loop (what `gt-serve` runs)."""
    asyncio.run(serve_app(app, host, port, on_listening=on_listening))


__all__ = ["run", "serve_app"]
