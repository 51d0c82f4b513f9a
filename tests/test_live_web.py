"""Live sessions rendered by the client (docs/live.md, "Live, rendered by the client"): `gt-serve --client-render`
(with tokens: the page carries its own) streams each frame's drive with its voice, and its page
(serve/pages/client.html) draws it with the web player
when the voice reaches its pts. Two transports: "ws" (the page's default), one WebSocket carrying a frame packet
(drive and audio) per frame, the audio played through WebAudio whose schedule is the clock; "webrtc", the drives on
an unordered data channel beside an audio track.

The format tests are pure Python; LiveAudio's (the ws page's audio schedule and clock) runs in node on a fake
AudioContext. The browser tests run Debian's chromium headless on loopback against the server with the tests' small
speaker: they skip without chromium, the web player's npm install or the serve extra, except where CI is set
(tests/ci_tools.py), where they fail."""

from __future__ import annotations

import base64
import json
import shutil
import struct
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest
from ci_tools import BROWSER_INSTALL, need, need_chromium, need_module
from serve_clients import SECRET, free_port

from tools.bench.live_clients import serving

ROOT = Path(__file__).resolve().parents[1]
SIZE = 64
MIN_PSNR_DB = 40.0
FLAGS = ("--autoplay-policy=no-user-gesture-required", "--disable-features=WebRtcHideLocalIpsWithMdns")


def _server_module():
    """The live wire format's module (gaussiantalker.serve.wire; it needs the serve extra)."""
    need_module("aiohttp", "serve")
    from gaussiantalker.serve import wire

    return wire


# -- the wire format, no browser -------------------------------------------------------------------------------


def test_drive_format_round_trips_and_refuses_bad_messages():
    from gaussiantalker.sdk.drive import FrameDrive, HeadPose

    server = _server_module()
    rng = np.random.default_rng(0)
    drive = FrameDrive.make(20, rng.normal(size=20), rng.normal(size=3) * 0.1,
                            head_pose=HeadPose.make(rng.normal(size=3) * 0.1, rng.normal(size=3) * 0.01))
    message = server.encode_drive(37, 37 / 25, drive, True, epoch=2)
    assert len(message) == 28 + 4 * (20 + 15 + 3) == 180
    decoded = server.decode_drive(message)
    assert (decoded["index"], decoded["pts"], decoded["epoch"], decoded["speaking"], decoded["rig"],
            decoded["split"]) == (37, 37 / 25, 2, True, "flame", 20)
    expected = np.concatenate([drive.expression, drive.flame_pose, drive.head_translation])
    assert decoded["values"].tobytes() == expected.astype("<f4").tobytes()

    from gaussiantalker.sdk.drive import BlendshapeDrive

    arkit = BlendshapeDrive.make(None, HeadPose.make([0.1, 0, 0], [0, 0.01, 0]))
    decoded = server.decode_drive(server.encode_drive(0, 0.0, arkit, False))
    assert decoded["rig"] == "arkit" and decoded["split"] == 52 and decoded["values"].size == 58

    bad = server.DriveFormatError
    with pytest.raises(bad, match="truncated: 10 bytes, the header alone is 28"):
        server.decode_drive(message[:10])
    with pytest.raises(bad, match=r"claims 38 values \(152 bytes\) but carries 148 bytes"):
        server.decode_drive(message[:-4])
    lying = bytearray(message)
    struct.pack_into("<H", lying, 24, 60000)  # a count far beyond the bytes present
    with pytest.raises(bad, match="claims 60000 values"):
        server.decode_drive(bytes(lying))
    with pytest.raises(bad, match="not a drive message"):
        server.decode_drive(b"XXXX" + message[4:])
    split = bytearray(message)
    struct.pack_into("<H", split, 26, 30)
    with pytest.raises(bad, match="the pose needs 18"):
        server.decode_drive(bytes(split))
    nan = bytearray(message)
    struct.pack_into("<f", nan, 28, float("nan"))
    with pytest.raises(bad, match="non-finite"):
        server.decode_drive(bytes(nan))


