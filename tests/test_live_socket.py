"""Client-render live sessions over one WebSocket (`gt-serve --client-render`, GET /live; docs/live.md
"One WebSocket a session"): a real server on loopback driven by an aiohttp client: every frame's drive and audio
in order, the voice carried sample for sample, barge-in, the microphone source and
the refusals of a bad page. No browser: tests/test_live_web.py runs the page itself, and checks the packet format
against the page's decoder."""

from __future__ import annotations

import asyncio
import json
import struct
import sys
import time
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from test_live_web import _server_module

from tools.bench.live_clients import serving
from tools.bench.ports import free_port

ROOT = Path(__file__).resolve().parents[1]


# -- a server on loopback --------------------------------------------------------------------------------------


def _start(bundle, *options: str, python: tuple[str, ...] = ("-m", "gaussiantalker.cli.serve")) -> tuple:
    """gt-serve --client-render on `bundle` (and `options`) on a free loopback port, once it answers: (process,
    port). `python`: what runs the command (a `-c` program that runs it, as the failure test does)."""
    port = free_port()
    # --debug: the admin routes (/health, /drives) without tokens, on loopback (tests/test_serve_security.py has
    # the tokens)
    process = serving([sys.executable, *python, str(bundle), "--port", str(port), "--client-render", "--debug",
                       "--drain-s", "1", *options], f"http://127.0.0.1:{port}/readyz", 120, name="gt-serve")
    return process, port


def _serve(bundle, *options: str) -> Iterator[tuple]:
    """`_start`ed for a module; after it, its log holds no traceback and a line for each session's start and
    end."""
    module = _server_module()
    process, port = _start(bundle, *options)
    yield module, port
    process.terminate()
    log = process.communicate(timeout=30)[0]
    assert "Traceback" not in log, log[-3000:]
    assert log.count("started: client-render, ws") == log.count("ended after"), log[-3000:]  # a line each


@pytest.fixture(scope="module")
def server(small_export):
    yield from _serve(small_export.path)


def _get(port: int, path: str) -> bytes:
    return urllib.request.urlopen(f"http://127.0.0.1:{port}{path}", timeout=10).read()


