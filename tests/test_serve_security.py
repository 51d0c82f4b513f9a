"""gt-serve against the attacks an outside review made on the live sample (docs/serve.md, "Threat model"): each
one as a test on a real server on loopback (ServerThread, tests/serve_clients.py), with the small speaker's bundle.

Bounds used here and why: the limits a test provokes are set small (1-3 s time-outs, 2-3 sessions) so that each
refusal comes within seconds; a refusal must come within 3x its limit plus 2 s (a loaded 2-core machine). Where a
client must be closed for not reading, its receive window is 4 kB, so the server's side fills within seconds."""

from __future__ import annotations

import asyncio
import json
import re
import socket
import time
import urllib.parse

import pytest
from ci_tools import need, need_module
from serve_clients import SECRET, RawWebSocket, ServerThread, http

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")


@pytest.fixture(scope="module", autouse=True)
def _serve_extra():
    need_module("jwt", "serve")
    need_module("prometheus_client", "serve")
    need_module("aiohttp", "serve")


@pytest.fixture(scope="module")
def server(small_export):
    """Client-render, with tokens, 3 sessions per client, 2 s to send the start message."""
    from gaussiantalker.serve import ServeLimits

    limits = ServeLimits(max_sessions=6, max_sessions_per_client=3, start_message_s=2.0, idle_timeout_s=2.0,
                         body_timeout_s=2.0)
    with ServerThread(small_export.path, client_render=True, secret=SECRET, limits=limits) as running:
        yield running


def _live(server, token: str | None = None, **kwargs) -> RawWebSocket:
    query = f"?token={urllib.parse.quote(token)}" if token else ""
    return RawWebSocket(server.port, f"/live{query}", **kwargs)


def _wait_sessions(server, count: int, timeout: float = 10.0) -> dict:
    admin = server.token(admin=True)
    deadline = time.monotonic() + timeout
    while True:
        health = json.loads(http(f"{server.url}/health?token={admin}")[1])
        if health["sessions"] == count or time.monotonic() > deadline:
            return health
        time.sleep(0.05)


# -- who may connect --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("path", ["/", "/bundle", "/live", "/stats", "/metrics", "/web/src/live.js"])
def test_every_route_but_the_probes_needs_a_token(server, path):
    status, body, _ = http(f"{server.url}{path}")
    assert status == 401 and body.decode().startswith("no token"), (status, body)
    assert http(f"{server.url}/healthz")[0] == 200 and http(f"{server.url}/readyz")[0] == 200


@pytest.mark.parametrize(("claims", "secret", "status", "message"), [
    ({"ttl_s": 1, "now": time.time() - 60}, None, 401, "the token has expired"),
    ({}, b"another-secret-of-thirty-two-bytes-or-more", 401, "the token is not signed with this server's secret"),
    ({"bundle": "someone-else.gtb"}, None, 403, "the token is for another bundle"),
])
def test_a_bad_token_is_refused_with_one_line(server, claims, secret, status, message):
    from gaussiantalker.serve import mint_token

    token = mint_token(secret or SECRET, claims.pop("ttl_s", 60), **claims)
    answer, body, _ = http(f"{server.url}/bundle?token={token}")
    assert (answer, body.decode()) == (status, message)
    assert http(f"{server.url}/bundle", headers={"Authorization": "Bearer garbage"})[1] == b"the token is malformed"


def test_the_bundle_claim_and_bearer_header_admit(server):
    token = server.token(bundle=server.bundle.name)
    status, body, _ = http(f"{server.url}/bundle", headers={"Authorization": f"Bearer {token}"})
    assert status == 200 and body == server.bundle.read_bytes()


def test_a_page_on_another_site_cannot_open_a_session(server):
    """Browsers apply no CORS to WebSockets: the Origin check is what stops a page elsewhere (with a stolen cookie
    or none) from driving a session, and the Host check what stops DNS rebinding."""
    token = server.token()
    socket_ = _live(server, token, headers={"Origin": "http://evil.example"})
    assert socket_.status == 403, socket_.head
    socket_.close()
    status, body, _ = http(f"{server.url}/bundle?token={token}", headers={"Host": f"evil.example:{server.port}"})
    assert (status, body) == (403, b"this server does not answer to that Host")
    status, _, _ = http(f"{server.url}/bundle?token={token}", headers={"Sec-Fetch-Site": "cross-site"})
    assert status == 403
    # the server's own origin is allowed
    same = _live(server, token, headers={"Origin": server.url})
    assert same.status == 101
    same.close()


