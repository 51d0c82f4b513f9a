"""Bounds on everything a client can make the server hold or do (docs/serve.md, "Limits"): the settings, the
session admission by client, and the rate meters that close a client sending faster than a page ever would."""

from __future__ import annotations

import os
import threading
import time
from dataclasses import dataclass, field


@dataclass(frozen=True)
class ServeLimits:
    """Every bound of a server, each named for what it defends (docs/serve.md has the table)."""

    max_sessions: int | None = None  # sessions open at once; None: 100 client-rendered, 2 per core in pixel mode
    max_sessions_per_client: int = 4  # by the token's subject, or by address where no token is asked
    max_connections: int = 512  # TCP connections at once (pages, their modules, sockets); more are closed at once
    idle_timeout_s: float = 10.0  # a connection without a whole request head this long after it opened or was last
    #                               answered is closed (slow headers, idle keep-alives)
    body_timeout_s: float = 10.0  # a request body must arrive within this
    max_body_bytes: int = 256 * 1024  # an offer's or a close's body, at most
    offer_connect_s: float = 15.0  # a WebRTC offer whose peer has not connected by then is closed
    start_message_s: float = 10.0  # a WebSocket page's start message must come this soon
    outbox_frames: int = 50  # frames (2 s) queued for a client that does not read; past it: closed with 1008
    interrupts_per_s: float = 4.0  # barge-ins a second, sustained (a burst of interrupt_burst allowed)
    interrupt_burst: int = 8
    mic_realtime_factor: float = 2.0  # microphone audio at most this times real time (a burst of mic_burst_s)
    mic_burst_s: float = 2.0
    mic_messages_per_s: float = 100.0  # microphone messages a second (a page sends 50); a burst of 2 s of them
    max_queued_s: float = 30.0  # audio waiting in a session, at most (runtime LiveSession max_queued_s)
    max_text_chars: int = 1000  # text the server speaks for a page
    speech_timeout_s: float = 10.0  # espeak-ng's time to speak it
    max_speech_bytes: int = 8 * 1024 * 1024  # espeak-ng's output, at most (about 3 minutes at 22 kHz)
    speech_processes: int = field(default_factory=lambda: os.cpu_count() or 2)  # espeak-ng runs at once
    drain_s: float = 30.0  # on SIGTERM, open sessions may finish this long before they are closed with 1001

    def session_cap(self, pixel: bool) -> int:
        """max_sessions, or its default for the mode."""
        if self.max_sessions is not None:
            return self.max_sessions
        return 2 * (os.cpu_count() or 2) if pixel else 100

    def check(self) -> None:
        """ValueError naming the first bound that is not a positive number."""
        for name, value in vars(self).items():
            if value is not None and not (isinstance(value, (int, float)) and value > 0):
                raise ValueError(f"limit {name} must be a positive number, got {value!r}")


class TokenBucket:
    """A rate meter: `rate` units a second, `burst` at most in store; take(n) says whether n units fit now."""

    def __init__(self, rate: float, burst: float) -> None:
        self.rate, self.burst = float(rate), float(burst)
        self._level, self._at = float(burst), time.monotonic()

    def take(self, amount: float = 1.0) -> bool:
        now = time.monotonic()
        self._level = min(self.burst, self._level + (now - self._at) * self.rate)
        self._at = now
        if amount > self._level:
            return False
        self._level -= amount
        return True


class Admission:
    """Sessions open, in all and per client; `admit(client)` returns None (a place is taken: `release` it) or the
    reason the session is refused. Thread-safe."""

    def __init__(self, total: int, per_client: int) -> None:
        self.total, self.per_client = total, per_client
        self._by_client: dict[str, int] = {}
        self._open = 0
        self._lock = threading.Lock()
        self.draining = False

    def admit(self, client: str) -> str | None:
        with self._lock:
            if self.draining:
                return "the server is draining; connect again to another replica"
            if self._open >= self.total:
                return f"the server is full ({self.total} sessions); try again later"
            if self._by_client.get(client, 0) >= self.per_client:
                return f"this client has {self.per_client} sessions open already"
            self._open += 1
            self._by_client[client] = self._by_client.get(client, 0) + 1
            return None

    def release(self, client: str) -> None:
        with self._lock:
            left = self._by_client.get(client, 0) - 1
            if left < 0:
                return
            self._open -= 1
            if left:
                self._by_client[client] = left
            else:
                del self._by_client[client]

    @property
    def open(self) -> int:
        return self._open


__all__ = ["Admission", "ServeLimits", "TokenBucket"]
