"""Live sessions rendered by the client (docs/live.md, "Live, rendered by the client"): samples/live_server.py
--client-render streams each frame's drive (binary, on an unordered data channel) beside the voice, and
samples/web/live.html draws it with the web player when the voice reaches its pts.

The format test is pure Python. The browser tests run Debian's chromium headless on loopback against the server
with the tests' small speaker: they skip without chromium, the web player's npm install or the live extra, except
where CI is set (tests/ci_tools.py), where they fail."""

from __future__ import annotations

import base64
import importlib.util
import socket
import struct
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest
from ci_tools import BROWSER_INSTALL, need, need_chromium, need_module

from tools.bench.live_clients import serving

ROOT = Path(__file__).resolve().parents[1]
SIZE = 64
MIN_PSNR_DB = 40.0
FLAGS = ("--autoplay-policy=no-user-gesture-required", "--disable-features=WebRtcHideLocalIpsWithMdns")


def _server_module():
    """samples/live_server.py as a module (it needs the live extra)."""
    need_module("aiortc", "live")
    spec = importlib.util.spec_from_file_location("live_server_under_test", ROOT / "samples" / "live_server.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


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


# -- in the browser --------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def live_web_ready() -> None:
    """Chromium, the web player's npm install and the live extra, checked before the speaker is made."""
    from tools.browser.web_harness import check_web_player

    need_chromium()
    need(check_web_player(), BROWSER_INSTALL)
    need_module("aiortc", "live")


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def start_server(bundle: Path, port: int, timeout: float = 120.0) -> subprocess.Popen:
    """live_server.py --client-render serving `bundle` on `port`, once it answers."""
    return serving([sys.executable, str(ROOT / "samples" / "live_server.py"), str(bundle), "--port", str(port),
                    "--client-render"], f"http://127.0.0.1:{port}/health", timeout)


def _get(port: int, path: str) -> bytes:
    return urllib.request.urlopen(f"http://127.0.0.1:{port}{path}", timeout=10).read()


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


def run_live_page(bundle: Path, speak_s: float = 3.0, after_interrupt_s: float = 1.5) -> dict:
    """One client-render session in chromium: the sample speech for `speak_s` of speaking drives, then a barge-in,
    then `after_interrupt_s` more. Returns what the page and the server saw, and two page renders."""
    from tools.browser.chromium import Chromium

    server = _server_module()
    port = _free_port()
    process = start_server(bundle, port)
    try:
        with Chromium(window=(400, 500), extra_flags=FLAGS) as browser:
            browser.navigate(f"http://127.0.0.1:{port}/?source=file&autostart=1&size={SIZE}")
            _wait(browser, "window.liveWeb && window.liveWeb.stats.state === 'connected'", 120)
            fps = 25
            _wait(browser, f"window.liveWeb.stats.received.filter((r) => r.speaking).length >= {int(speak_s * fps)}"
                  " || window.liveWeb.stats.error", 60)
            called = time.monotonic()
            interrupt = browser.evaluate("window.liveWeb.interrupt()")
            returned = time.monotonic() - called
            time.sleep(after_interrupt_s)
            stats = browser.evaluate("({state: window.liveWeb.stats.state, error: window.liveWeb.stats.error, "
                                     "session: window.liveWeb.stats.session, received: window.liveWeb.received(), "
                                     "rendered: window.liveWeb.stats.rendered, queue: window.liveWeb.stats.queue, "
                                     "interrupts: window.liveWeb.stats.interrupts, "
                                     "bad: window.liveWeb.stats.badMessages})")
            drives = server_drives(server, port, stats["session"])
            speaking = [r["index"] for r in stats["received"] if r["speaking"]]
            chosen = [speaking[len(speaking) // 3], speaking[-1]]
            renders = {}
            for index in chosen:
                reply = browser.evaluate(f"window.liveWeb.render({index})", timeout=120)
                renders[index] = np.frombuffer(base64.b64decode(reply["data"]), np.uint8).reshape(
                    reply["height"], reply["width"], 3)
            units = browser.evaluate(JS_UNITS, timeout=60)
            browser.evaluate("window.liveWeb.stop()")
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


def test_page_renders_the_servers_drives_on_the_audio_clock_and_barge_in_stops_speech(live_web_ready,
                                                                                       small_export):
    check_live_page(small_export.path)


def check_live_page(bundle: Path) -> None:
    from gaussiantalker.runtime import TalkingHead
    from gaussiantalker.sdk.drive import FrameDrive
    from gaussiantalker.sdk.image import psnr_db

    result = run_live_page(bundle)
    stats, drives = result["stats"], result["drives"]
    print({k: stats[k] for k in ("state", "queue", "interrupts", "bad")}, "rendered", len(stats["rendered"]),
          "interrupt", result["interrupt"], f"{result['interrupt_call_s']:.3f} s")
    assert stats["state"] == "connected" and not stats["error"] and stats["bad"] == 0, stats
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

    # The page's decoder refuses what lies about its size; its queue keeps pts order and drops stale drives.
    units = result["units"]
    assert units["ok"] == 38
    assert units["truncated"] == "DriveFormatError: drive message truncated: 10 bytes, the header alone is 28"
    assert units["short"] == "DriveFormatError: drive message claims 38 values (152 bytes) but carries 148 bytes"
    assert units["lying"].startswith("DriveFormatError: drive message claims 60000 values")
    assert units["order"] == [10, 11, 12, 13, 14] and units["afterBargeIn"] == [10, 11]
    assert units["lateOld"] is False and units["take"] == 12 and units["skipped"] == 2


if __name__ == "__main__":  # a quick run against a bundle: python tests/test_live_web.py BUNDLE
    check_live_page(Path(sys.argv[1]))