def test_a_token_bound_to_an_origin_is_good_for_that_origin_only(server):
    token = server.token(origin="https://app.example.com")
    assert http(f"{server.url}/bundle?token={token}", headers={"Origin": "https://other.example.com"})[0] == 403
    assert http(f"{server.url}/bundle?token={token}")[0] == 200  # no Origin: not a browser's cross-site request


def test_an_offer_must_be_json(server):
    """A cross-site text/plain POST needs no preflight, so /offer takes only application/json."""
    token = server.token()
    status, body, _ = http(f"{server.url}/offer?token={token}", method="POST", body=b'{"sdp": "x"}',
                           headers={"Content-Type": "text/plain"})
    assert (status, body) == (415, b"the body must be application/json")


def test_the_counters_need_an_admin_token(server):
    token, admin = server.token(), server.token(admin=True)
    for path in ("/stats", "/health", "/metrics", "/drives?session=x"):
        status, body, _ = http(f"{server.url}{path}{'&' if '?' in path else '?'}token={token}")
        assert status == 403 and b"admin" in body, (path, status, body)
    status, body, _ = http(f"{server.url}/metrics?token={admin}")
    assert status == 200 and b"gt_serve_sessions" in body and b"gt_serve_refusals_total" in body


def test_the_page_sets_its_token_as_a_strict_cookie(server):
    token = server.token()
    status, _, headers = http(f"{server.url}/?token={token}")
    cookie = headers.get("Set-Cookie", "")
    assert status == 200 and "gt_serve_token=" in cookie and "HttpOnly" in cookie and "SameSite=Strict" in cookie
    # the token in the page's URL leaves with no Referer, and no other site may frame the page
    assert headers["Referrer-Policy"] == "no-referrer"
    assert headers["Content-Security-Policy"] == "frame-ancestors 'self'"
    assert http(f"{server.url}/bundle", headers={"Cookie": f"gt_serve_token={token}"})[0] == 200


# -- no client text reaches a program as an option ------------------------------------------------------------


def test_text_that_looks_like_an_option_is_spoken_not_obeyed(tmp_path):
    """'-f/path' made espeak-ng read the file aloud; '-q' made it wait on stdin. Both are now text on stdin: the
    speech is as long as the words themselves (espeak-ng says "f, slash, ..." for the first)."""
    from gaussiantalker.serve.text_speech import SpeechError, speak, synthesiser

    need(None if synthesiser() else "espeak-ng is not installed (Debian: apt-get install espeak-ng)", ".ci/install")
    secret = tmp_path / "secret.txt"
    secret.write_text("the secret file says " + "many words " * 200)

    async def run():
        gate = asyncio.Semaphore(2)
        bounds = {"max_chars": 1000, "timeout_s": 10.0, "max_bytes": 8 << 20, "gate": gate}
        read_aloud, _ = await speak(f"-f{secret}", **bounds)
        started = time.monotonic()
        quiet, _ = await speak("-q", **bounds)
        waited = time.monotonic() - started
        with pytest.raises(SpeechError, match="at most 1000 are spoken"):
            await speak("word " * 1000, **bounds)
        with pytest.raises(SpeechError, match="longer than 20000 bytes"):
            await speak("a long sentence that makes more than a second of speech " * 5,
                        **(bounds | {"max_bytes": 20000}))
        return read_aloud, quiet, waited

    read_aloud, quiet, waited = asyncio.run(run())
    assert read_aloud.size / 16000 < 15.0, read_aloud.size / 16000  # the file's 400 words: over two minutes
    assert waited < 5.0 and quiet.size > 0


# -- bounds on each client ----------------------------------------------------------------------------------------


def test_sessions_are_capped_per_client_and_in_all(server):
    """The 4th session of one token subject is closed with 1013 and a reason; other subjects still get theirs,
    up to the server's cap (6)."""
    sockets = []
    try:
        token = server.token(subject="one-client")
        for _ in range(3):
            ws = _live(server, token)
            ws.send(json.dumps({"source": "none"}))
            assert ws.receive()[0] == 1
            sockets.append(ws)
        refused = _live(server, token)
        code, reason, texts = refused.until_close()
        assert code == 1013 and "this client has 3 sessions open already" in reason, (code, reason)
        assert texts == [{"error": "this client has 3 sessions open already"}]
        for n in range(3):
            ws = _live(server, server.token(subject=f"other-{n}"))
            ws.send(json.dumps({"source": "none"}))
            assert ws.receive()[0] == 1
            sockets.append(ws)
        code, reason, _ = _live(server, server.token(subject="late")).until_close()
        assert code == 1013 and "the server is full (6 sessions)" in reason, (code, reason)
        assert http(f"{server.url}/readyz")[0] == 503
    finally:
        for ws in sockets:
            ws.close()
    assert _wait_sessions(server, 0)["sessions"] == 0