def _frame_packet(server, index: int = 37, epoch: int = 0, samples: int = 640) -> bytes:
    from gaussiantalker.sdk.drive import FrameDrive

    rng = np.random.default_rng(index)
    drive = FrameDrive.make(20, rng.normal(size=20), rng.normal(size=3) * 0.1)
    audio = (rng.normal(size=samples) * 3000).astype(np.int16)
    return server.encode_frame_packet(server.encode_drive(index, index / 25, drive, True, epoch), audio)


# The spec's refusals (docs/live.md): (name, packet maker, message); both decoders must give exactly these.
def frame_packet_refusals(server) -> list[tuple[str, bytes, str]]:
    packet = _frame_packet(server)
    lying = bytearray(packet)
    struct.pack_into("<I", lying, 8, 4000)
    version = bytearray(packet)
    version[4] = 2
    short_drive = bytearray(packet[:12 + 20])
    struct.pack_into("<I", short_drive, 8, 20)  # honest about a drive message that is itself truncated
    return [
        ("truncated", packet[:7], "frame packet truncated: 7 bytes, the header alone is 12"),
        ("lying", bytes(lying[:12 + 180]),
         "frame packet claims a 4000-byte drive but carries 180 bytes after its header"),
        ("odd audio", packet[:12 + 180 + 641], "frame packet audio is 641 bytes: not whole int16 samples"),
        ("magic", b"GTLX" + packet[4:], "not a frame packet (bad magic)"),
        ("version", bytes(version), "frame packet version 2 audio dtype 0: only version 1 int16 is read"),
        ("drive", bytes(short_drive), "drive message truncated: 20 bytes, the header alone is 28"),
    ]


def fuzzed_frame_packets(server, count: int = 300, seed: int = 0) -> list[bytes]:
    """Seeded mutations of valid frame packets (tests/fuzz_mutations.py): bytes anywhere, and the header's and the
    drive's integer fields set to 0, -1, huge or off by one."""
    from fuzz_mutations import mutate_bytes, mutate_field_bytes

    rng = np.random.default_rng(seed)
    valid = [_frame_packet(server, index, epoch, samples) for index, epoch, samples in
             ((0, 0, 640), (37, 2, 640), (5, 1, 0), (9, 0, 1))]
    fields = [(8, 4), (4, 1), (5, 1), (6, 2), (12 + 8, 4), (12 + 12, 4), (12 + 24, 2), (12 + 26, 2)]
    out = list(valid)
    while len(out) < count:
        data = valid[int(rng.integers(len(valid)))]
        data = mutate_field_bytes(data, rng, fields)[0] if rng.random() < 0.4 else mutate_bytes(data, rng)[0]
        out.append(data)
    return out


def _verdict(message: str) -> str:
    """A refusal, less what each language spells its own way (the drive's magic bytes, a float's text)."""
    if message.startswith("not a drive message"):
        return "not a drive message"
    if message.startswith("drive message pts"):
        return "drive message pts"
    return message


def python_verdicts(server, packets: list[bytes]) -> list:
    out = []
    for data in packets:
        try:
            decoded = server.decode_frame_packet(data)
        except server.DriveFormatError as error:
            out.append(("error", _verdict(str(error))))
            continue
        d = decoded["drive"]
        out.append(("ok", d["index"], d["pts"], d["epoch"], d["speaking"], d["rig"], d["split"],
                    d["values"].tolist(), decoded["audio"].tolist()))
    return out


# The page's frame packet decoder on packets sent from here (base64): its verdict on each, as python_verdicts.
JS_FRAME_VERDICTS = """
(async (packets) => {
  const m = await import('/web/src/live.js');
  return packets.map((text) => {
    const bytes = Uint8Array.from(atob(text), (c) => c.charCodeAt(0));
    try {
      const { drive: d, audio } = m.decodeFramePacket(bytes.buffer);
      return ['ok', d.index, d.pts, d.epoch, d.speaking, d.rig, d.split, Array.from(d.values), Array.from(audio)];
    } catch (e) {
      return ['error', e.name + ': ' + e.message];
    }
  });
})
"""


