"""The attacks of docs/serve.md's threat model, run against `gt-serve BUNDLE --client-render` (tokens on) and, with a
baseline, against an older server script (49c2f1e's `samples/live_server.py`, on that commit's package): each
attack says "held" or "broke" with what was observed (status, close code, speaking frames, seconds).

Each server runs on loopback in a process of its own, one after the other, its output in a log file. gt-serve signs
tokens with a fresh secret in a temporary folder. The token attacks send none; every other attack carries a valid
token, as a client with a stolen or its own token would (each attack its own subject, since sessions are counted
per subject; the Host attack an admin one, so that only the Host check can refuse it). The baseline asks no token.

The attacks that only wait for the server (the text source, the drip-fed head, the silent WebSocket, the client
that does not read) run at once, after the quick ones, so that a server's run takes little longer than the
longest of them.
"""

from __future__ import annotations

import asyncio
import base64
import json
import os
import re
import shutil
import socket
import struct
import subprocess
import sys
import tempfile
import time
import urllib.error
import urllib.request
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path

from .live_clients import SERVE_MODULE, SERVER_START_S, SPEECH, Baseline, serving
from .ports import free_port

NEW_LABEL = "gt-serve"
TOKEN_TTL_S = 600.0  # longer than a server's whole run
FRAME_PACKET_HEADER = 12  # a frame packet's bytes before its drive message (docs/serve.md, "Wire format")
DRIVE_FLAGS = 6  # the drive message's flags byte; bit 0: speaking
TCP_ESTABLISHED = 1  # tcp_info's first byte while the connection is open both ways
OPCODE_TEXT, OPCODE_BINARY, OPCODE_CLOSE = 1, 2, 8


@dataclass(frozen=True)
class Target:
    """A server under attack: its label in the report, its loopback port, and the secret its tokens are signed
    with (None: a server that asks no token)."""

    label: str
    port: int
    secret: bytes | None = None

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def query(self, subject: str, admin: bool = False) -> str:
        """`?token=...` for a valid token of `subject` ("" where the server asks none)."""
        if self.secret is None:
            return ""
        from gaussiantalker.serve import mint_token

        return "?token=" + mint_token(self.secret, TOKEN_TTL_S, subject=f"gt-bench-{subject}", admin=admin)


@dataclass(frozen=True)
class Outcome:
    """What one attack observed: `held` (None: it could not run here), the evidence, and its seconds."""

    held: bool | None
    evidence: str
    seconds: float = 0.0


