"""What the gt-serve tests share: a server in a thread of this process (its own event loop, stopped by an
event), free ports, a token minted with the tests' secret; and, from the attack bench, `http` and a raw WebSocket
client that can refuse to read (a small receive window) the way an attacker's client does."""

from __future__ import annotations

import asyncio
import threading
from pathlib import Path

from tools.bench.ports import free_port
from tools.bench.serve_attacks import RawWebSocket, http

SECRET = b"0123456789abcdef0123456789abcdef-tests-only"


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
