"""What the gt-serve tests share: a server in a thread of this process (its own event loop, stopped by an
event), free ports, a token minted with the tests' secret, and a raw WebSocket client that can refuse to read
(a small receive window) the way an attacker's client does."""

from __future__ import annotations

import asyncio
import base64
import json
import os
import socket
import struct
import threading
import urllib.error
import urllib.request
from pathlib import Path

SECRET = b"0123456789abcdef0123456789abcdef-tests-only"


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


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


def http(url: str, *, method: str = "GET", body: bytes | None = None, headers: dict | None = None,
         timeout: float = 15.0) -> tuple[int, bytes, dict]:
    """(status, body, headers) of one request; HTTP errors are answers, not exceptions."""
    request = urllib.request.Request(url, data=body, method=method, headers=headers or {})
    try:
        with urllib.request.urlopen(request, timeout=timeout) as response:
            return response.status, response.read(), dict(response.headers)
    except urllib.error.HTTPError as error:
        return error.code, error.read(), dict(error.headers)


class RawWebSocket:
    """A WebSocket client on a plain socket: the handshake, masked frames out, frames in, and a receive buffer
    as small as asked (a client that reads nothing then holds the server's frames in the server)."""

    def __init__(self, port: int, path: str, *, headers: dict | None = None, receive_buffer: int | None = None,
                 host: str | None = None, timeout: float = 15.0) -> None:
        self.sock = socket.socket()
        if receive_buffer is not None:
            self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, receive_buffer)
        self.sock.settimeout(timeout)
        self.sock.connect(("127.0.0.1", port))
        key = base64.b64encode(os.urandom(16)).decode()
        lines = [f"GET {path} HTTP/1.1", f"Host: {host or f'127.0.0.1:{port}'}", "Upgrade: websocket",
                 "Connection: Upgrade", f"Sec-WebSocket-Key: {key}", "Sec-WebSocket-Version: 13",
                 *(f"{k}: {v}" for k, v in (headers or {}).items())]
        self.sock.sendall(("\r\n".join(lines) + "\r\n\r\n").encode())
        head = b""
        while b"\r\n\r\n" not in head:
            chunk = self.sock.recv(1)
            if not chunk:
                break
            head += chunk
        self.status = int(head.split(b" ", 2)[1]) if head else 0
        self.head = head.decode("latin-1")

    def send(self, payload: bytes | str) -> None:
        opcode = 1 if isinstance(payload, str) else 2
        data = payload.encode() if isinstance(payload, str) else payload
        mask = os.urandom(4)
        length = len(data)
        header = bytes([0x80 | opcode])
        if length < 126:
            header += bytes([0x80 | length])
        elif length < 65536:
            header += bytes([0x80 | 126]) + struct.pack(">H", length)
        else:
            header += bytes([0x80 | 127]) + struct.pack(">Q", length)
        masked = bytes(b ^ mask[i % 4] for i, b in enumerate(data))
        self.sock.sendall(header + mask + masked)

    def _exact(self, count: int) -> bytes:
        data = b""
        while len(data) < count:
            chunk = self.sock.recv(count - len(data))
            if not chunk:
                raise ConnectionError("closed")
            data += chunk
        return data

    def receive(self) -> tuple[int, bytes]:
        """(opcode, payload) of the next frame: 1 text, 2 binary, 8 close (payload: code u16 + reason)."""
        first, second = self._exact(2)
        length = second & 0x7F
        if length == 126:
            (length,) = struct.unpack(">H", self._exact(2))
        elif length == 127:
            (length,) = struct.unpack(">Q", self._exact(8))
        return first & 0x0F, self._exact(length)

    def until_close(self, limit: int = 100000) -> tuple[int, str, list]:
        """Read until the close frame: (code, reason, the text messages before it, parsed)."""
        texts = []
        for _ in range(limit):
            opcode, payload = self.receive()
            if opcode == 1:
                texts.append(json.loads(payload))
            elif opcode == 8:
                code = struct.unpack(">H", payload[:2])[0] if len(payload) >= 2 else 1005
                return code, payload[2:].decode("utf-8", "replace"), texts
        raise AssertionError("no close frame")

    def close(self) -> None:
        self.sock.close()