@dataclass
class Watch:
    """What a WebSocket client read before a deadline or the server's close: the close code and reason (None: not
    closed), seconds until then, frame packets and those marked speaking, text messages, and how the socket ended
    where it ended without a close frame."""

    code: int | None = None
    reason: str = ""
    seconds: float = 0.0
    frames: int = 0
    speaking: int = 0
    texts: list | None = None
    ended: str = ""

    @property
    def closed(self) -> bool:
        return self.code is not None or bool(self.ended)

    def describe(self) -> str:
        """The close as the report shows it."""
        if self.code is not None:
            reason = f" \"{self.reason}\"" if self.reason else ""
            return f"closed {self.code}{reason} after {self.seconds:.1f} s"
        if self.ended:
            return f"{self.ended} after {self.seconds:.1f} s"
        return f"still open after {self.seconds:.1f} s"


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
    """A WebSocket client on a plain socket (the handshake, masked frames out, frames in) whose receive buffer can
    be made as small as a client that does not read would leave it."""

    def __init__(self, port: int, path: str, *, headers: dict | None = None, receive_buffer: int | None = None,
                 host: str | None = None, timeout: float = 15.0) -> None:
        self.sock = socket.socket()
        if receive_buffer is not None:
            self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, receive_buffer)
        self.sock.settimeout(timeout)
        self.sock.connect(("127.0.0.1", port))
        key = base64.b64encode(os.urandom(16)).decode()
        lines = [f"GET {path} HTTP/1.1", f"Host: {host or f'127.0.0.1:{port}'}", "Upgrade: websocket",
                 "Connection: Upgrade",
                 f"Sec-WebSocket-Key: {key}", "Sec-WebSocket-Version: 13",
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

    def refusal(self) -> str:
        """A refused handshake's status and the first line of its body."""
        match = re.search(r"content-length:\s*(\d+)", self.head, re.IGNORECASE)
        body = self._exact(min(int(match.group(1)), 200)) if match else b""
        return f"{self.status} \"{_first_line(body)}\""

    def send(self, payload: bytes | str) -> None:
        opcode = OPCODE_TEXT if isinstance(payload, str) else OPCODE_BINARY
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

    def watch(self, seconds: float, *, until_text: bool = False) -> Watch:
        """Read for up to `seconds` (`until_text`: or until the first text message); stops at the server's close."""
        seen, started = Watch(texts=[]), time.monotonic()
        while (left := started + seconds - time.monotonic()) > 0:
            self.sock.settimeout(left)
            try:
                opcode, payload = self.receive()
            except TimeoutError:
                break
            except OSError as error:  # ConnectionError included: the server went without a close frame
                seen.ended = "connection ended" if isinstance(error, ConnectionError) else type(error).__name__
                break
            if opcode == OPCODE_CLOSE:
                seen.code = struct.unpack(">H", payload[:2])[0] if len(payload) >= 2 else 1005
                seen.reason = payload[2:].decode("utf-8", "replace")
                break
            if opcode == OPCODE_BINARY:
                seen.frames += 1
                speaking = len(payload) > FRAME_PACKET_HEADER + DRIVE_FLAGS
                seen.speaking += speaking and payload[FRAME_PACKET_HEADER + DRIVE_FLAGS] & 1
            elif opcode == OPCODE_TEXT:
                seen.texts.append(json.loads(payload))
                if until_text:
                    break
        seen.seconds = time.monotonic() - started
        return seen

    def until_close(self, limit: int = 100000) -> tuple[int, str, list]:
        """Read until the close frame: (code, reason, the text messages before it, parsed)."""
        texts = []
        for _ in range(limit):
            opcode, payload = self.receive()
            if opcode == OPCODE_TEXT:
                texts.append(json.loads(payload))
            elif opcode == OPCODE_CLOSE:
                code = struct.unpack(">H", payload[:2])[0] if len(payload) >= 2 else 1005
                return code, payload[2:].decode("utf-8", "replace"), texts
        raise AssertionError("no close frame")

    def close(self) -> None:
        self.sock.close()


def _first_line(body: bytes, limit: int = 80) -> str:
    """A reply's first line, cut at `limit` characters."""
    lines = body.decode("utf-8", "replace").strip().splitlines()
    return (lines[0][:limit] + ("..." if len(lines[0]) > limit else "")) if lines else ""


def _session(target: Target, subject: str, start: dict, **options) -> tuple[RawWebSocket, Watch]:
    """A /live WebSocket with a valid token that has sent `start`, and what it read up to the server's answer."""
    ws = RawWebSocket(target.port, "/live" + target.query(subject), **options)
    ws.send(json.dumps(start))
    return ws, ws.watch(60.0, until_text=True)


def _answered(seen: Watch) -> bool:
    """Whether the server answered a start message with a session."""
    return bool(seen.texts) and "session" in seen.texts[-1]


# -- the attacks --------------------------------------------------------------------------------------------------


def cross_site_websocket(target: Target) -> Outcome:
    """Held: a /live WebSocket from Origin http://evil.example (a page on another site) is not upgraded."""
    started = time.monotonic()
    ws = RawWebSocket(target.port, "/live" + target.query("origin"), headers={"Origin": "http://evil.example"})
    try:
        if ws.status != 101:
            return Outcome(True, ws.refusal(), time.monotonic() - started)
        ws.send(json.dumps({"source": "none"}))
        seen = ws.watch(10.0, until_text=True)
        said = "a session answered" if _answered(seen) else seen.describe()
        return Outcome(False, f"101 upgraded; {said}", time.monotonic() - started)
    finally:
        ws.close()


def rebound_host_stats(target: Target) -> Outcome:
    """Held: GET /stats with Host: evil.example (DNS rebinding; an admin token where one is asked) is refused."""
    started = time.monotonic()
    status, body, _ = http(f"{target.url}/stats{target.query('host', admin=True)}", headers={"Host": "evil.example"})
    seconds = time.monotonic() - started
    if status == 200:
        return Outcome(False, f"200: every session's counters ({len(json.loads(body))} sessions)", seconds)
    return Outcome(400 <= status < 500, f"{status} \"{_first_line(body)}\"", seconds)


def bundle_without_token(target: Target) -> Outcome:
    """Held: GET /bundle with no token is refused, not answered with the speaker's bundle."""
    started = time.monotonic()
    status, body, _ = http(f"{target.url}/bundle")
    seconds = time.monotonic() - started
    if status == 200:
        return Outcome(False, f"200: the bundle ({len(body) / 1e6:.1f} MB)", seconds)
    return Outcome(status in (401, 403), f"{status} \"{_first_line(body)}\"", seconds)


async def _webrtc_offer() -> str:
    """A real WebRTC offer's SDP (a data channel and an audio track to receive), its peer closed at once."""
    from aiortc import RTCPeerConnection

    pc = RTCPeerConnection()
    pc.createDataChannel("drives")
    pc.addTransceiver("audio", direction="recvonly")
    await pc.setLocalDescription(await pc.createOffer())
    sdp = pc.localDescription.sdp
    await pc.close()
    return sdp


def text_plain_offer(target: Target) -> Outcome:
    """Held: POST /offer with a real WebRTC offer as text/plain (a cross-site form post: no CORS preflight) is
    refused with 415, before the body is read."""
    body = json.dumps({"sdp": asyncio.run(_webrtc_offer()), "type": "offer", "source": "none"}).encode()
    started = time.monotonic()
    query = target.query("text-plain")
    status, answer, _ = http(f"{target.url}/offer{query}", method="POST", body=body,
                          headers={"Content-Type": "text/plain"})
    seconds = time.monotonic() - started
    if status == 200:
        session = json.loads(answer)["session"]
        http(f"{target.url}/close{query}", method="POST", body=session.encode())
        return Outcome(False, "200: a session opened (SDP answer)", seconds)
    return Outcome(status == 415, f"{status} \"{_first_line(answer)}\"", seconds)


def malformed_offer(target: Target) -> Outcome:
    """Held: POST /offer with a body that is not JSON is a 400 with one line and no traceback or path in it."""
    started = time.monotonic()
    status, answer, _ = http(f"{target.url}/offer{target.query('malformed')}", method="POST", body=b'{"sdp": "v=0',
                          headers={"Content-Type": "application/json"})
    text = answer.decode("utf-8", "replace").strip()
    leaks = re.search(r"Traceback|File \"|\.py\b|(^|\s)/\w+/", text)
    lines = len(text.splitlines())
    held = status == 400 and lines == 1 and leaks is None
    said = f"{status}, {lines} line{'s' * (lines != 1)}: \"{_first_line(answer)}\""
    return Outcome(held, said + (f"; shows {leaks.group(0).strip()!r}" if leaks else ""), time.monotonic() - started)


def interrupt_burst(target: Target) -> Outcome:
    """Held: 50 interrupts in a burst close the session with 1008 within 3 s."""
    ws, _ = _session(target, "interrupts", {"source": "none"})
    try:
        for _ in range(50):
            ws.send(json.dumps({"interrupt": True}))
        seen = ws.watch(3.0)
    except OSError as error:
        return Outcome(True, f"reset while sending ({type(error).__name__})")
    finally:
        ws.close()
    held = seen.code == 1008 and seen.seconds <= 3.0
    answers = sum("interrupted" in text for text in seen.texts)
    return Outcome(held, f"{seen.describe()}; {answers} interrupts answered", seen.seconds)


def microphone_flood(target: Target, messages: int = 1000) -> Outcome:
    """Held: 1000 two-byte microphone messages in a burst get the session closed (within 5 s)."""
    ws, _ = _session(target, "microphone", {"source": "mic", "mic_rate": 16000})
    started, sent = time.monotonic(), 0
    try:
        while sent < messages:
            ws.send(b"\x00\x00")
            sent += 1
        seen = ws.watch(5.0)
    except OSError as error:
        return Outcome(True, f"reset after {sent} messages ({type(error).__name__})", time.monotonic() - started)
    finally:
        ws.close()
    return Outcome(seen.closed, f"{sent} messages sent; {seen.describe()}", time.monotonic() - started)


def _speech_seconds(arguments: list[str], text: str = "") -> float:
    """Seconds of speech espeak-ng makes here for `arguments` (its command line after --stdout) and `text` on stdin."""
    wav = subprocess.run(["espeak-ng", "--stdout", *arguments], input=text.encode(), capture_output=True,
                         timeout=60).stdout
    return max(0, len(wav) - 44) / 2 / struct.unpack_from("<I", wav, 24)[0] if len(wav) > 44 else 0.0


def text_as_option(target: Target, seconds: float = 15.0) -> Outcome:
    """Held: the text source "-f<path of a 400-word file>" is spoken as text, not obeyed: its speaking frames are
    no more than espeak-ng's speech of the text itself (the path spelt out) plus 1 s of frames; the file read aloud
    would speak all along (about 2 minutes)."""
    if shutil.which("espeak-ng") is None:
        return Outcome(None, "not run: espeak-ng is not installed")
    with tempfile.TemporaryDirectory() as folder:
        words = Path(folder) / "words.txt"
        words.write_text("the secret file says " + "many words " * 200)
        text = f"-f{words}"
        # What the two readings would speak, for the evidence: the text's own words, or the file's.
        as_text, as_option = _speech_seconds([], text), _speech_seconds([text])
        started = time.monotonic()
        ws, answer = _session(target, "text", {"source": "text", "text": text})
        try:
            if not _answered(answer):
                return Outcome(True, f"no session: {answer.texts or answer.describe()}", time.monotonic() - started)
            seen = ws.watch(seconds)
        finally:
            ws.close()
    said = (f"{seen.speaking} speaking frames of {seen.frames} in {seen.seconds:.0f} s (espeak-ng here speaks the "
            f"text {as_text:.1f} s, the file {as_option:.0f} s)")
    as_text_frames = (as_text + 1.0) * seen.frames / max(seen.seconds, 1e-9)  # the text's own speech, 1 s slack
    return Outcome(seen.speaking <= as_text_frames, said + ("" if not seen.closed else f"; {seen.describe()}"),
                   time.monotonic() - started)


def drip_fed_head(target: Target, limit_s: float = 15.0) -> Outcome:
    """Held: a request head fed a header line a second (slowloris) has its connection closed within 15 s."""
    sock = socket.create_connection(("127.0.0.1", target.port))
    started = time.monotonic()
    try:
        sock.sendall(b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\n")
        while (left := started + limit_s - time.monotonic()) > 0:
            sock.settimeout(min(1.0, left))
            try:
                if not sock.recv(4096):  # the server's answer (a 408, say) is read past; its end is the close
                    return Outcome(True, f"closed after {time.monotonic() - started:.1f} s",
                                   time.monotonic() - started)
            except TimeoutError:
                sock.sendall(b"X-Drip: 1\r\n")
    except OSError as error:
        return Outcome(True, f"reset after {time.monotonic() - started:.1f} s ({type(error).__name__})",
                       time.monotonic() - started)
    finally:
        sock.close()
    return Outcome(False, f"still open after {limit_s:g} s", time.monotonic() - started)


def silent_websocket(target: Target, limit_s: float = 15.0) -> Outcome:
    """Held: a /live WebSocket that never sends its start message is closed within 15 s."""
    ws = RawWebSocket(target.port, "/live" + target.query("silent"))
    try:
        seen = ws.watch(limit_s)
    finally:
        ws.close()
    told = f"; told {seen.texts[0]}" if seen.texts else ""
    return Outcome(seen.closed, seen.describe() + told, seen.seconds)


def sessions_of_one_client(target: Target, count: int = 6, allowed: int = 4) -> Outcome:
    """Held: of 6 sessions one client (one token) opens at once, the first 4 are answered and the 5th and 6th
    refused with 1013."""
    started, sockets, results = time.monotonic(), [], []
    query = target.query("one-client")
    try:
        for _ in range(count):
            ws = RawWebSocket(target.port, "/live" + query)
            sockets.append(ws)
            try:
                ws.send(json.dumps({"source": "none"}))
            except OSError:
                pass  # already refused: its close is read below
            seen = ws.watch(10.0, until_text=True)
            if not _answered(seen) and not seen.closed:
                seen = ws.watch(5.0)
            results.append("answered" if _answered(seen) else seen.code or seen.ended or "no answer")
    finally:
        for ws in sockets:
            ws.close()
    held = results[:allowed] == ["answered"] * allowed and all(r == 1013 for r in results[allowed:])
    said = ", ".join(f"{results.count(r)}x {r}" for r in dict.fromkeys(results))
    return Outcome(held, f"{said} (in order: {', '.join(map(str, results))})", time.monotonic() - started)


def _tcp_open(sock: socket.socket) -> bool:
    """Whether the kernel still holds the connection open both ways (no FIN or reset has come)."""
    return sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_INFO, 8)[0] == TCP_ESTABLISHED


def _listed(target: Target, session: str) -> bool | None:
    """Whether the server's /stats still lists `session` (None where its /stats names no sessions: the baseline)."""
    if target.secret is None:
        return None
    status, body, _ = http(f"{target.url}/stats{target.query('unread-admin', admin=True)}", timeout=5)
    return status == 200 and any(entry.get("session") == session for entry in json.loads(body))


def unread_frames(target: Target, limit_s: float = 20.0) -> Outcome:
    """Held: a client that reads none of its frames after the server's answer (a 4 kB receive buffer) while the
    server speaks to it is closed by the server within 20 s."""
    ws, answer = _session(target, "unread", {"source": "file", "chunk_ms": 20}, receive_buffer=4096)
    started, gone = time.monotonic(), None
    try:
        session = answer.texts[-1].get("session", "") if answer.texts else ""
        while time.monotonic() - started < limit_s and _tcp_open(ws.sock):
            if _listed(target, session) is False:
                gone = time.monotonic() - started
                break
            time.sleep(0.25)
        waited = time.monotonic() - started
        # A close the kernel has not seen yet waits behind the unread frames: reading them out finds it at once,
        # while a server that kept the session goes on sending.
        seen = ws.watch(3.0)
    finally:
        ws.close()
    if gone is not None:
        return Outcome(True, f"its session gone from /stats after {gone:.1f} s; then read: {seen.describe()}", gone)
    if waited < limit_s:
        return Outcome(True, f"the server ended the connection after {waited:.1f} s; then read: {seen.describe()}",
                       waited)
    if seen.closed:
        return Outcome(True, f"closed within {limit_s:g} s, its close behind the unread frames: {seen.describe()}",
                       waited)
    return Outcome(False, f"open after {limit_s:g} s; reading, {seen.frames} more frames in {seen.seconds:.0f} s",
                   waited)


@dataclass(frozen=True)
class Attack:
    """One attack: its key, its name in the table, its function, and whether it only waits on the server (those
    run at once)."""

    key: str
    title: str
    run: Callable[[Target], Outcome]
    waits: bool = False

    @property
    def held_when(self) -> str:
        """What counts as held: the function's docstring, without its "Held: "."""
        return " ".join((self.run.__doc__ or "").split()).removeprefix("Held: ")


ATTACKS = (
    Attack("cross_site_websocket", "cross-site Origin WebSocket on /live", cross_site_websocket),
    Attack("rebound_host_stats", "Host: evil.example on /stats", rebound_host_stats),
    Attack("bundle_without_token", "/bundle without a token", bundle_without_token),
    Attack("text_plain_offer", "text/plain POST to /offer", text_plain_offer),
    Attack("malformed_offer", "malformed JSON offer", malformed_offer),
    Attack("interrupt_burst", "50 interrupts in a burst", interrupt_burst),
    Attack("microphone_flood", "microphone flood of tiny messages", microphone_flood),
    Attack("sessions_of_one_client", "6 sessions from one client", sessions_of_one_client),
    Attack("text_as_option", "text source `-f<file of 400 words>`", text_as_option, waits=True),
    Attack("drip_fed_head", "drip-fed request head", drip_fed_head, waits=True),
    Attack("silent_websocket", "WebSocket that never sends its start", silent_websocket, waits=True),
    Attack("unread_frames", "client that does not read its frames", unread_frames, waits=True),
)


def _attempt(attack: Attack, target: Target) -> dict:
    """One attack's outcome as a dict; an attack that raises is reported with the error, held unknown."""
    try:
        return asdict(attack.run(target))
    except Exception as error:  # reported in the table: the attack itself failed, which says nothing either way
        return asdict(Outcome(None, f"the attack failed: {type(error).__name__}: {error}"))


def run_attacks(target: Target, log: Callable[[str], None] = print) -> dict:
    """Every attack against `target`: the quick ones one by one, then the waiting ones at once; key -> outcome."""
    results = {}
    for attack in (a for a in ATTACKS if not a.waits):
        results[attack.key] = _attempt(attack, target)
        log(f"  {attack.title}: {_verdict(results[attack.key])}")
    waiting = [a for a in ATTACKS if a.waits]
    with ThreadPoolExecutor(len(waiting)) as pool:
        outcomes = pool.map(lambda attack: _attempt(attack, target), waiting)
        for attack, outcome in zip(waiting, outcomes, strict=True):
            results[attack.key] = outcome
            log(f"  {attack.title}: {_verdict(outcome)}")
    return results


def _verdict(outcome: dict) -> str:
    """"held", "broke" or "not run", and the evidence."""
    word = {True: "held", False: "broke", None: "not run"}[outcome["held"]]
    return f"{word}: {outcome['evidence']}"


def _write_secret(folder: Path) -> Path:
    """A fresh token secret in `folder` (mode 600)."""
    from gaussiantalker.serve import new_secret

    path = folder / "secret.txt"
    descriptor = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(descriptor, "w") as file:
        file.write(new_secret() + "\n")
    return path


def _stop(process, log_path: Path) -> dict:
    """Stop a server; its log's error and traceback lines counted."""
    process.terminate()
    try:
        process.wait(timeout=60)
    except Exception:  # noqa: BLE001 (it did not stop: killed)
        process.kill()
        process.wait()
    text = log_path.read_text(errors="replace") if log_path.is_file() else ""
    return {"log_error_lines": sum(" ERROR " in line or line.startswith("ERROR") for line in text.splitlines()),
            "log_tracebacks": text.count("Traceback")}


def attack_server(bundle: Path, folder: Path, baseline: Baseline | None = None,
                  log: Callable[[str], None] = print) -> dict:
    """Start gt-serve (tokens on) or, with `baseline`, the baseline script on `bundle`, run every attack, stop it;
    its label, command, seconds, log counts and outcomes."""
    port = free_port()
    arguments = [str(bundle), "--port", str(port), "--client-render", "--audio", str(SPEECH)]
    if baseline is None:
        secret_path = _write_secret(folder)
        from gaussiantalker.serve import read_secret

        command = [sys.executable, "-m", SERVE_MODULE, *arguments, "--secret-file", str(secret_path)]
        label, name, ready, options = NEW_LABEL, "gt-serve", "/readyz", {}
        target = Target(label, port, read_secret(secret_path))
    else:
        command = [sys.executable, str(baseline.script), *arguments]
        label = (baseline.commit() or baseline.script.name)[:7]
        name, ready, options = baseline.script.name, "/health", {"cwd": baseline.src, "env": baseline.env()}
        target = Target(label, port)
    log_path = folder / f"{name}.log"
    log(f"{label}: starting {name}")
    process = serving(command, f"http://127.0.0.1:{port}{ready}", SERVER_START_S, name=name, log_path=log_path,
                      **options)
    started = time.monotonic()
    try:
        outcomes = run_attacks(target, log)
    finally:
        logs = _stop(process, log_path)
    return {"label": label, "name": name, "command": command, "seconds": round(time.monotonic() - started, 1),
            **logs, "outcomes": outcomes}


def run_serve_attacks(bundle: Path, baseline: Baseline | None = None, log: Callable[[str], None] = print) -> dict:
    """Every attack against the baseline (when given) and then gt-serve: the servers' runs and each attack's
    criterion."""
    with tempfile.TemporaryDirectory(prefix="gt-serve-attacks-") as folder:
        servers = []
        if baseline is not None:
            servers.append({**attack_server(bundle, Path(folder), baseline, log), "baseline": baseline.describe()})
        servers.append(attack_server(bundle, Path(folder), None, log))
    return {"bundle": str(bundle), "servers": servers,
            "attacks": [{"key": a.key, "title": a.title, "held_when": a.held_when} for a in ATTACKS]}


def serve_attacks_table(result: dict) -> str:
    """The markdown table, attack by attack with each server's verdict side by side, and what counts as held."""
    servers = result["servers"]
    rows = ["| attack | " + " | ".join(s["label"] for s in servers) + " |", "|---|" + "---|" * len(servers)]
    for attack in result["attacks"]:
        cells = []
        for server in servers:
            outcome = server["outcomes"][attack["key"]]
            word = {True: "held", False: "**broke**", None: "not run"}[outcome["held"]]
            cells.append(f"{word}: {outcome['evidence']}".replace("|", "\\|"))
        rows.append(f"| {attack['title']} | " + " | ".join(cells) + " |")
    criteria = "\n".join(f"* {a['title']}: {a['held_when']}" for a in result["attacks"])
    runs = "; ".join(f"{s['label']} {s['seconds']:g} s (tracebacks in its log: {s['log_tracebacks']})"
                     for s in servers)
    return "\n".join(rows) + f"\n\nWhat counts as held:\n\n{criteria}\n\nAttack time per server: {runs}."


__all__ = ["ATTACKS", "Attack", "Outcome", "Target", "attack_server", "run_attacks", "run_serve_attacks",
           "serve_attacks_table"]