def test_a_page_that_never_sends_its_start_message_is_closed(server):
    started = time.monotonic()
    code, _, texts = _live(server, server.token()).until_close()
    assert code == 1008 and texts[0]["error"].startswith("bad start message: no start message within 2 s")
    assert time.monotonic() - started < 2 * 3 + 2


def test_a_client_that_does_not_read_is_closed_and_freed(server):
    """A page that stops reading (a 4 kB receive window) while the server speaks to it (37 kB/s): its queue fills
    within the outbox's 2 s past what the sockets hold, and it is closed with 1008 within 15 s; its session is
    gone."""
    ws = _live(server, server.token(), receive_buffer=4096)
    ws.send(json.dumps({"source": "file", "chunk_ms": 20}))
    started = time.monotonic()
    time.sleep(1.0)
    assert _wait_sessions(server, 1, timeout=0)["sessions"] == 1
    while time.monotonic() - started < 30 and _wait_sessions(server, 0, timeout=0)["sessions"]:
        time.sleep(0.25)
    closed_after = time.monotonic() - started
    assert _wait_sessions(server, 0, timeout=0)["sessions"] == 0, "a client that does not read was kept"
    # What the server holds for it: 64 kB of kernel buffer, aiohttp's 64 kB, and the outbox's 2 s of frames.
    assert closed_after < 15, closed_after
    try:  # the close frame waits behind the unread frames; the server may give up on it and reset
        code, reason, _ = ws.until_close()
    except ConnectionError:
        return
    assert code == 1008 and reason == "the client does not read its frames", (code, reason)


def test_interrupts_faster_than_a_person_are_refused(server):
    ws = _live(server, server.token())
    ws.send(json.dumps({"source": "none"}))
    for _ in range(50):
        ws.send(json.dumps({"interrupt": True}))
    code, reason, _ = ws.until_close()
    assert code == 1008 and reason == "more than 4 interrupts a second", (code, reason)
    assert _wait_sessions(server, 0)["sessions"] == 0


def test_a_microphone_flood_is_refused(server):
    """1.17 M tiny messages once made another session 56% late: more than 2x real time, or 100 messages a
    second (a page sends 50), closes the client."""
    ws = _live(server, server.token())
    ws.send(json.dumps({"source": "mic", "mic_rate": 16000}))
    for _ in range(400):
        ws.send(b"\x00\x00")
    code, reason, _ = ws.until_close()
    assert code == 1008 and reason == "microphone audio faster than 2x real time", (code, reason)
    ws = _live(server, server.token())
    ws.send(json.dumps({"source": "mic", "mic_rate": 16000}))
    second = b"\x00\x00" * 16000
    for _ in range(6):
        ws.send(second)
    code, reason, _ = ws.until_close()
    assert code == 1008 and reason == "microphone audio faster than 2x real time", (code, reason)


def test_slow_headers_and_idle_connections_are_closed(server):
    """A connection that drips its request head (slowloris) or sends nothing is closed at the idle time-out (2 s
    here), and /healthz keeps answering meanwhile."""
    drips = []
    for _ in range(20):
        sock = socket.create_connection(("127.0.0.1", server.port))
        sock.sendall(b"GET /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\n")
        drips.append(sock)
    started = time.monotonic()
    assert http(f"{server.url}/healthz", timeout=5)[0] == 200
    for sock in drips:
        sock.settimeout(10)
        try:
            while True:
                sock.sendall(b"X-Slow: 1\r\n")
                if not sock.recv(1024):
                    break
        except (TimeoutError, ConnectionError, OSError):
            pass
        sock.close()
    assert time.monotonic() - started < 2 * 3 + 2


def test_a_slow_body_is_timed_out(server):
    token = server.token()
    sock = socket.create_connection(("127.0.0.1", server.port))
    sock.sendall(f"POST /offer?token={token} HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\n"
                 "Content-Length: 1000\r\n\r\n{".encode())
    sock.settimeout(10)
    answer = sock.recv(4096).decode()
    sock.close()
    assert answer.startswith("HTTP/1.1 408"), answer