def page_frame_verdicts(browser, packets: list[bytes]) -> list:
    arg = json.dumps([base64.b64encode(p).decode() for p in packets])
    out = browser.evaluate(f"({JS_FRAME_VERDICTS.strip()})({arg})", timeout=60)
    for verdict in out:
        if verdict[0] == "error":
            name, _, message = verdict[1].partition(": ")
            assert name == "DriveFormatError", verdict
            verdict[1] = _verdict(message)
    return [tuple(v) for v in out]


def test_frame_packet_round_trips_and_refuses_bad_packets():
    server = _server_module()
    packet = _frame_packet(server, 37, 2)
    assert len(packet) == 12 + 180 + 2 * 640
    decoded = server.decode_frame_packet(packet)
    assert decoded["drive"]["index"] == 37 and decoded["drive"]["epoch"] == 2 and decoded["audio"].size == 640
    # Float audio (what a LiveFrame carries) is rounded to int16 and clipped; a frame may carry no audio.
    message = packet[12:12 + 180]  # its drive message
    floats = np.array([0.5, -1.0, 1.0, 2.0, 1e-6], np.float32)
    assert server.decode_frame_packet(server.encode_frame_packet(message, floats))["audio"].tolist() == [
        16384, -32768, 32767, 32767, 0]
    assert server.decode_frame_packet(server.encode_frame_packet(message, np.zeros(0, np.int16)))["audio"].size == 0
    for name, data, message in frame_packet_refusals(server):
        with pytest.raises(server.DriveFormatError) as caught:
            server.decode_frame_packet(data)
        assert str(caught.value) == message, name


# LiveAudio on a fake AudioContext whose clock the script moves: the schedule, the clock it gives, an underrun and
# a barge-in. Prints what the test checks as JSON.
LIVE_AUDIO_SCRIPT = """
import { LiveAudio } from %(live_js)s;
class FakeContext {
  constructor() { Object.assign(this, { currentTime: 10, outputLatency: 0.02, sampleRate: 48000, state: 'running',
    destination: {}, started: [] }); }
  createGain() { return { gain: { value: 1 }, connect() {} }; }
  createBuffer(channels, length, rate) {
    const data = new Float32Array(length);
    return { length, sampleRate: rate, getChannelData: () => data };
  }
  createBufferSource() {
    const ctx = this;
    return { connect() {}, start(at) { this.at = at; ctx.started.push(this); }, stop() { this.stopped = true; } };
  }
  close() { this.state = 'closed'; }
}
const ctx = new FakeContext();
const audio = new LiveAudio({ context: ctx, bufferS: 0.1 });
const frame = new Int16Array(640).fill(1000);
const out = { before: audio.now() };
const schedule = (i, epoch = 0) => audio.schedule(i / 25, frame, 16000, { epoch, index: i });
out.starts = [0, 1, 2].map((i) => schedule(i));          // 10.1, 10.14, 10.18: back to back after the buffer
ctx.currentTime = 10.14;                                   // heard: 10.12, half-way through frame 0
out.heard = audio.now();
ctx.currentTime = 10.40;                                   // past the end of frame 2: an underrun
out.held = audio.now();                                    // the clock waits at the end of what played
out.reanchored = schedule(3);                              // 10.5
out.underruns = audio.underruns;
out.afterUnderrun = (ctx.currentTime = 10.53, audio.now());  // heard 10.51: frame 3 + 0.01
for (const i of [4, 5, 6, 7]) schedule(i);                 // 10.54 .. 10.66
ctx.currentTime = 10.56;                                   // frame 4 plays; 5, 6, 7 wait
audio.bargeIn(1, null);                                    // the server's answer to a barge-in
out.stoppedAt = ctx.started.filter((s) => s.stopped).map((s) => s.at);
out.stopped = audio.stopped;
out.lateOld = schedule(8, 0);                              // an old-epoch frame arriving after it: refused
out.next = schedule(9, 1);                                 // the new epoch: a jitter buffer ahead (10.66)
out.underrunsAfter = audio.underruns;
out.samples = Array.from(ctx.started[0].buffer.getChannelData(0).slice(0, 2));
console.log(JSON.stringify(out));
"""


