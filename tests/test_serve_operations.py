"""gt-serve's operations (docs/serve.md, "Operations"): the drain on SIGTERM (readiness off, new sessions refused
with 1013, open ones running on until --drain-s, then closed with 1001, the process exiting 0), a second signal
cutting the drain short, and the metrics a session leaves. A real `gt-serve` process on loopback with the small
speaker; bounds: the drain's 2 s plus 3 s for a loaded machine."""

from __future__ import annotations

import json
import signal
import sys
import time

from ci_tools import need_module
from serve_clients import SECRET, RawWebSocket, ServerThread, free_port, http

from tools.bench.live_clients import serving


def _server(bundle, port: int, secret_file, drain_s: float):
    return serving([sys.executable, "-m", "gaussiantalker.cli.serve", str(bundle), "--client-render", "--port",
                    str(port), "--secret-file", str(secret_file), "--drain-s", str(drain_s)],
                   f"http://127.0.0.1:{port}/readyz", 120, name="gt-serve")


def _token(**claims) -> str:
    from gaussiantalker.serve import mint_token

    return mint_token(SECRET, 60.0, **claims)


def _open_session(port: int) -> RawWebSocket:
    ws = RawWebSocket(port, f"/live?token={_token()}")
    ws.send(json.dumps({"source": "file", "chunk_ms": 20}))
    assert json.loads(ws.receive()[1])["fps"] == 25
    return ws


def test_sigterm_drains_then_closes_with_1001(small_export, tmp_path):
    need_module("aiohttp", "serve")
    secret = tmp_path / "secret.txt"
    secret.write_bytes(SECRET)
    port = free_port()
    process = _server(small_export.path, port, secret, drain_s=2.0)
    try:
        ws = _open_session(port)
        for _ in range(10):  # frames flow
            assert ws.receive()[0] == 2
        process.send_signal(signal.SIGTERM)
        signalled = time.monotonic()
        deadline = signalled + 5
        while http(f"http://127.0.0.1:{port}/readyz")[0] != 503 and time.monotonic() < deadline:
            time.sleep(0.05)
        status, body, _ = http(f"http://127.0.0.1:{port}/readyz")
        assert status == 503 and json.loads(body)["reason"] == "draining"
        code, reason, texts = RawWebSocket(port, f"/live?token={_token()}").until_close()
        assert code == 1013 and "draining" in reason and "draining" in texts[0]["error"]
        frames = 0
        while True:  # the open session runs on until the drain's end
            opcode, payload = ws.receive()
            if opcode == 8:
                break
            frames += opcode == 2
        closed_after = time.monotonic() - signalled
        assert int.from_bytes(payload[:2], "big") == 1001 and payload[2:] == b"the server is going away"
        assert 1.5 <= closed_after <= 2 + 3, closed_after
        assert frames >= 25, frames  # about 50 frames in the 2 s
        assert process.wait(timeout=15) == 0
    finally:
        if process.poll() is None:
            process.kill()
        log = process.communicate(timeout=30)[0]
    assert "Traceback" not in log, log[-3000:]
    assert log.count("started: client-render") == 1 and "the server is going away" in log, log[-3000:]


def test_a_second_signal_ends_the_drain_at_once(small_export, tmp_path):
    need_module("aiohttp", "serve")
    secret = tmp_path / "secret.txt"
    secret.write_bytes(SECRET)
    port = free_port()
    process = _server(small_export.path, port, secret, drain_s=60.0)
    try:
        ws = _open_session(port)
        process.send_signal(signal.SIGTERM)
        time.sleep(0.5)
        signalled = time.monotonic()
        process.send_signal(signal.SIGINT)
        code, _, _ = ws.until_close()
        assert code == 1001 and time.monotonic() - signalled < 3, time.monotonic() - signalled
        assert process.wait(timeout=15) == 0
    finally:
        if process.poll() is None:
            process.kill()
        process.communicate(timeout=30)


def test_metrics_count_sessions_frames_and_refusals(small_export, tmp_path):
    need_module("prometheus_client", "serve")
    from gaussiantalker.serve import ServeLimits

    with ServerThread(small_export.path, client_render=True, secret=SECRET,
                      limits=ServeLimits(max_sessions_per_client=1)) as running:
        ws = _open_session(running.port)
        for _ in range(30):
            ws.receive()
        http(f"{running.url}/bundle")  # no token: a refusal
        metrics = http(f"{running.url}/metrics?token={running.token(admin=True)}")[1].decode()
        ws.close()
    values = {line.rsplit(" ", 1)[0]: float(line.rsplit(" ", 1)[1]) for line in metrics.splitlines()
              if line and not line.startswith("#")}
    assert values['gt_serve_sessions{mode="client-render"}'] == 1
    assert values['gt_serve_sessions_started_total{mode="client-render"}'] == 1
    assert values['gt_serve_frames_total{mode="client-render"}'] >= 30
    assert values['gt_serve_frame_seconds_count{mode="client-render"}'] >= 30
    assert values['gt_serve_refusals_total{reason="token"}'] == 1
    assert values["gt_serve_draining"] == 0


def test_the_secret_and_token_commands(tmp_path):
    """`gt-serve secret -o F` writes a 256-bit secret readable by its owner only (and refuses to overwrite it);
    `gt-serve token` prints a token that secret verifies, with the claims asked for."""
    need_module("jwt", "serve")
    import stat
    import subprocess

    from gaussiantalker.serve import read_secret, verify_token

    secret = tmp_path / "secret.txt"
    command = [sys.executable, "-m", "gaussiantalker.cli.serve"]
    subprocess.run([*command, "secret", "-o", str(secret)], check=True, capture_output=True, timeout=60)
    assert stat.S_IMODE(secret.stat().st_mode) == 0o600 and len(read_secret(secret)) == 64
    again = subprocess.run([*command, "secret", "-o", str(secret)], capture_output=True, text=True, timeout=60)
    assert again.returncode == 2 and "exists" in again.stderr
    token = subprocess.run([*command, "token", "--secret-file", str(secret), "--ttl-s", "30", "--subject", "app-7",
                            "--bundle", "speaker.gtb", "--admin"], check=True, capture_output=True, text=True,
                           timeout=60).stdout.strip()
    claims = verify_token(token, read_secret(secret))
    assert (claims.subject, claims.bundle, claims.admin) == ("app-7", "speaker.gtb", True)
    assert 25 <= claims.expires - time.time() <= 31