# -- errors -------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(("body", "message"), [
    (b"{not json", "the body is not JSON"),
    (b"[1, 2]", "the body must be a JSON object"),
    (b'{"type": "offer"}', 'an offer needs sdp (a string) and type "offer"'),
    (b'{"sdp": "v=0\\r\\nnonsense", "type": "offer", "source": "none"}', "the offer's SDP could not be used"),
    (b'{"sdp": "x", "type": "offer", "source": "radio"}', "source must be file, text or none, got 'radio'"),
])
def test_a_malformed_offer_is_a_400_with_one_line(server, body, message):
    need_module("aiortc", "serve")
    status, answer, _ = http(f"{server.url}/offer?token={server.token()}", method="POST", body=body,
                             headers={"Content-Type": "application/json"})
    assert (status, answer.decode()) == (400, message)
    assert _wait_sessions(server, 0)["sessions"] == 0


def test_a_start_that_fails_tells_the_page(server):
    ws = _live(server, server.token())
    ws.send(json.dumps({"source": "text", "text": "word " * 400}))
    code, _, texts = ws.until_close()
    assert code == 1008 and texts == [{"error": "bad start message: text is 2000 characters: at most 1000 are "
                                                "spoken"}]


def test_a_server_off_loopback_refuses_to_start_without_a_secret(small_export):
    import subprocess
    import sys

    result = subprocess.run([sys.executable, "-m", "gaussiantalker.cli.serve", str(small_export.path), "--host",
                             "0.0.0.0", "--port", "0"], capture_output=True, text=True, timeout=60)
    said = " ".join(re.sub("[\u2500-\u257f]", " ", result.stderr).split())  # typer's box drawn around it
    assert result.returncode == 2 and "a server others can reach needs tokens" in said, result.stderr


def test_repeated_tracebacks_are_logged_once_per_interval():
    import logging

    from gaussiantalker.serve.logs import RepeatedTracebacks

    records = []
    logger = logging.getLogger("test_serve_security.repeated")
    logger.propagate = False
    handler = logging.Handler()
    handler.emit = records.append
    logger.addHandler(handler)
    logger.addFilter(RepeatedTracebacks(interval_s=60))
    for _ in range(100):
        try:
            raise ValueError("same place")
        except ValueError as error:
            logger.error("failed", exc_info=error)
    logger.error("a line without a traceback")
    assert len(records) == 101 and [bool(r.exc_info) for r in records].count(True) == 1
    assert records[1].getMessage() == "failed (ValueError: same place; its traceback as logged before)"
    assert records[-1].getMessage() == "a line without a traceback"


def test_an_offer_whose_peer_never_connects_expires(small_export):
    """An offer whose peer never answers (no ICE from it, ever) held a session and its thread for ever; here it is
    closed after offer_connect_s (1 s in this server) and counted as a refusal."""
    need_module("aiortc", "serve")
    from aiortc import RTCPeerConnection

    from gaussiantalker.serve import ServeLimits

    async def offer() -> str:
        pc = RTCPeerConnection()
        pc.createDataChannel("drives")
        pc.addTransceiver("audio", direction="recvonly")
        await pc.setLocalDescription(await pc.createOffer())
        sdp = pc.localDescription.sdp
        await pc.close()  # the page goes away before it ever connects
        return sdp

    sdp = asyncio.run(offer())
    limits = ServeLimits(offer_connect_s=1.0)
    with ServerThread(small_export.path, client_render=True, secret=SECRET, limits=limits) as running:
        status, body, _ = http(f"{running.url}/offer?token={running.token()}", method="POST",
                               body=json.dumps({"sdp": sdp, "type": "offer", "source": "none"}).encode(),
                               headers={"Content-Type": "application/json"})
        assert status == 200, body
        assert _wait_sessions(running, 1, timeout=0)["sessions"] == 1
        assert _wait_sessions(running, 0, timeout=1 * 3 + 2)["sessions"] == 0
        metrics = http(f"{running.url}/metrics?token={running.token(admin=True)}")[1].decode()
        assert 'gt_serve_refusals_total{reason="offer_not_connected"} 1.0' in metrics


def test_connections_past_the_cap_are_turned_away(small_export):
    """Connections are capped (--max-connections, 4 here): the 5th gets `503 too many connections` and is closed
    before anything is read; once one closes, a new one is served."""
    from gaussiantalker.serve import ServeLimits

    with ServerThread(small_export.path, client_render=True, secret=SECRET,
                      limits=ServeLimits(max_connections=4)) as running:
        held = [socket.create_connection(("127.0.0.1", running.port)) for _ in range(4)]
        time.sleep(0.2)
        extra = socket.create_connection(("127.0.0.1", running.port))
        extra.settimeout(5)
        answer = extra.recv(1024)
        extra.close()
        assert answer.startswith(b"HTTP/1.1 503") and answer.endswith(b"too many connections\r\n"), answer
        held.pop().close()
        time.sleep(0.2)
        assert http(f"{running.url}/healthz")[0] == 200
        for sock in held:
            sock.close()