def test_live_audio_schedule_clock_underrun_and_barge_in(tmp_path):
    """LiveAudio (web/src/live.js) in node on a fake AudioContext: back-to-back packets after the jitter buffer,
    the pts heard (less the output latency), the clock holding through an underrun and re-anchoring after it, and
    a barge-in stopping the old epoch's queued audio and refusing its late packets."""
    node = shutil.which("node")
    need(None if node else "node is missing (Debian's npm brings it)", BROWSER_INSTALL)
    script = tmp_path / "live_audio.mjs"
    script.write_text(LIVE_AUDIO_SCRIPT % {"live_js": json.dumps((ROOT / "web" / "src" / "live.js").as_uri())})
    done = subprocess.run([node, str(script)], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr[-2000:]
    out = json.loads(done.stdout)
    assert out["before"] is None  # NaN: nothing scheduled
    assert out["starts"] == pytest.approx([10.1, 10.14, 10.18])
    assert out["heard"] == pytest.approx(0.02)
    assert out["held"] == pytest.approx(3 / 25)
    assert out["reanchored"] == pytest.approx(10.5) and out["underruns"] == 1
    assert out["afterUnderrun"] == pytest.approx(3 / 25 + 0.01)
    assert out["stoppedAt"] == pytest.approx([10.58, 10.62, 10.66]) and out["stopped"] == 3
    assert out["lateOld"] is None and out["next"] == pytest.approx(10.66) and out["underrunsAfter"] == 1
    assert out["samples"] == pytest.approx([1000 / 32768] * 2)


# -- in the browser --------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def live_web_ready() -> None:
    """Chromium, the web player's npm install and the serve extra, checked before the speaker is made."""
    from tools.browser.web_harness import check_web_player

    need_chromium()
    need(check_web_player(), BROWSER_INSTALL)
    need_module("aiortc", "serve")


def start_server(bundle: Path, port: int, timeout: float = 120.0) -> subprocess.Popen:
    """gt-serve --client-render serving `bundle` on `port` with tokens (tests/serve_clients.py SECRET), once it
    answers."""
    secret = Path(tempfile.mkdtemp(prefix="gt-serve-test-")) / "secret.txt"
    secret.write_bytes(SECRET)
    return serving([sys.executable, "-m", "gaussiantalker.cli.serve", str(bundle), "--port", str(port),
                    "--client-render", "--secret-file", str(secret), "--drain-s", "1"],
                   f"http://127.0.0.1:{port}/readyz", timeout, name="gt-serve")


def _get(port: int, path: str) -> bytes:
    """GET `path` with an admin token (the tests read the server's counters and recorded drives)."""
    from gaussiantalker.serve import mint_token

    token = mint_token(SECRET, 60.0, admin=True)
    return urllib.request.urlopen(f"http://127.0.0.1:{port}{path}{'&' if '?' in path else '?'}token={token}",
                                  timeout=10).read()


def page_token() -> str:
    """A page's token (what an app's backend mints), for the page's ?token=."""
    from gaussiantalker.serve import mint_token

    return mint_token(SECRET, 600.0)


def _wait(browser, expression: str, timeout: float = 90.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = browser.evaluate(expression)
        if value:
            return value
        time.sleep(0.2)
    raise AssertionError(f"timed out waiting for {expression}: {browser.evaluate('window.liveWeb?.stats?.state')}, "
                         f"{browser.console[-10:]}")


def server_drives(server, port: int, session: str) -> dict[int, dict]:
    """The server's recorded drives of `session` (GET /drives), decoded, by frame index."""
    body, drives, at = _get(port, f"/drives?session={session}"), {}, 0
    while at < len(body):
        (length,) = struct.unpack_from("<H", body, at)
        decoded = server.decode_drive(body[at + 2:at + 2 + length])
        drives[decoded["index"]] = decoded
        at += 2 + length
    return drives


def page_url(port: int, transport: str, source: str = "file") -> str:
    """The page starting a `source` session at once; ws is the page's default transport, so it is not named."""
    named = "" if transport == "ws" else f"&transport={transport}"
    return f"http://127.0.0.1:{port}/?source={source}&autostart=1&size={SIZE}{named}&token={page_token()}"


# What the tests read of the page (window.liveWeb), the same in both transports; audio (LiveAudio's counts and the
# pts heard) only in ws.
PAGE_STATS = """({state: window.liveWeb.stats.state, error: window.liveWeb.stats.error,
  session: window.liveWeb.stats.session, transport: window.liveWeb.stats.transport,
  received: window.liveWeb.received(), rendered: window.liveWeb.stats.rendered, queue: window.liveWeb.stats.queue,
  interrupts: window.liveWeb.stats.interrupts, bad: window.liveWeb.stats.badMessages,
  answer: window.liveWeb.stats.answer ?? null, mic: window.liveWeb.stats.mic,
  audio: window.liveWeb.audio ? window.liveWeb.audio.stats : null})"""


def run_live_page(bundle: Path, transport: str = "ws", speak_s: float = 3.0, after_interrupt_s: float = 1.5) -> dict:
    """One client-render session in chromium over `transport`: the sample speech for `speak_s` of speaking drives,
    then a barge-in, then `after_interrupt_s` more. Returns what the page and the server saw, two page renders, and
    the page's unit checks (ws: its frame packet decoder's verdicts on the spec's refusals and on fuzzed packets,
    with Python's)."""
    from tools.browser.chromium import Chromium

    server = _server_module()
    port = free_port()
    process = start_server(bundle, port)
    try:
        with Chromium(window=(400, 500), extra_flags=FLAGS) as browser:
            browser.navigate(page_url(port, transport))
            _wait(browser, "window.liveWeb && window.liveWeb.stats.state === 'connected'", 120)
            fps = 25
            _wait(browser, f"window.liveWeb.stats.received.filter((r) => r.speaking).length >= {int(speak_s * fps)}"
                  " || window.liveWeb.stats.error", 60)
            called = time.monotonic()
            interrupt = browser.evaluate("window.liveWeb.interrupt()")
            returned = time.monotonic() - called
            time.sleep(after_interrupt_s)
            stats = browser.evaluate(PAGE_STATS)
            drives = server_drives(server, port, stats["session"])
            speaking = [r["index"] for r in stats["received"] if r["speaking"]]
            chosen = [speaking[len(speaking) // 3], speaking[-1]]
            renders = {}
            for index in chosen:
                reply = browser.evaluate(f"window.liveWeb.render({index})", timeout=120)
                renders[index] = np.frombuffer(base64.b64decode(reply["data"]), np.uint8).reshape(
                    reply["height"], reply["width"], 3)
            browser.evaluate("window.liveWeb.stop()")
            units = browser.evaluate(JS_UNITS, timeout=60)
            if transport == "ws":
                refusals = frame_packet_refusals(server)
                units["refusals"] = page_frame_verdicts(browser, [data for _, data, _ in refusals])
                units["expected_refusals"] = [("error", message) for _, _, message in refusals]
                fuzzed = fuzzed_frame_packets(server)
                units["fuzzed"] = page_frame_verdicts(browser, fuzzed), python_verdicts(server, fuzzed)
    finally:
        process.terminate()
        log = process.communicate(timeout=30)[0]
    return {"stats": stats, "drives": drives, "renders": renders, "interrupt": interrupt, "log": log,
            "interrupt_call_s": returned, "units": units}


# The page's decoder and queue, exercised in the page: refusals bounded by the bytes present, and the barge-in.
JS_UNITS = """
(async () => {
  const m = await import('/web/src/live.js');
  const out = {};
  const header = new ArrayBuffer(28 + 4 * 38);
  const v = new DataView(header);
  [0x47, 0x54, 0x4c, 0x44].forEach((b, i) => v.setUint8(i, b));
  v.setUint8(4, 1); v.setUint32(8, 5, true); v.setFloat64(16, 0.2, true); v.setUint16(24, 38, true);
  v.setUint16(26, 20, true);
  const tryDecode = (buffer) => {
    try { m.decodeDrive(buffer); return null; } catch (e) { return e.name + ': ' + e.message; }
  };
  out.ok = m.decodeDrive(header).values.length;
  out.truncated = tryDecode(header.slice(0, 10));
  out.short = tryDecode(header.slice(0, header.byteLength - 4));
  const lying = header.slice(0); new DataView(lying).setUint16(24, 60000, true);
  out.lying = tryDecode(lying);
  const q = new m.DriveQueue();
  const d = (index, epoch) => ({ index, pts: index / 25, epoch, speaking: epoch === 0 });
  for (const i of [10, 12, 11, 13, 14]) q.push(d(i, 0));          // unordered arrival, pts order kept
  out.order = q.items.map((x) => x.index);
  q.bargeIn(1, 12);                                                  // the control channel: epoch 1 from frame 12
  out.afterBargeIn = q.items.map((x) => x.index);
  out.lateOld = q.push(d(13, 0));                                    // an old-epoch drive arriving late: refused
  q.push(d(12, 1));
  out.take = q.take(12.5 / 25).index;
  out.skipped = q.skipped;
  return out;
})()
"""


@pytest.mark.parametrize("transport", ["ws", "webrtc"])
def test_page_renders_the_servers_drives_on_the_audio_clock_and_barge_in_stops_speech(live_web_ready,
                                                                                       small_export, transport):
    check_live_page(small_export.path, transport)


def check_live_page(bundle: Path, transport: str = "ws") -> None:
    from gaussiantalker.runtime import TalkingHead
    from gaussiantalker.sdk.drive import FrameDrive
    from gaussiantalker.sdk.image import psnr_db

    result = run_live_page(bundle, transport)
    stats, drives = result["stats"], result["drives"]
    print(transport, {k: stats[k] for k in ("state", "queue", "interrupts", "bad", "audio")}, "rendered",
          len(stats["rendered"]), "interrupt", result["interrupt"], f"{result['interrupt_call_s']:.3f} s")
    assert stats["state"] == "connected" and not stats["error"] and stats["bad"] == 0, stats
    assert stats["transport"] == transport
    assert "Traceback" not in result["log"], result["log"][-3000:]

    # Every drive the page received is the server's, value for value; indexes unique, pts = index / fps.
    received = stats["received"]
    assert len(received) >= 3 * 25 + 25, len(received)
    indexes = [r["index"] for r in received]
    assert len(set(indexes)) == len(indexes)
    for r in received:
        server_drive = drives[r["index"]]
        assert r["pts"] == server_drive["pts"] == r["index"] / 25
        assert r["epoch"] == server_drive["epoch"] and r["speaking"] == server_drive["speaking"]
        assert np.array_equal(np.asarray(r["values"], np.float32), server_drive["values"]), r["index"]
    # Loopback loses nothing: every drive made after the channel opened reached the page.
    first, last = min(indexes), max(indexes)
    assert sorted(indexes) == list(range(first, last + 1))
    # Rendered in pts order on the audio clock, each no earlier than its pts.
    rendered = stats["rendered"]
    assert len(rendered) >= 5, rendered[-5:]
    pts = [r["pts"] for r in rendered]
    assert all(a < b for a, b in zip(pts, pts[1:], strict=False)), pts
    assert all(r["clock"] >= r["pts"] for r in rendered)

    # The page's frames are the Python runtime's frames of the same drives.
    with TalkingHead(bundle, resolution=(SIZE, SIZE), renderer="gl", composite=False) as head:
        n_expr = head.driver.config.n_expr
        for index, frame in result["renders"].items():
            values = drives[index]["values"]
            drive = FrameDrive(values[:n_expr], values[n_expr:n_expr + 15], values[n_expr + 15:])
            score = psnr_db(head.render(drive), frame)
            print(f"frame {index}: PSNR {score:.1f} dB")
            assert score >= MIN_PSNR_DB, (index, score)

    # Barge-in: after the interrupt the server's drives are the ease to idle, never speaking again, the jaw shut
    # within the ease; the page heard the new epoch and renders only idle drives after it.
    epoch = result["interrupt"]["epoch"]
    assert epoch == 1 and stats["interrupts"] and stats["interrupts"][0]["epoch"] == 1, stats["interrupts"]
    first = stats["interrupts"][0]["index"]  # the new epoch's first frame, told on the control channel
    after = sorted((d for d in drives.values() if d["epoch"] >= epoch), key=lambda d: d["index"])
    assert after[0]["index"] == first and len(after) >= 20 and not any(d["speaking"] for d in after)
    assert all(d["epoch"] == (d["index"] >= first) for d in drives.values())
    jaw = [float(np.abs(d["values"][n_expr + 6:n_expr + 9]).max()) for d in after]
    assert max(jaw[5:]) == 0.0, jaw[:8]
    last_speaking = max(r["pts"] for r in received if r["speaking"])
    assert rendered[-1]["pts"] > last_speaking and not rendered[-1]["speaking"], rendered[-3:]
    if transport == "ws":
        check_ws_audio(stats, epoch)

    # The page's decoder refuses what lies about its size; its queue keeps pts order and drops stale drives.
    units = result["units"]
    assert units["ok"] == 38
    assert units["truncated"] == "DriveFormatError: drive message truncated: 10 bytes, the header alone is 28"
    assert units["short"] == "DriveFormatError: drive message claims 38 values (152 bytes) but carries 148 bytes"
    assert units["lying"].startswith("DriveFormatError: drive message claims 60000 values")
    assert units["order"] == [10, 11, 12, 13, 14] and units["afterBargeIn"] == [10, 11]
    assert units["lateOld"] is False and units["take"] == 12 and units["skipped"] == 2
    if transport == "ws":
        # The page's frame packet decoder gives the spec's refusals word for word, and on fuzzed packets the same
        # verdict as Python's decode_frame_packet (the same fields and samples where both accept).
        assert units["refusals"] == units["expected_refusals"]
        page, python = units["fuzzed"]
        assert len(page) == len(python)
        for k, (a, b) in enumerate(zip(page, python, strict=True)):
            assert a == b, (k, a[:2], b[:2])


# Chromium's fake microphone plays the sample speech (in a loop); its permission prompt is answered yes.
MIC_FLAGS = (*FLAGS, "--use-fake-ui-for-media-stream", "--use-fake-device-for-media-stream",
             f"--use-file-for-fake-audio-capture={ROOT / 'samples' / 'demo_speech.wav'}")


def test_page_talks_with_its_microphone_over_the_socket(live_web_ready, small_export):
    """source mic (ws only): the page's AudioWorklet sends the microphone as int16 PCM at its context's rate, and
    the server's drives speak it: the mouth moves with the voice."""
    from tools.browser.chromium import Chromium

    server = _server_module()
    port = free_port()
    process = start_server(small_export.path, port)
    try:
        with Chromium(window=(400, 500), extra_flags=MIC_FLAGS) as browser:
            browser.navigate(page_url(port, "ws", "mic"))
            _wait(browser, "window.liveWeb && window.liveWeb.stats.state === 'connected'", 120)
            _wait(browser, "window.liveWeb.stats.received.filter((r) => r.speaking).length >= 50"
                  " || window.liveWeb.stats.error", 60)
            stats = browser.evaluate(PAGE_STATS)
            drives = server_drives(server, port, stats["session"])
            browser.evaluate("window.liveWeb.stop()")
    finally:
        process.terminate()
        log = process.communicate(timeout=30)[0]
    mic, audio, received = stats["mic"], stats["audio"], stats["received"]
    print({k: stats[k] for k in ("state", "queue", "bad", "audio", "mic")}, "rendered", len(stats["rendered"]))
    assert stats["state"] == "connected" and not stats["error"] and stats["bad"] == 0, stats
    assert "Traceback" not in log, log[-3000:]
    # The microphone went out at the context's rate, 20 ms a message.
    assert mic["rate"] == audio["contextRate"] and mic["sent"] >= 50, (mic, audio)
    assert mic["bytes"] == mic["sent"] * 2 * round(mic["rate"] / 50), mic
    # The server's drives speak: the jaw opens and closes with the voice, and each frame's audio carries it.
    speaking = [drives[r["index"]] for r in received if r["speaking"]]
    assert len(speaking) >= 50
    split = speaking[0]["split"]
    jaw = np.array([float(np.abs(d["values"][split + 6:split + 9]).max()) for d in speaking])
    assert np.ptp(jaw) > 0.05, jaw
    assert max(r["audio"]["peak"] for r in received if r["speaking"]) > 1000
    assert len(stats["rendered"]) >= 5 and audio["scheduled"] >= len(received) - 1, audio


def check_ws_audio(stats: dict, epoch: int) -> None:
    """ws: the page played every frame's audio on one continuous schedule and drew the drives on that clock; after
    the barge-in the old speech was cut and the new epoch's frames carry silence."""
    answer, audio, received, rendered = stats["answer"], stats["audio"], stats["received"], stats["rendered"]
    fps, rate = answer["fps"], answer["sample_rate"]
    assert answer["rig"] == "flame" and answer["session"] == stats["session"], answer
    assert audio is not None and np.isfinite(audio["heardPts"]), audio
    per_frame = round(rate / fps)
    # Every frame came with its audio; every one was scheduled but old-epoch frames arriving after the barge-in.
    assert all(r["audio"]["samples"] == per_frame for r in received), {r["audio"]["samples"] for r in received}
    unscheduled = [r for r in received if r["audio"]["start"] is None]
    assert all(r["epoch"] < epoch for r in unscheduled), unscheduled[:3]
    assert audio["scheduled"] == len(received) - len(unscheduled) and audio["overruns"] == 0, audio
    # The cut is what was queued ahead: the jitter buffer (more after a burst), well under a second.
    assert len(unscheduled) + audio["stopped"] <= fps, (len(unscheduled), audio)
    # Back to back: each scheduled frame starts where the one before it ends, but after an underrun or the cut.
    old = [r["audio"]["start"] for r in received if r["epoch"] < epoch and r["audio"]["start"] is not None]
    gaps = np.diff(old) - 1 / fps
    assert np.all(gaps > -1e-6) and np.sum(gaps > 1e-6) <= audio["underruns"], (gaps.max(), audio)
    assert max(r["audio"]["peak"] for r in received if r["speaking"]) > 1000  # the speech is heard
    # The new epoch's frames are silence (the ease to idle).
    assert all(r["audio"]["peak"] == 0 for r in received if r["epoch"] >= epoch)
    # Drawn on the audio clock: each rendered drive was due, by at most a frame and the jitter buffer.
    clocks = np.array([r["clock"] for r in rendered]) - np.array([r["pts"] for r in rendered])
    assert np.all(np.isfinite(clocks)) and np.all(clocks >= 0), clocks
    assert clocks.max() <= 1 / fps + audio["bufferS"], clocks.max()


if __name__ == "__main__":  # a quick run against a bundle: python tests/test_live_web.py BUNDLE [ws|webrtc]
    check_live_page(Path(sys.argv[1]), *sys.argv[2:3])