def _until_closed(port: int, timeout: float) -> None:
    """Wait until the server has no session and no pool thread left (AssertionError after `timeout`)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if json.loads(_get(port, "/health")) == {"sessions": 0, "driver_threads": 0}:
            return
        time.sleep(0.1)
    raise AssertionError(f"a session outlived its page by {timeout} s: {_get(port, '/health')!r}")


async def _session(port: int, start: dict, *, frames: int, interrupt_at: int | None = None, mic=None,
                   raw: bytes | str | None = None) -> dict:
    """Open /live, send `start`, read `frames` frame packets (barging in after `interrupt_at` of them; sending
    `mic` = (int16 samples, rate) in 20 ms chunks at real time, as a page does; sending `raw` after the
    answer), then leave. Returns the answer, the packets (raw bytes), the text messages and the session's
    recorded drives (GET /drives, read before leaving)."""
    import aiohttp

    out: dict = {"packets": [], "texts": []}
    async with aiohttp.ClientSession() as http, http.ws_connect(f"ws://127.0.0.1:{port}/live") as ws:
        await ws.send_str(json.dumps(start) if isinstance(start, dict) else start)
        out["answer"] = json.loads((await ws.receive(timeout=60)).data)
        if "error" in out["answer"]:
            out["closed"] = (await ws.receive(timeout=10)).type
            return out
        if mic is not None:
            samples, rate = mic
            step = rate // 50
            began = time.monotonic()
            for k, first in enumerate(range(0, samples.shape[0], step)):
                await asyncio.sleep(max(0.0, began + k * 0.02 - time.monotonic()))
                await ws.send_bytes(samples[first:first + step].astype("<i2").tobytes())
        if raw is not None:
            await (ws.send_bytes(raw) if isinstance(raw, bytes) else ws.send_str(raw))
        while len(out["packets"]) < frames:
            message = await ws.receive(timeout=30)
            if message.type == aiohttp.WSMsgType.BINARY:
                out["packets"].append(message.data)
                if len(out["packets"]) == interrupt_at:
                    await ws.send_str(json.dumps({"interrupt": True}))
            elif message.type == aiohttp.WSMsgType.TEXT:
                out["texts"].append(json.loads(message.data))
                if "error" in out["texts"][-1]:
                    break
            else:
                out["closed"] = message.type
                break
        if "closed" not in out and not (out["texts"] and "error" in out["texts"][-1]):
            session = out["answer"]["session"]
            out["drives"] = await asyncio.get_running_loop().run_in_executor(
                None, _get, port, f"/drives?session={session}")
    return out


def test_a_session_streams_every_frame_with_its_voice_and_barges_in(server):
    """The sample speech pushed in 20 ms chunks: frame packets 0, 1, 2, ... each carrying the server's recorded
    drive byte for byte and its 640 samples; the speaking frames' audio is the speech itself (16 kHz in and out:
    int16 of the same samples); after the barge-in the server says the new epoch at once and
    with its first frame, and every later frame is idle and silent."""
    from gaussiantalker.sdk.audio import load_audio

    module, port = server
    out = asyncio.run(_session(port, {"source": "file", "chunk_ms": 20}, frames=100, interrupt_at=60))
    answer = out["answer"]
    assert answer["fps"] == 25 and answer["sample_rate"] == 16000 and answer["rig"] == "flame"
    decoded = [module.decode_frame_packet(p) for p in out["packets"]]
    indexes = [d["drive"]["index"] for d in decoded]
    assert indexes == list(range(100))
    assert all(d["audio"].shape == (640,) and d["drive"]["pts"] == d["drive"]["index"] / 25 for d in decoded)
    body = out["drives"]
    recorded, at = {}, 0
    while at < len(body):
        (length,) = struct.unpack_from("<H", body, at)
        recorded[module.decode_drive(body[at + 2:at + 2 + length])["index"]] = body[at + 2:at + 2 + length]
        at += 2 + length
    for packet in out["packets"]:
        (length,) = struct.unpack_from("<I", packet, 8)
        assert packet[12:12 + length] == recorded[module.decode_frame_packet(packet)["drive"]["index"]]

    speaking = [d["drive"]["speaking"] for d in decoded]
    first = speaking.index(True)
    assert first <= 15, first  # 160 ms of lookahead and a chunk of slack, not seconds
    texts = out["texts"]
    assert texts[0] == {"interrupted": {"epoch": 1}}, texts
    told = texts[1]["interrupt"]
    assert told["epoch"] == 1 and 60 <= told["index"] <= 75, texts
    cut = told["index"]
    assert all(d["drive"]["epoch"] == (d["drive"]["index"] >= cut) for d in decoded)
    # Until the barge-in the head speaks (a loaded machine may let the pusher fall behind: an idle frame then, whose
    # audio is silence, and the speech goes on in the next); after it, never.
    assert sum(speaking[first:cut]) >= 0.9 * (cut - first) and not any(speaking[cut:])
    heard = np.concatenate([d["audio"] for d in decoded[first:cut] if d["drive"]["speaking"]])
    assert not any(d["audio"].any() for d in decoded[first:cut] if not d["drive"]["speaking"])
    speech = np.clip(np.round(load_audio(ROOT / "samples" / "demo_speech.wav", 16000) * 32768.0), -32768, 32767)
    np.testing.assert_array_equal(heard, speech[:heard.size].astype(np.int16))
    assert not any(d["audio"].any() for d in decoded[cut:])
    assert not any(d["audio"].any() for d in decoded[:first])


def test_the_microphone_source_moves_the_mouth(server):
    """source "mic": the page's int16 PCM at 48 kHz becomes the session's voice: speaking frames whose audio is
    the speech resampled to 16 kHz (loud where the speech is), and a jaw that opens."""
    from gaussiantalker.sdk.audio import load_audio

    module, port = server
    speech = load_audio(ROOT / "samples" / "demo_speech.wav", 48000)[:48000 * 3]
    pcm = np.clip(np.round(speech * 32767), -32768, 32767).astype(np.int16)
    out = asyncio.run(_session(port, {"source": "mic", "mic_rate": 48000}, frames=90, mic=(pcm, 48000)))
    decoded = [module.decode_frame_packet(p) for p in out["packets"]]
    speaking = [d for d in decoded if d["drive"]["speaking"]]
    assert len(speaking) >= 50, len(speaking)
    level = np.sqrt(np.mean(np.concatenate([d["audio"] for d in speaking]).astype(np.float64) ** 2)) / 32768
    assert level > 0.02, level
    n_expr = speaking[0]["drive"]["split"]
    jaw = [float(d["drive"]["values"][n_expr + 6]) for d in speaking]
    assert max(jaw) - min(jaw) > 0.05, (min(jaw), max(jaw))


@pytest.mark.parametrize(("start", "raw", "message"), [
    ("not json", None, "bad start message: the first message must be the start message"),
    ({"source": "radio"}, None, "bad start message: source must be file, text, none or mic, got 'radio'"),
    ({"source": "mic"}, None, "bad start message: source mic needs mic_rate"),
    ({"source": "mic", "mic_rate": 5}, None, "bad start message: mic_rate must be a whole number of Hz in "
                                             "8000..192000, got 5"),
    ({"source": "none", "chunk_ms": 0}, None, "bad start message: chunk_ms must be a number of milliseconds"),
    ({"source": "mic", "mic_rate": 16000}, b"\x01\x02\x03", "a microphone message of 3 bytes: not whole int16"),
    ({"source": "none"}, b"\x00\x00", "the page may send"),
    ({"source": "none"}, '{"say": "hi"}', "the page may send"),
])
def test_a_bad_page_is_told_why_and_its_session_ends(server, start, raw, message):
    """Each mistake gets one {"error": ...} naming it, then the socket closes and no session is left open."""
    import aiohttp

    module, port = server
    out = asyncio.run(_session(port, start, frames=1000, raw=raw))
    error = out["answer"].get("error") or out["texts"][-1].get("error")
    assert error is not None and error.startswith(message), (error, message)
    _until_closed(port, 5.0)  # (the pool's thread ends once its last session has: within a frame or two)
    assert out.get("closed") in (None, aiohttp.WSMsgType.CLOSE, aiohttp.WSMsgType.CLOSED, aiohttp.WSMsgType.CLOSING)


@pytest.fixture(scope="module")
def stream_server(ga_voice_bundle):
    """gt-serve --client-render on a bundle whose translator streams (the built-in FLAME voice), its sessions' frames
    made by two pool threads (one by default: the `server` fixture's)."""
    yield from _serve(ga_voice_bundle, "--max-sessions-per-client", "8",  # every test session is one client
                      "--drive-threads", "2")


def test_streaming_sessions_share_translator_calls(stream_server):
    """Eight sessions at once on a streaming bundle: each gets every frame in order with the voice's samples and a
    face that speaks, and /metrics shows translator calls that served more than one session (the pool's batch; with
    two pool threads and two clock phases a frame, eight sessions put at least two on one thread's phase) and the
    rows those calls made."""
    module, port = stream_server

    async def together():
        return await asyncio.gather(*[_session(port, {"source": "file", "chunk_ms": 20}, frames=60)
                                      for _ in range(8)])

    spoken = 0
    for out in asyncio.run(together()):
        decoded = [module.decode_frame_packet(p) for p in out["packets"]]
        assert [d["drive"]["index"] for d in decoded] == list(range(60))
        speaking = [d for d in decoded if d["drive"]["speaking"]]
        assert len(speaking) >= 30 and all(d["audio"].shape == (640,) for d in decoded)
        spoken += len(speaking)
        values = np.stack([d["drive"]["values"] for d in speaking])
        assert np.all(np.isfinite(values)) and np.ptp(values, axis=0).max() > 0.05  # the face moves
    metrics = _get(port, "/metrics").decode()
    count = float(next(line.split()[-1] for line in metrics.splitlines()
                       if line.startswith("gt_serve_translator_batch_sessions_count")))
    single = float(next(line.split()[-1] for line in metrics.splitlines()
                        if line.startswith('gt_serve_translator_batch_sessions_bucket{le="1.0"}')))
    assert count > 0 and single < count, (single, count)
    rows = {kind: float(next(line.split()[-1] for line in metrics.splitlines()
                             if line.startswith(f'gt_serve_translator_rows_total{{kind="{kind}"}}')))
            for kind in ("committed", "provisional")}
    # a speaking frame's row is final once the frames up to it and its lookahead (the delay, 4 frames) are committed
    assert rows["committed"] >= spoken - 8 * 5 and rows["provisional"] >= 0, (rows, spoken)
    # the pool threads' CPU, in the translator calls and in the rest of their work, each counted
    cpu = {part: float(next(line.split()[-1] for line in metrics.splitlines()
                            if line.startswith(f'gt_serve_pool_cpu_seconds_total{{part="{part}"}}')))
           for part in ("translator", "frames")}
    assert cpu["translator"] > 0 and cpu["frames"] > 0, cpu


def test_the_load_bench_runs_an_older_gt_serve_as_its_baseline(tmp_path):
    """`gt-bench live-clients --baseline-server` takes a script that runs an older commit's gt-serve: the bench opens
    its admin routes (--debug: it has no secret) and lifts its per-client cap (every load client is one address),
    and names it gt-serve in the report; a live_server.py sample gets neither."""
    from tools.bench.live_clients import Baseline

    wrapper = tmp_path / "serve_main.py"
    wrapper.write_text("from gaussiantalker.cli.serve import main\n\nmain()\n")
    sample = tmp_path / "live_server.py"
    sample.write_text("print('a sample server')\n")
    assert Baseline(wrapper, tmp_path).arguments(100) == ["--debug", "--max-sessions", "100",
                                                          "--max-sessions-per-client", "100"]
    assert Baseline(sample, tmp_path).arguments(100) == []
    assert Baseline(wrapper, tmp_path).is_gt_serve and not Baseline(sample, tmp_path).is_gt_serve


def test_a_client_asking_for_deflate_gets_plain_frames(server):
    """A browser's handshake asks for permessage-deflate; the server declines it (docs/serve.md, "Limits"): the
    answer names no extension, and the frame packets come as they are made."""
    import aiohttp

    _, port = server

    async def run() -> tuple[int, str | None, bytes]:
        async with aiohttp.ClientSession() as http, http.ws_connect(f"ws://127.0.0.1:{port}/live",
                                                                    compress=15) as ws:
            await ws.send_str(json.dumps({"source": "none"}))
            await ws.receive(timeout=60)  # the answer
            packet = await ws.receive(timeout=30)
            return ws.compress, ws._response.headers.get("Sec-WebSocket-Extensions"), packet.data

    compress, extensions, packet = asyncio.run(run())
    assert compress == 0 and extensions is None
    assert packet[:4] == b"GTLF"  # a frame packet, as sent


# Sessions' driver failures, in order: the first session's frame 25 raises, the second's first frame; later
# sessions never fail. Injected in LiveSession.frame_params (the frame's parameters from the rows), which every
# client-render session's frames go through, made alone or together.
DRIVER_FAILURES = (25, 0)
FAILING_SERVER = f"""
import runpy, sys
from gaussiantalker.serve import drive_sessions
plans, Live = iter({DRIVER_FAILURES!r}), drive_sessions.LiveSession
class FailingLive(Live):
    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.fail_from, self.rendered = next(plans, None), 0
    def frame_params(self, plan):
        if self.fail_from is not None and self.rendered >= self.fail_from:
            raise RuntimeError(f"injected driver failure from frame {{self.fail_from}}")
        self.rendered += 1
        return super().frame_params(plan)
drive_sessions.LiveSession = FailingLive
sys.argv = ["gt-serve", *sys.argv[1:]]
runpy.run_module("gaussiantalker.cli.serve", run_name="__main__", alter_sys=True)
"""


def test_a_session_whose_driver_raises_is_logged_once_told_and_closed(small_export):
    """Making a frame raises mid-reply (frame 25) and on the first frame: each time the page gets every frame made
    before, then one error line that names what failed without the error's text, and the session and its pool
    thread are gone once the page leaves (10 s allows for a loaded machine); the log has each failure once with
    its traceback (the second, from the same place, points to the first's); the next session works."""
    module = _server_module()
    process, port = _start(small_export.path, python=("-c", FAILING_SERVER))
    told = "the live session ended: its driver raised (RuntimeError)"
    try:
        for fail_from in DRIVER_FAILURES:
            out = asyncio.run(_session(port, {"source": "file", "chunk_ms": 20}, frames=100))
            indexes = [module.decode_frame_packet(p)["drive"]["index"] for p in out["packets"]]
            assert indexes == list(range(fail_from)), (fail_from, indexes)
            assert out["texts"] == [{"error": told}], out["texts"]
            _until_closed(port, 10.0)
        out = asyncio.run(_session(port, {"source": "file", "chunk_ms": 20}, frames=30))
        assert len(out["packets"]) == 30 and not out["texts"], out["texts"]
    finally:
        process.terminate()
        log = process.communicate(timeout=30)[0]
    records = [line for line in log.splitlines() if " ERROR gaussiantalker.serve: " in line]
    for fail_from in DRIVER_FAILURES:
        message = f"injected driver failure from frame {fail_from}"
        assert sum(message in record for record in records) == 1, (message, log[-5000:])
    assert log.count("Traceback") == 1 and log.count("its traceback as logged before") == 1, log[-5000:]
    assert log.count("started: client-render, ws") == log.count("ended after") == 3, log[-3000:]
