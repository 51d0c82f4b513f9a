"""What the gt-serve tests share: a server in a thread of this process (its own event loop, stopped by an
event), free ports, a token minted with the tests' secret; and, from the attack bench, `http` and a raw WebSocket
client that can refuse to read (a small receive window) the way an attacker's client does."""

from __future__ import annotations

import asyncio
import os
import random
import socket
import threading
from pathlib import Path

from tools.bench.serve_attacks import RawWebSocket, http

SECRET = b"0123456789abcdef0123456789abcdef-tests-only"


# Ports handed to the tests' servers: below Linux's ephemeral range (32768-60999), so that no outgoing connection
# (nginx to a replica, a browser, a client) takes a port between its choice and the server's bind, and never the
# same one twice in a run (a port the kernel hands out with bind(0) can come back at the next call).
_PORT_RANGE = (20000, 32000)
_handed_out: set[int] = set()
_ports = random.Random(os.getpid())


def free_port() -> int:
    """A loopback port nothing listens on now and no earlier call of this run returned."""
    for _ in range(1000):
        port = _ports.randrange(*_PORT_RANGE)
        if port in _handed_out:
            continue
        with socket.socket() as sock:
            try:
                sock.bind(("127.0.0.1", port))
            except OSError:
                continue
        _handed_out.add(port)
        return port
    raise RuntimeError(f"no free loopback port in {_PORT_RANGE}")


class ServerThread:
    """gaussiantalker.serve's app for `bundle` served on 127.0.0.1 in a thread: `with ServerThread(...) as s:`
    then s.port, s.url, s.token(...)."""

    def __init__(self, bundle: Path, **options) -> None:
        from gaussiantalker.serve.app import ServeOptions, make_app

        self.app = make_app(bundle, ServeOptions(**options))
        self.secret = options.get("secret")
        self.bundle = Path(bundle)
        self._stop: asyncio.Event | None = None
        self._ready = threading.Event()
        self.port = 0
        self.error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        from gaussiantalker.serve.server import serve_app

        async def main() -> None:
            self._stop = asyncio.Event()
            self.loop = asyncio.get_running_loop()

            def listening(port: int) -> None:
                self.port = port
                self._ready.set()

            await serve_app(self.app, "127.0.0.1", 0, on_listening=listening, stop=self._stop)

        try:
            asyncio.run(main())
        except BaseException as error:  # noqa: BLE001 (reported by __enter__ or the test)
            self.error = error
            self._ready.set()

    def __enter__(self) -> ServerThread:
        self._thread.start()
        assert self._ready.wait(60), "the server did not start"
        if self.error is not None:
            raise self.error
        return self

    def stop(self) -> None:
        """Drain and stop (what SIGTERM does)."""
        if self._stop is not None and self._thread.is_alive():
            self.loop.call_soon_threadsafe(self._stop.set)
        self._thread.join(60)

    def __exit__(self, *exc) -> None:
        self.stop()

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def token(self, **claims) -> str:
        from gaussiantalker.serve import mint_token

        return mint_token(self.secret, claims.pop("ttl_s", 60.0), **claims)


__all__ = ["RawWebSocket", "SECRET", "ServerThread", "free_port", "http"]
