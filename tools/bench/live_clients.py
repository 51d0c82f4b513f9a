"""Client-render live sessions under load (docs/live.md, "Live, rendered by the client"): how many sessions one
`samples/live_server.py --client-render` sustains on this machine.

The server runs on loopback in a process of its own; N load clients (aiortc peers, in client processes of their
own) each open a session with the sample speech as the voice (pushed by the server at real time in 20 ms chunks:
the producer that costs the translator most, one call per frame), read every drive on the unordered "drives"
data channel and every RTP packet of the audio track (counted, sequence numbers checked, not decoded: decoding
is the page's cost, not the server's), interrupt after SPEAK_S and leave IDLE_S later.

Per N: late frames (a drive arriving more than LATE_TOLERANCE_S after its due time, start + pts on the wall
clock, or never arriving), the server's CPU seconds per session-second, first-frame latency (the answer to the
first speaking drive), barge-in latency (POST /interrupt to the first idle drive after it), audio packets
received per expected packet, and the machine's load average.
"""

from __future__ import annotations

import asyncio
import json
import math
import multiprocessing
import os
import socket
import struct
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
SERVER = ROOT / "samples" / "live_server.py"
SPEAK_S = 4.0
IDLE_S = 1.5
STAGGER_S = 0.05  # between two clients' offers: a ramp, not a stampede of DTLS handshakes
# A drive may arrive this long after its due time and still be shown with its sound: the page hears the voice at
# least a jitter buffer (Chromium: 40 ms and up) after it left, and draws when the voice reaches the pts.
LATE_TOLERANCE_S = 0.1
CLOCK_WINDOW_S = 2.0  # the page's clock follows the smallest arrival - pts over this window (LiveClock)
CLIENTS_PER_PROCESS = 40
HEADER = struct.Struct("<4sBBBBIIdHH")  # a drive message's header
PACKET_DRIVE_BYTES = struct.Struct("<I")  # a frame packet's drive length, at offset 8
TRANSPORTS = ("webrtc", "ws")
TRANSPORT_NAMES = {"ws": "One WebSocket a session (frame packets: drive + int16 audio)",
                   "webrtc": "WebRTC (drives on a data channel, voice on an Opus audio track)"}


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def _cpu_seconds(pid: int) -> float:
    """User + system CPU seconds of process `pid` (its threads included)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


async def _client(url: str, delay: float, speak_s: float, idle_s: float, chunk_ms: float, packets: dict) -> dict:
    import aiohttp
    from aiortc import RTCPeerConnection, RTCSessionDescription

    await asyncio.sleep(delay)
    result: dict = {"drives": [], "error": None, "audio_per_s": 50.0}  # two 20 ms Opus packets a 40 ms frame
    pc = RTCPeerConnection()
    try:
        transceiver = pc.addTransceiver("audio", direction="recvonly")
        pc.createDataChannel("control")
        channel = pc.createDataChannel("drives", ordered=False, maxRetransmits=0)

        @channel.on("message")
        def on_drive(message: bytes) -> None:
            arrival = time.monotonic()
            _, _, _, flags, _, index, epoch, pts, _, _ = HEADER.unpack_from(message)
            result["drives"].append((index, epoch, flags & 1, pts, arrival, len(message)))

        await pc.setLocalDescription(await pc.createOffer())
        async with aiohttp.ClientSession() as http:
            sent = time.monotonic()
            async with http.post(f"{url}/offer", json={"sdp": pc.localDescription.sdp,
                                                        "type": pc.localDescription.type, "source": "file",
                                                        "chunk_ms": chunk_ms}) as reply:
                if reply.status != 200:
                    raise RuntimeError(f"offer: HTTP {reply.status}: {await reply.text()}")
                answer = await reply.json()
            await pc.setRemoteDescription(RTCSessionDescription(sdp=answer["sdp"], type=answer["type"]))
            result.update(offer_sent=sent, answered=time.monotonic(), start_time=answer["start_time"],
                          fps=answer["fps"])
            await asyncio.sleep(max(0.0, result["answered"] + speak_s - time.monotonic()))
            result["interrupt_sent"] = time.monotonic()
            async with http.post(f"{url}/interrupt", data=answer["session"]) as reply:
                result["interrupt"] = await reply.json()
            await asyncio.sleep(idle_s)
            result["closed"] = time.monotonic()
            async with http.post(f"{url}/close", data=answer["session"]):
                pass
        receiver = transceiver.receiver
        result["audio_packets"], result["audio_lost"] = packets.get(id(receiver), (0, 0, None))[:2]
    except Exception as exc:  # reported per client: a refused or failed session is part of what is measured
        result["error"] = f"{type(exc).__name__}: {exc}"
    finally:
        await pc.close()
    return result


async def _ws_client(url: str, delay: float, speak_s: float, idle_s: float, chunk_ms: float) -> dict:
    """One load client on the WebSocket transport: reads every frame packet (its drive header and its audio's
    length; the audio is not played: that is the page's cost), barges in after `speak_s` and leaves `idle_s`
    later."""
    import aiohttp

    await asyncio.sleep(delay)
    result: dict = {"drives": [], "error": None, "audio_packets": 0, "audio_lost": 0, "audio_per_s": 0.0}
    try:
        async with aiohttp.ClientSession() as http:
            sent = time.monotonic()
            async with http.ws_connect(url.replace("http://", "ws://") + "/live", max_msg_size=1 << 20) as socket:
                await socket.send_json({"source": "file", "chunk_ms": chunk_ms})
                answer = await socket.receive_json(timeout=120)
                if "error" in answer:
                    raise RuntimeError(f"start: {answer['error']}")
                frame_samples = answer["sample_rate"] / answer["fps"]
                result.update(offer_sent=sent, answered=time.monotonic(), start_time=answer["start_time"],
                              fps=answer["fps"], audio_per_s=float(answer["fps"]))

                async def read() -> None:
                    async for message in socket:
                        if message.type != aiohttp.WSMsgType.BINARY:
                            continue
                        arrival = time.monotonic()
                        (drive_bytes,) = PACKET_DRIVE_BYTES.unpack_from(message.data, 8)
                        _, _, _, flags, _, index, epoch, pts, _, _ = HEADER.unpack_from(message.data, 12)
                        result["drives"].append((index, epoch, flags & 1, pts, arrival, len(message.data)))
                        samples = (len(message.data) - 12 - drive_bytes) // 2
                        # A frame's audio is its share of the timeline: 640 or 641 samples where fps does not
                        # divide the rate.
                        result["audio_packets"] += abs(samples - frame_samples) < 1

                reader = asyncio.ensure_future(read())
                await asyncio.sleep(max(0.0, result["answered"] + speak_s - time.monotonic()))
                result["interrupt_sent"] = time.monotonic()
                await socket.send_json({"interrupt": True})
                await asyncio.sleep(idle_s)
                result["closed"] = time.monotonic()
                reader.cancel()
    except Exception as exc:  # reported per client: a refused or failed session is part of what is measured
        result["error"] = f"{type(exc).__name__}: {exc}"
    return result


def _client_process(url: str, count: int, first: int, speak_s: float, idle_s: float, chunk_ms: float,
                    queue, transport: str = "webrtc") -> None:
    """`count` load clients on one event loop; their results go to `queue`."""
    from aiortc.rtcrtpreceiver import RTCRtpReceiver

    packets: dict = {}  # id(receiver) -> [packets, lost, last sequence number]

    async def count_packet(self, packet, arrival_time_ms) -> None:
        """Read every audio RTP packet (count it, check its sequence number) without decoding it."""
        entry = packets.setdefault(id(self), [0, 0, None])
        entry[0] += 1
        if entry[2] is not None:
            entry[1] += max(0, (packet.sequence_number - entry[2] - 1) % 65536)
        entry[2] = packet.sequence_number

    RTCRtpReceiver._handle_rtp_packet = count_packet

    async def main() -> list:
        if transport == "ws":
            return await asyncio.gather(*(_ws_client(url, (first + k) * STAGGER_S, speak_s, idle_s, chunk_ms)
                                          for k in range(count)))
        return await asyncio.gather(*(_client(url, (first + k) * STAGGER_S, speak_s, idle_s, chunk_ms,
                                              packets) for k in range(count)))

    queue.put(asyncio.run(main()))


def serving(command: list[str], url: str, timeout: float, name: str = "live_server.py") -> subprocess.Popen:
    """Start `command` (the server `name`) and return it once `url` answers; RuntimeError with its output's tail if
    it exits first or does not answer within `timeout` seconds (then it is killed)."""
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            urllib.request.urlopen(url, timeout=1).read()
            return process
        except OSError:
            if process.poll() is not None:
                raise RuntimeError(f"{name} exited: {process.stdout.read()[-3000:]}") from None
            time.sleep(0.2)
    process.kill()
    raise RuntimeError(f"{name} did not answer within {timeout:g} s: {process.stdout.read()[-3000:]}")


def _start_server(bundle: Path, port: int, lookahead_ms: float, batch_frames: int = 1,
                  context_ms: float = 1000.0) -> subprocess.Popen:
    return serving([sys.executable, str(SERVER), str(bundle), "--port", str(port), "--client-render",
                    "--lookahead-ms", str(lookahead_ms), "--batch-frames", str(batch_frames), "--context-ms",
                    str(context_ms)],
                   f"http://127.0.0.1:{port}/health", 180)


def _percentiles(values: list[float]) -> dict:
    if not values:
        return {"p50_ms": None, "p95_ms": None, "max_ms": None}
    array = 1000 * np.asarray(values)
    return {"p50_ms": float(np.percentile(array, 50)), "p95_ms": float(np.percentile(array, 95)),
            "max_ms": float(array.max())}


def _late_vs_clock(drives: list, fps: float) -> list[float]:
    """Per drive: how much later it arrived than the page's clock (web/src/live.js LiveClock) would show it: its
    arrival - pts, less the smallest arrival - pts of the drives that arrived in the CLOCK_WINDOW_S before it. The
    voice left the server with the drive, so a drive later than that by more than the jitter buffer misses its
    sound; a stall of the server's driver delays drive and voice alike and is not late by this measure (it is in
    `behind`)."""
    ordered = sorted(drives, key=lambda d: d[4])
    window: list[tuple[float, float]] = []
    out = []
    for _, _, _, pts, arrival, _ in ordered:
        window.append((arrival, arrival - pts))
        while window[0][0] < arrival - CLOCK_WINDOW_S:
            window.pop(0)
        out.append(arrival - pts - min(offset for _, offset in window))
    return out


def _analyse(clients: list[dict], cpu_s: float, wall_s: float) -> dict:
    """One N's figures from its clients' records."""
    late = behind = expected = missing = 0
    first_frame, barge_in, jitter, delays = [], [], [], []
    packets = expected_packets = lost = errors = 0
    session_s = 0.0
    for client in clients:
        if client["error"] or not client["drives"]:
            errors += 1
            continue
        drives = client["drives"]
        fps, start = client["fps"], client["start_time"]
        # Frames due from the first drive the open channel delivered until the client left: all must arrive.
        first_due = min(d[0] for d in drives)
        last_due = math.floor((client["closed"] - start) * fps) - 3
        kept = [d for d in drives if first_due <= d[0] <= last_due]
        indexes = {d[0] for d in kept}
        expected += max(0, last_due - first_due + 1)
        missing += sum(index not in indexes for index in range(first_due, last_due + 1))
        lateness = _late_vs_clock(kept, fps)
        jitter += lateness
        late += sum(value > LATE_TOLERANCE_S for value in lateness)
        for index, _, _, _, arrival, _ in kept:
            delays.append(arrival - (start + index / fps))
            behind += delays[-1] > LATE_TOLERANCE_S
        speaking = [arrival for _, _, s, _, arrival, _ in drives if s]
        if speaking:
            first_frame.append(min(speaking) - client["answered"])
        idle = [arrival for _, _, s, _, arrival, _ in drives if not s and arrival > client["interrupt_sent"]]
        if idle:
            barge_in.append(min(idle) - client["interrupt_sent"])
        session_s += client["closed"] - client["answered"]
        packets += client["audio_packets"]
        lost += client["audio_lost"]
        expected_packets += round((client["closed"] - client["answered"]) * client["audio_per_s"])
    late += missing

    def ms(values, q):
        return 1000 * float(np.percentile(values, q)) if values else None

    return {"clients": len(clients), "failed": errors, "frames_due": expected, "late_frames": late,
            "late_share": late / expected if expected else 1.0, "missing_frames": missing,
            "jitter_p50_ms": ms(jitter, 50), "jitter_p99_ms": ms(jitter, 99),
            "behind_share": behind / expected if expected else 1.0,
            "delay_p50_ms": ms(delays, 50), "delay_p99_ms": ms(delays, 99),
            "server_cpu_s": cpu_s, "wall_s": wall_s, "session_s": session_s,
            "cpu_s_per_session_s": cpu_s / session_s if session_s else None,
            "first_frame": _percentiles(first_frame), "barge_in": _percentiles(barge_in),
            "audio_packets_per_expected": packets / expected_packets if expected_packets else 0.0,
            "audio_packets_lost": lost}


def run_live_clients_bench(bundle: Path, counts: list[int], lookahead_ms: float = 160.0,
                           speak_s: float = SPEAK_S, idle_s: float = IDLE_S, chunk_ms: float = 20.0,
                           log=print, transport: str = "webrtc", batch_frames: int = 1,
                           context_ms: float = 1000.0) -> dict:
    """Start the client-render server once, then for each N its load clients on `transport` ("webrtc": audio
    track and data channel; "ws": one WebSocket); returns the figures per N."""
    if transport not in TRANSPORTS:
        raise ValueError(f"transport must be one of {TRANSPORTS}, got {transport!r}")
    port = _free_port()
    url = f"http://127.0.0.1:{port}"
    server = _start_server(bundle, port, lookahead_ms, batch_frames, context_ms)
    context = multiprocessing.get_context("spawn")
    runs = []
    try:
        for n in counts:
            load_before = os.getloadavg()
            cpu_before, started = _cpu_seconds(server.pid), time.monotonic()
            queue = context.Queue()
            processes = []
            for first in range(0, n, CLIENTS_PER_PROCESS):
                count = min(CLIENTS_PER_PROCESS, n - first)
                process = context.Process(target=_client_process, args=(url, count, first, speak_s, idle_s,
                                                                        chunk_ms, queue, transport))
                process.start()
                processes.append(process)
            clients = []
            for _ in processes:
                clients += queue.get(timeout=120 + n * STAGGER_S + speak_s + idle_s)
            for process in processes:
                process.join(30)
            cpu_s, wall_s = _cpu_seconds(server.pid) - cpu_before, time.monotonic() - started
            row = {"n": n, **_analyse(clients, cpu_s, wall_s), "load_before": load_before,
                   "load_after": os.getloadavg()}
            runs.append(row)
            log(f"N={n}: late {100 * row['late_share']:.1f}%, {row['cpu_s_per_session_s']:.3f} CPU s per "
                f"session-second, first frame p50 {row['first_frame']['p50_ms']} ms, barge-in p50 "
                f"{row['barge_in']['p50_ms']} ms, failed {row['failed']}, load {load_before[0]:.2f}->"
                f"{row['load_after'][0]:.2f}")
            deadline = time.monotonic() + 30  # every session closed before the next N
            while time.monotonic() < deadline:
                health = json.loads(urllib.request.urlopen(f"{url}/health", timeout=10).read())
                if health["sessions"] == 0:
                    break
                time.sleep(0.5)
    finally:
        server.terminate()
        server_log = server.communicate(timeout=30)[0]
    sustained = [row["n"] for row in runs if row["late_share"] <= 0.05 and not row["failed"]]
    return {"runs": runs, "largest_n_within_5pct_late": max(sustained) if sustained else 0,
            "late_tolerance_ms": 1000 * LATE_TOLERANCE_S, "speak_s": speak_s, "idle_s": idle_s,
            "lookahead_ms": lookahead_ms, "chunk_ms": chunk_ms, "transport": transport, "batch_frames": batch_frames,
            "context_ms": context_ms,
            "server_log_tail": server_log[-2000:]}


def live_clients_table(result: dict) -> str:
    lines = ["| N | late frames | lost | jitter p50 / p99 | behind schedule | delay p50 / p99 | server CPU s per "
             "session-s | first frame p50 / p95 | barge-in p50 / p95 | audio packets | failed | load avg (1 min) "
             "before → after |", "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]

    def ms(value) -> str:
        return "–" if value is None else f"{value:.0f}"

    for row in result["runs"]:
        lines.append(f"| {row['n']} | {100 * row['late_share']:.1f}% ({row['late_frames']}/{row['frames_due']}) | "
                     f"{row['missing_frames']} | {ms(row['jitter_p50_ms'])} / {ms(row['jitter_p99_ms'])} ms | "
                     f"{100 * row['behind_share']:.1f}% | {ms(row['delay_p50_ms'])} / {ms(row['delay_p99_ms'])} ms | "
                     f"{row['cpu_s_per_session_s']:.3f} | {ms(row['first_frame']['p50_ms'])} / "
                     f"{ms(row['first_frame']['p95_ms'])} ms | {ms(row['barge_in']['p50_ms'])} / "
                     f"{ms(row['barge_in']['p95_ms'])} ms | {100 * row['audio_packets_per_expected']:.0f}% | "
                     f"{row['failed']} | {row['load_before'][0]:.2f} → {row['load_after'][0]:.2f} |")
    lines.append("")
    lines.append(f"Largest N with at most 5% late frames: **{result['largest_n_within_5pct_late']}**. Late: a drive "
                 f"arriving more than {result['late_tolerance_ms']:.0f} ms after the page's clock (the smallest "
                 "arrival − pts of the last 2 s, which follows the voice) would show it, or lost. Behind schedule: "
                 f"more than {result['late_tolerance_ms']:.0f} ms after start + pts on the wall clock (driver stalls, "
                 "which delay the voice alike).")
    return "\n".join(lines)
