"""Client-render live sessions under load (docs/live.md, "Live, rendered by the client" and "Load"): how many
sessions one `gt-serve BUNDLE --client-render` sustains on this machine, with tokens on, and, with a baseline, the
same load against an older server script (a `samples/live_server.py` of an earlier commit, run on that commit's
package) in alternating rounds.

Each server runs on loopback in a process of its own, its output in a log file (one line a session start and end:
a pipe nobody reads would fill and stall it). gt-serve checks tokens: its secret is a file in a temporary folder,
each load client mints its own token with a subject of its own (sessions are capped per subject), and the bench
reads /health with an admin token. The baseline has no tokens.

N load clients (aiortc peers, in client processes of their own) each open a session with the sample speech as the
voice (given to the session by the server at real time in 20 ms chunks: the producer that costs the translator
most, one call per frame), read every drive on the unordered "drives" data channel and every RTP packet of the
audio track (counted, sequence numbers checked, not decoded: decoding is the page's cost, not the server's),
interrupt after SPEAK_S and leave IDLE_S later.

Per server and N: late frames (a drive arriving more than LATE_TOLERANCE_S after its due time, start + pts on the
wall clock, or never arriving), the server's CPU seconds per session-second, first-frame latency (the answer to
the first speaking drive), barge-in latency (POST /interrupt to the first idle drive after it), audio packets
received per expected packet, and the machine's load average; with a baseline, each figure's new / old ratio over
the rounds pooled (rounds run old, new, old, new ... for each N).
"""

from __future__ import annotations

import asyncio
import json
import math
import multiprocessing
import os
import struct
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .ports import free_port

ROOT = Path(__file__).resolve().parents[2]
SERVE_MODULE = "gaussiantalker.cli.serve"  # gt-serve
SPEECH = ROOT / "samples" / "demo_speech.wav"  # the voice of every server under test: the same file for all
SERVER_START_S = 180.0
TOKEN_TTL_S = 900.0  # a client's token: longer than its stagger, its session and the requests after it
DEFAULT_MAX_SESSIONS = 100  # gt-serve's cap in client-render mode: raised only for a larger N
SPEAK_S = 4.0
IDLE_S = 1.5
STAGGER_S = 0.05  # between two clients' offers: a ramp, not a stampede of DTLS handshakes
# A drive may arrive this long after its due time and still be shown with its sound: the page hears the voice at
# least a jitter buffer (Chromium: 40 ms and up) after it left, and draws when the voice reaches the pts.
LATE_TOLERANCE_S = 0.1
CLOCK_WINDOW_S = 2.0  # the page's clock follows the smallest arrival - pts over this window (LiveClock)
CLIENTS_PER_PROCESS = 40
# The server's CPU is read this often during a round, so its cost can be split between speaking and idle sessions
# (`cpu_split`): the round's total includes the ramp of offers and the idle tail.
CPU_SAMPLE_S = 0.25
HEADER = struct.Struct("<4sBBBBIIdHH")  # a drive message's header
PACKET_DRIVE_BYTES = struct.Struct("<I")  # a frame packet's drive length, at offset 8
WIRE_VERSION = 1  # the frame packet and drive message this bench reads (the baseline's answer names none)
TRANSPORTS = ("webrtc", "ws", "ws-deflate")
TRANSPORT_NAMES = {"ws": "One WebSocket a session (frame packets: drive + int16 audio)",
                   "ws-deflate": "One WebSocket a session, each client asking for permessage-deflate as a browser does",
                   "webrtc": "WebRTC (drives on a data channel, voice on an Opus audio track)"}


def _cpu_seconds(pid: int) -> float:
    """User + system CPU seconds of process `pid` (its threads included)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _children(pid: int) -> list[int]:
    """The running child processes of `pid` (nginx's workers under its master)."""
    found = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        text = (task / "children").read_text() if (task / "children").is_file() else ""
        found += [int(child) for child in text.split()]
    return found


def _auth(token: str | None) -> dict[str, str]:
    """The headers that carry a client's token (none for a server without tokens)."""
    return {"Authorization": f"Bearer {token}"} if token else {}


def _check_wire(answer: dict) -> None:
    """A server that names its wire version must speak the one this bench reads (the baseline names none)."""
    if answer.get("wire", WIRE_VERSION) != WIRE_VERSION:
        raise RuntimeError(f"the server speaks wire version {answer['wire']}; this bench reads {WIRE_VERSION}")


async def _client(url: str, delay: float, speak_s: float, idle_s: float, chunk_ms: float, packets: dict,
                  token: str | None = None) -> dict:
    """One load client on WebRTC: drives on the data channel, the voice's RTP packets counted; `token` (None: no
    tokens) goes with every request."""
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
        async with aiohttp.ClientSession(headers=_auth(token)) as http:
            sent = time.monotonic()
            async with http.post(f"{url}/offer", json={"sdp": pc.localDescription.sdp,
                                                        "type": pc.localDescription.type, "source": "file",
                                                        "chunk_ms": chunk_ms}) as reply:
                if reply.status != 200:
                    raise RuntimeError(f"offer: HTTP {reply.status}: {await reply.text()}")
                answer = await reply.json()
            _check_wire(answer)
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


async def _ws_client(url: str, delay: float, speak_s: float, idle_s: float, chunk_ms: float,
                     token: str | None = None, deflate: bool = False) -> dict:
    """One load client on the WebSocket transport: reads every frame packet (its drive header and its audio's
    length; the audio is not played: that is the page's cost), barges in after `speak_s` and leaves `idle_s`
    later. `token` (None: no tokens) goes with the socket's request; a close by the server before the client
    leaves is recorded (`server_closed`: its close code). `deflate`: the handshake asks for permessage-deflate, as
    a browser's does (`compressed`: whether the server took it)."""
    import aiohttp

    await asyncio.sleep(delay)
    result: dict = {"drives": [], "error": None, "audio_packets": 0, "audio_lost": 0, "audio_per_s": 0.0,
                    "server_closed": None}
    try:
        async with aiohttp.ClientSession(headers=_auth(token)) as http:
            sent = time.monotonic()
            async with http.ws_connect(url.replace("http://", "ws://") + "/live", max_msg_size=1 << 20,
                                       compress=15 if deflate else 0) as socket:
                result["compressed"] = bool(socket.compress)
                await socket.send_json({"source": "file", "chunk_ms": chunk_ms})
                answer = await socket.receive_json(timeout=120)
                if "error" in answer:
                    raise RuntimeError(f"start: {answer['error']}")
                _check_wire(answer)
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
                    result["server_closed"] = socket.close_code

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
                    queue, transport: str = "webrtc", tokens: list | None = None) -> None:
    """`count` load clients on one event loop (`tokens`: each one's, or None without tokens); their results go to
    `queue`."""
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

    tokens = tokens or [None] * count

    async def main() -> list:
        if transport in ("ws", "ws-deflate"):
            return await asyncio.gather(*(_ws_client(url, (first + k) * STAGGER_S, speak_s, idle_s, chunk_ms,
                                                     tokens[k], transport == "ws-deflate") for k in range(count)))
        return await asyncio.gather(*(_client(url, (first + k) * STAGGER_S, speak_s, idle_s, chunk_ms,
                                              packets, tokens[k]) for k in range(count)))

    queue.put(asyncio.run(main()))


def serving(command: list[str], url: str, timeout: float, name: str = "live_server.py", *,
            log_path: Path | None = None, cwd: Path | None = None, env: dict | None = None) -> subprocess.Popen:
    """Start `command` (the server `name`) and return it once `url` answers; RuntimeError with its output's tail if
    it exits first or does not answer within `timeout` seconds (then it is killed). Its output goes to the
    returned process's stdout pipe, or to `log_path` (a server with many sessions logs more than a pipe holds
    until it is read); `cwd` and `env` as for subprocess.Popen."""
    if log_path is None:
        process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=cwd,
                                   env=env)
    else:
        with open(log_path, "w") as log:
            process = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT, text=True, cwd=cwd, env=env)

    def output_tail() -> str:
        text = process.stdout.read() if log_path is None else Path(log_path).read_text(errors="replace")
        return text[-3000:]

    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            urllib.request.urlopen(url, timeout=1).read()
            return process
        except OSError:
            if process.poll() is not None:
                raise RuntimeError(f"{name} exited: {output_tail()}") from None
            time.sleep(0.2)
    process.kill()
    process.wait()
    raise RuntimeError(f"{name} did not answer within {timeout:g} s: {output_tail()}")


@dataclass(frozen=True)
class ServerSettings:
    """What every server under test runs with (the same for the baseline and gt-serve)."""

    lookahead_ms: float = 160.0
    batch_frames: int = 1
    context_ms: float = 1000.0
    streaming: bool = True  # False: gt-serve --no-stream (a baseline from before streaming never streams)

    def arguments(self) -> list[str]:
        """The options both servers' command lines share."""
        return ["--client-render", "--audio", str(SPEECH), "--lookahead-ms", str(self.lookahead_ms),
                "--batch-frames", str(self.batch_frames), "--context-ms", str(self.context_ms),
                *([] if self.streaming else ["--no-stream"])]


@dataclass(frozen=True)
class Baseline:
    """An older server script (`samples/live_server.py` of an earlier commit, or a script that runs that commit's
    gt-serve: `from gaussiantalker.cli.serve import main; main()`) and the checkout of that commit
    whose `src/` it imports (put first on PYTHONPATH, and its working folder, so the package it loads is that
    commit's and not this checkout's editable install)."""

    script: Path
    checkout: Path
    bundle: Path | None = None  # the bundle it serves (None: the new server's), e.g. the speaker as its commit exports

    @property
    def src(self) -> Path:
        return self.checkout / "src"

    def env(self) -> dict:
        """The environment the baseline runs in: this one, with the checkout's src/ first on PYTHONPATH."""
        paths = [str(self.src), *filter(None, os.environ.get("PYTHONPATH", "").split(os.pathsep))]
        return {**os.environ, "PYTHONPATH": os.pathsep.join(paths)}

    def package(self) -> Path:
        """Where the baseline's `gaussiantalker.runtime` comes from, asked of the interpreter it runs in;
        ValueError unless it is the checkout's."""
        probe = subprocess.run([sys.executable, "-c", "import gaussiantalker.runtime as r; print(r.__file__)"],
                               cwd=self.src, env=self.env(), capture_output=True, text=True, timeout=120)
        if probe.returncode != 0:
            raise ValueError(f"the baseline's package does not import from {self.src}: "
                             f"{probe.stderr.strip()[-500:]}")
        found = Path(probe.stdout.strip().splitlines()[-1]).resolve()
        if not found.is_relative_to(self.src.resolve()):
            raise ValueError(f"the baseline would import gaussiantalker from {found}, not from {self.src}")
        return found

    def commit(self) -> str | None:
        """The checkout's commit, "+changes" after it where its src/ differs from it (None where git cannot
        say)."""
        probe = subprocess.run(["git", "-C", str(self.checkout), "rev-parse", "HEAD"], capture_output=True,
                               text=True)
        if not probe.stdout.strip():
            return None
        changed = subprocess.run(["git", "-C", str(self.checkout), "diff", "--quiet", "HEAD", "--", "src"],
                                 capture_output=True).returncode != 0
        return probe.stdout.strip() + ("+changes" if changed else "")

    @property
    def is_gt_serve(self) -> bool:
        """Whether the script runs an older gt-serve (`gaussiantalker.cli.serve`), not a live_server.py sample."""
        text = self.script.read_text(errors="replace") if self.script.is_file() else ""
        return "gaussiantalker.cli.serve" in text or self.script.name == "serve.py"

    def arguments(self, max_sessions: int) -> list[str]:
        """Options of its own: an older gt-serve (a script that runs `gaussiantalker.cli.serve`) runs without a
        secret, so it opens /health, which the bench reads, with --debug, and every load client is the same
        address, so the sessions one client may hold are raised to the round's N."""
        if not self.is_gt_serve:
            return []
        return ["--debug", "--max-sessions", str(max_sessions), "--max-sessions-per-client", str(max_sessions)]

    def describe(self) -> dict:
        """The baseline as the report names it; ValueError where its package would not be its checkout's."""
        return {"script": str(self.script), "checkout": str(self.checkout), "commit": self.commit(),
                "package": str(self.package()), "name": "gt-serve" if self.is_gt_serve else self.script.name,
                "bundle": None if self.bundle is None else str(self.bundle)}


def baseline_checkout(script: Path) -> Path | None:
    """The git checkout a baseline script lies in (None when it lies in none)."""
    probe = subprocess.run(["git", "-C", str(script.resolve().parent), "rev-parse", "--show-toplevel"],
                           capture_output=True, text=True)
    return Path(probe.stdout.strip()) if probe.returncode == 0 and probe.stdout.strip() else None


@dataclass
class Server:
    """A server under test: `label` "new" (gt-serve, tokens signed with `secret`) or "old" (the baseline, no
    tokens), its process, base URL, command and log file."""

    label: str
    process: subprocess.Popen
    url: str
    command: list[str]
    log_path: Path
    secret: bytes | None = None
    runs: list[dict] = field(default_factory=list)  # its rows, one per N and round
    # Replicas behind a load balancer: `process` is the balancer (nginx), `replicas` the gt-serve processes whose
    # /health answers at `replica_urls`; every process's CPU counts. `command`: the last replica's.
    replicas: list[subprocess.Popen] = field(default_factory=list)
    replica_urls: list[str] = field(default_factory=list)

    def cpu_seconds(self) -> float:
        """CPU seconds so far of every process serving its sessions (a balancer's workers too)."""
        if not self.replicas:
            return _cpu_seconds(self.process.pid)
        pids = [*(replica.pid for replica in self.replicas), self.process.pid, *_children(self.process.pid)]
        return sum(_cpu_seconds(pid) for pid in dict.fromkeys(pids))

    def client_tokens(self, count: int, tag: str) -> list[str | None]:
        """A token per load client, each with its own subject (gt-serve caps sessions per subject)."""
        if self.secret is None:
            return [None] * count
        from gaussiantalker.serve import mint_token

        return [mint_token(self.secret, TOKEN_TTL_S, subject=f"gt-bench-{tag}-{k}") for k in range(count)]

    def _admin_headers(self) -> dict[str, str]:
        """An admin token's header where it checks tokens."""
        if self.secret is None:
            return {}
        from gaussiantalker.serve import mint_token

        return _auth(mint_token(self.secret, 60.0, subject="gt-bench-admin", admin=True))

    def open_sessions(self) -> int:
        """The sessions it holds now (/health, with an admin token where it checks tokens)."""
        headers = self._admin_headers()
        return sum(json.loads(urllib.request.urlopen(urllib.request.Request(f"{url}/health", headers=headers),
                                                     timeout=10).read())["sessions"]
                   for url in self.replica_urls or [self.url])

    def counters(self) -> tuple[dict[str, float] | None, dict[str, float] | None]:
        """From one read of every process's /metrics, summed over them: the rows its pools' streaming translator
        calls made so far, by kind, and the CPU seconds its client-render pool threads spent, by part (translator,
        frames); each None where it is not counted (an older commit's server, or /metrics not answering)."""
        headers, rows, pool = self._admin_headers(), {}, {}
        for url in self.replica_urls or [self.url]:
            try:
                text = urllib.request.urlopen(urllib.request.Request(f"{url}/metrics", headers=headers),
                                              timeout=10).read().decode("utf-8")
            except (OSError, ValueError):
                return None, None
            for totals, read in ((rows, translator_rows_of), (pool, pool_cpu_of)):
                for key, value in read(text).items():
                    totals[key] = totals.get(key, 0.0) + value
        return rows or None, pool or None

    def wait_idle(self, timeout: float = 30.0) -> bool:
        """Wait until every session has closed (before the next round); False if some are open at `timeout`."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.open_sessions() == 0:
                return True
            time.sleep(0.5)
        return False

    def stop(self) -> dict:
        """Stop it (replicas first, then their balancer); its log's tail and how many of its lines name an error
        or a traceback (every replica's log, for replicas)."""
        for process in [*self.replicas, self.process]:
            process.terminate()
            try:
                process.wait(timeout=60)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()
        logs = [self.log_path.with_name(f"{self.log_path.stem}-{k}.log") for k in range(len(self.replicas))]
        text = "".join(path.read_text(errors="replace") for path in logs or [self.log_path] if path.is_file())
        errors = sum(" ERROR " in line or "Traceback" in line for line in text.splitlines())
        return {"log_tail": text[-2000:], "log_error_lines": errors}


def _start_new_server(bundle: Path, settings: ServerSettings, folder: Path, max_sessions: int,
                      replicas: int = 1, options: tuple[str, ...] = ()) -> Server:
    """gt-serve on a free loopback port, tokens on (a fresh secret in `folder`), once /readyz answers; with
    `replicas` > 1, that many gt-serve processes sharing the secret behind nginx (deploy/nginx.conf: least_conn,
    WebSockets passed through), the clients sent to nginx. `options`: more of gt-serve's, this server's alone."""
    from gaussiantalker.serve import new_secret, read_secret

    secret_path = folder / "secret.txt"
    descriptor = os.open(secret_path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(descriptor, "w") as file:
        file.write(new_secret() + "\n")
    secret = read_secret(secret_path)

    def start(port: int, log_path: Path) -> tuple[subprocess.Popen, list[str]]:
        command = [sys.executable, "-m", SERVE_MODULE, str(bundle), "--port", str(port), "--secret-file",
                   str(secret_path), "--max-sessions", str(max_sessions), *settings.arguments(), *options]
        return serving(command, f"http://127.0.0.1:{port}/readyz", SERVER_START_S, name=f"gt-serve :{port}",
                       log_path=log_path), command

    if replicas == 1:
        port = free_port()
        process, command = start(port, folder / "gt-serve.log")
        return Server("new", process, f"http://127.0.0.1:{port}", command, folder / "gt-serve.log", secret=secret)
    return _start_replicas(start, folder, replicas, secret)


def _start_replicas(start, folder: Path, replicas: int, secret: bytes | None, label: str = "new") -> Server:
    """`replicas` gt-serve processes (`start(port, log_path)`) behind nginx on loopback (`label` "old": the
    baseline's, logs and nginx in a folder of their own)."""
    if label != "new":
        folder = folder / label
        folder.mkdir()
    from .replicas import nginx_binary, nginx_config

    nginx = nginx_binary()
    if nginx is None:
        raise RuntimeError("--replicas needs nginx, the load balancer in front of them (Debian: apt-get install "
                           "nginx; docs/serve.md, \"Replicas behind a load balancer\")")
    *ports, listen, backend = (free_port() for _ in range(replicas + 2))
    started: list[subprocess.Popen] = []
    try:
        command = []
        for k, port in enumerate(ports):
            process, command = start(port, folder / f"gt-serve-{k}.log")
            started.append(process)
        prefix = folder / "nginx"
        (prefix / "logs").mkdir(parents=True)
        (prefix / "nginx.conf").write_text(nginx_config(listen, ports, backend))
        url = f"http://127.0.0.1:{listen}"
        balancer = serving([nginx, "-p", str(prefix), "-c", str(prefix / "nginx.conf")], f"{url}/readyz", 30,
                           name="nginx", log_path=prefix / "logs" / "stdout.log")
    except BaseException:
        for process in started:
            process.kill()
            process.wait()
        raise
    return Server(label, balancer, url, command, folder / "gt-serve.log", secret=secret, replicas=started,
                  replica_urls=[f"http://127.0.0.1:{port}" for port in ports])


def _start_baseline_server(baseline: Baseline, bundle: Path, settings: ServerSettings, folder: Path,
                           max_sessions: int, replicas: int = 1) -> Server:
    """The baseline script on a free loopback port, on its checkout's package, once /health answers; with
    `replicas` > 1 (an older gt-serve only), that many behind nginx, as the new server's."""
    def start(port: int, log_path: Path) -> tuple[subprocess.Popen, list[str]]:
        command = [sys.executable, str(baseline.script), str(baseline.bundle or bundle), "--port", str(port),
                   *settings.arguments(), *baseline.arguments(max_sessions)]
        return serving(command, f"http://127.0.0.1:{port}/health", SERVER_START_S, name=baseline.script.name,
                       log_path=log_path, cwd=baseline.src, env=baseline.env()), command

    if replicas > 1:
        if not baseline.is_gt_serve:
            raise ValueError("replicas of the baseline need a baseline that runs gt-serve (its /readyz behind "
                             "nginx), not a live_server.py sample")
        return _start_replicas(start, folder, replicas, None, label="old")
    port = free_port()
    process, command = start(port, folder / "baseline.log")
    return Server("old", process, f"http://127.0.0.1:{port}", command, folder / "baseline.log")


def _run_clients(url: str, tokens: list, speak_s: float, idle_s: float, chunk_ms: float, transport: str) -> list:
    """One round's load clients (len(tokens) of them, CLIENTS_PER_PROCESS a process); their records."""
    context = multiprocessing.get_context("spawn")
    n = len(tokens)
    queue = context.Queue()
    processes = []
    for first in range(0, n, CLIENTS_PER_PROCESS):
        count = min(CLIENTS_PER_PROCESS, n - first)
        process = context.Process(target=_client_process, args=(url, count, first, speak_s, idle_s, chunk_ms, queue,
                                                                transport, tokens[first:first + count]))
        process.start()
        processes.append(process)
    clients = []
    for _ in processes:
        clients += queue.get(timeout=120 + n * STAGGER_S + speak_s + idle_s)
    for process in processes:
        process.join(30)
    return clients


class _CpuSampler(threading.Thread):
    """The server's CPU seconds read every CPU_SAMPLE_S while a round runs: `samples`, (time.monotonic(), CPU s)
    pairs, the clients' clock (CLOCK_MONOTONIC is the machine's, shared by its processes)."""

    def __init__(self, server: Server) -> None:
        super().__init__(name="gt-bench-cpu", daemon=True)
        self.server, self.samples, self._done = server, [], threading.Event()

    def run(self) -> None:
        while not self._done.is_set():
            self.samples.append((time.monotonic(), self.server.cpu_seconds()))
            self._done.wait(CPU_SAMPLE_S)

    def stop(self) -> list[tuple[float, float]]:
        self._done.set()
        self.join()
        self.samples.append((time.monotonic(), self.server.cpu_seconds()))
        return self.samples


def cpu_terms(clients: list[dict], samples: list[tuple[float, float]]) -> tuple[np.ndarray, np.ndarray]:
    """Per interval between two CPU samples: (the server's CPU rate in cores, [1, sessions speaking, sessions idle]
    averaged over the interval). A client speaks from its answer to its barge-in and idles until it leaves."""
    times = np.array([t for t, _ in samples])
    cpu = np.array([c for _, c in samples])
    lo, hi = times[:-1], times[1:]
    width = np.maximum(hi - lo, 1e-9)
    speaking, idle = np.zeros(len(lo)), np.zeros(len(lo))
    for client in clients:
        if client["error"] or "closed" not in client:
            continue
        start, barge, end = client["answered"], client["interrupt_sent"], client["closed"]
        speaking += np.clip(np.minimum(hi, barge) - np.maximum(lo, start), 0, None)
        idle += np.clip(np.minimum(hi, end) - np.maximum(lo, barge), 0, None)
    return np.diff(cpu) / width, np.stack([np.ones(len(lo)), speaking / width, idle / width], 1)


def translator_rows_of(exposition: str) -> dict[str, float]:
    """gt_serve_translator_rows_total by kind (committed, provisional) from a /metrics body; {} where it has none."""
    return _counter_of(exposition, "gt_serve_translator_rows_total", "kind")


def pool_cpu_of(exposition: str) -> dict[str, float]:
    """gt_serve_pool_cpu_seconds_total by part (translator, frames) from a /metrics body; {} where it has none."""
    return _counter_of(exposition, "gt_serve_pool_cpu_seconds_total", "part")


def _counter_of(exposition: str, name: str, label: str) -> dict[str, float]:
    """The samples of counter `name` in a /metrics body, summed by their `label`."""
    from prometheus_client.parser import text_string_to_metric_families

    values: dict[str, float] = {}
    for family in text_string_to_metric_families(exposition):
        for sample in family.samples:
            if sample.name == name:
                key = sample.labels.get(label, "")
                values[key] = values.get(key, 0.0) + sample.value
    return values


def round_pool_cpu(before: dict | None, after: dict | None) -> dict | None:
    """A round's pool CPU seconds by part (`Server.counters` before and after it); None where it is not counted."""
    if after is None:
        return None
    before = before or {}
    return {part: after.get(part, 0.0) - before.get(part, 0.0) for part in ("translator", "frames")}


def _pooled_pool_cpu(rows: list[dict]) -> dict | None:
    """Every round's pool CPU summed by part (None unless each round has it)."""
    return _summed_rounds(rows, "pool_cpu", ("translator", "frames"))


def _summed_rounds(rows: list[dict], field: str, keys: tuple[str, ...]) -> dict | None:
    """Every round's `field` (a dict of `keys`) summed key by key; None unless each round has it."""
    counted = [row.get(field) for row in rows]
    if not counted or any(count is None for count in counted):
        return None
    return {key: sum(count[key] for count in counted) for key in keys}


def speaking_seconds(clients: list[dict]) -> float:
    """Session-seconds the clients' voices spoke: from each answer to its barge-in."""
    return sum(max(0.0, client["interrupt_sent"] - client["answered"]) for client in clients
               if not client["error"] and "interrupt_sent" in client)


def round_rows(before: dict | None, after: dict | None, clients: list[dict]) -> dict | None:
    """A round's translator rows (`Server.counters` before and after it) and its speaking session-seconds;
    None where the server does not count rows."""
    if after is None:
        return None
    before = before or {}
    return {"committed": after.get("committed", 0.0) - before.get("committed", 0.0),
            "provisional": after.get("provisional", 0.0) - before.get("provisional", 0.0),
            "speaking_s": speaking_seconds(clients)}


def _pooled_rows(rows: list[dict]) -> dict | None:
    """Every round's translator rows summed (None unless each round has them)."""
    return _summed_rounds(rows, "translator_rows", ("committed", "provisional", "speaking_s"))


def cpu_split(parts: list[tuple[np.ndarray, np.ndarray]]) -> dict | None:
    """Least squares over every interval of `parts` (`cpu_terms` of one or more rounds): server CPU = base +
    speaking x (CPU s per speaking session-second) + idle x (per idle session-second); None with fewer than 8
    intervals or no session in them."""
    rates = np.concatenate([rate for rate, _ in parts]) if parts else np.zeros(0)
    design = np.concatenate([terms for _, terms in parts]) if parts else np.zeros((0, 3))
    if len(rates) < 8 or not design[:, 1:].any():
        return None
    (base, speaking, idle), *_ = np.linalg.lstsq(design, rates, rcond=None)
    return {"base_cores": float(base), "speaking_s_per_session_s": float(speaking),
            "idle_s_per_session_s": float(idle), "intervals": int(len(rates))}


def _run_round(server: Server, n: int, index: int, speak_s: float, idle_s: float, chunk_ms: float,
               transport: str) -> tuple[dict, list, tuple[np.ndarray, np.ndarray]]:
    """N load clients against `server` once: the round's row, its clients' records and its `cpu_terms`."""
    tokens = server.client_tokens(n, f"n{n}-r{index}")
    load_before = os.getloadavg()
    rows_before, pool_before = server.counters()
    sampler = _CpuSampler(server)
    sampler.start()
    started = time.monotonic()
    clients = _run_clients(server.url, tokens, speak_s, idle_s, chunk_ms, transport)
    wall_s = time.monotonic() - started
    samples = sampler.stop()
    terms = cpu_terms(clients, samples)
    row = {"server": server.label, "n": n, "round": index,
           **_analyse(clients, samples[-1][1] - samples[0][1], wall_s), "cpu_split": cpu_split([terms]),
           "load_before": load_before, "load_after": os.getloadavg()}
    rows_after, pool_after = server.counters()
    row["translator_rows"] = round_rows(rows_before, rows_after, clients)
    row["pool_cpu"] = round_pool_cpu(pool_before, pool_after)
    row["drained"] = server.wait_idle()  # every session closed before the next round
    return row, clients, terms


def _round_line(row: dict) -> str:
    """A round's progress line."""
    return (f"N={row['n']} round {row['round'] + 1} {row['server']}: late {100 * row['late_share']:.1f}%, "
            f"{_cpu(row['cpu_s_per_session_s'])} CPU s per session-second, first frame p50 "
            f"{_ms(row['first_frame']['p50_ms'])} ms, barge-in p50 {_ms(row['barge_in']['p50_ms'])} ms, failed "
            f"{row['failed']}, closed by the server {row['server_closed']}, load {row['load_before'][0]:.2f}->"
            f"{row['load_after'][0]:.2f}" + ("" if row["drained"] else ", sessions still open after 30 s"))


def _pooled(rows: list[dict], clients: list, terms: list[tuple[np.ndarray, np.ndarray]]) -> dict:
    """One server's figures for one N over all its rounds: every client's record together, CPU summed, its split
    fitted over every round's intervals."""
    return {"n": rows[0]["n"], "rounds": len(rows),
            **_analyse(clients, sum(r["server_cpu_s"] for r in rows), sum(r["wall_s"] for r in rows)),
            "cpu_split": cpu_split(terms), "translator_rows": _pooled_rows(rows), "pool_cpu": _pooled_pool_cpu(rows),
            "load_before": rows[0]["load_before"],
            "load_after": rows[-1]["load_after"]}


def _alternate(servers: list[Server], counts: list[int], rounds: int, speak_s: float, idle_s: float,
               chunk_ms: float, transport: str, log) -> dict[str, list[dict]]:
    """For each N, `rounds` rounds of every server in turn (old, new, old, new ...); each server's pooled row
    per N, by label (every round's row goes to the server's `runs`)."""
    pooled: dict[str, list[dict]] = {server.label: [] for server in servers}
    for n in counts:
        records: dict[str, tuple[list, list, list]] = {server.label: ([], [], []) for server in servers}
        for index in range(rounds):
            for server in servers:
                row, clients, terms = _run_round(server, n, index, speak_s, idle_s, chunk_ms, transport)
                log(_round_line(row))
                server.runs.append(row)
                records[server.label][0].append(row)
                records[server.label][1].extend(clients)
                records[server.label][2].append(terms)
        for label, (rows, clients, terms) in records.items():
            pooled[label].append(_pooled(rows, clients, terms))
    return pooled


def _ratio(new, old) -> float | None:
    """new / old, None where either is missing or old is 0."""
    return new / old if new is not None and old else None


def _ratios(new_runs: list[dict], old_runs: list[dict]) -> list[dict]:
    """Per N: gt-serve's figures over the baseline's."""
    out = []
    for new, old in zip(new_runs, old_runs, strict=True):
        out.append({"n": new["n"], "late_share": _ratio(new["late_share"], old["late_share"]),
                    "first_frame_p50": _ratio(new["first_frame"]["p50_ms"], old["first_frame"]["p50_ms"]),
                    "cpu_s_per_session_s": _ratio(new["cpu_s_per_session_s"], old["cpu_s_per_session_s"]),
                    "barge_in_p50": _ratio(new["barge_in"]["p50_ms"], old["barge_in"]["p50_ms"])})
    return out


def _largest_sustained(runs: list[dict]) -> int:
    """The largest N with at most 5% late frames and no failed client (0: none)."""
    sustained = [row["n"] for row in runs if row["late_share"] <= 0.05 and not row["failed"]]
    return max(sustained) if sustained else 0


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
            "audio_packets_lost": lost, "server_closed": sum(bool(c.get("server_closed")) for c in clients),
            "compressed": sum(bool(c.get("compressed")) for c in clients)}


def run_live_clients_bench(bundle: Path, counts: list[int], lookahead_ms: float = 160.0,
                           speak_s: float = SPEAK_S, idle_s: float = IDLE_S, chunk_ms: float = 20.0,
                           log=print, transport: str = "webrtc", batch_frames: int = 1,
                           context_ms: float = 1000.0, baseline: Baseline | None = None, rounds: int = 1,
                           replicas: int = 1, baseline_replicas: int = 1, stream_delay_ms: float | None = None) -> dict:
    """Start gt-serve (tokens on; `replicas` > 1: that many behind nginx) and, with `baseline`, the baseline
    script (`baseline_replicas` of it), then for each N `rounds` rounds of its load clients on `transport`
    ("webrtc": audio track and data channel; "ws": one WebSocket; "ws-deflate": one asking for permessage-deflate)
    against each server in turn; returns gt-serve's figures per N (`runs`), the baseline's and the ratios.
    `stream_delay_ms`: gt-serve's --stream-delay-ms (the baseline runs its default stream)."""
    if transport not in TRANSPORTS:
        raise ValueError(f"transport must be one of {TRANSPORTS}, got {transport!r}")
    settings = ServerSettings(lookahead_ms, batch_frames, context_ms)
    described = baseline.describe() if baseline is not None else None
    servers: list[Server] = []
    logs: dict[str, dict] = {}
    with tempfile.TemporaryDirectory(prefix="gt-bench-live-clients-") as folder:
        try:
            cap = max(DEFAULT_MAX_SESSIONS, max(counts))
            if baseline is not None:
                servers.append(_start_baseline_server(baseline, bundle, settings, Path(folder), cap,
                                                      baseline_replicas))
            options = () if stream_delay_ms is None else ("--stream-delay-ms", f"{stream_delay_ms:g}")
            servers.append(_start_new_server(bundle, settings, Path(folder), cap, replicas, options))
            pooled = _alternate(servers, counts, rounds, speak_s, idle_s, chunk_ms, transport, log)
        finally:
            for server in servers:
                logs[server.label] = server.stop()
    new = next(server for server in servers if server.label == "new")
    result = {"runs": pooled["new"], "largest_n_within_5pct_late": _largest_sustained(pooled["new"]),
              "round_runs": [row for server in servers for row in server.runs], "rounds": rounds,
              "late_tolerance_ms": 1000 * LATE_TOLERANCE_S, "speak_s": speak_s, "idle_s": idle_s,
              "lookahead_ms": lookahead_ms, "chunk_ms": chunk_ms, "transport": transport, "batch_frames": batch_frames,
              "context_ms": context_ms, "stream_delay_ms": stream_delay_ms,
              "server": {"command": new.command, "tokens": True, "replicas": replicas},
              "server_log_tail": logs["new"]["log_tail"], "server_log_error_lines": logs["new"]["log_error_lines"],
              "baseline": None, "ratios": None}
    if baseline is not None:
        old = pooled["old"]
        result["baseline"] = {**described, "command": servers[0].command, "tokens": False, "runs": old,
                              "replicas": baseline_replicas,
                              "largest_n_within_5pct_late": _largest_sustained(old),
                              "server_log_tail": logs["old"]["log_tail"],
                              "server_log_error_lines": logs["old"]["log_error_lines"]}
        result["ratios"] = _ratios(pooled["new"], old)
    return result


def _ms(value) -> str:
    return "–" if value is None else f"{value:.0f}"


def _cpu(value) -> str:
    return "–" if value is None else f"{value:.3f}"


def _split(split: dict | None) -> str:
    """A row's speaking / idle CPU per session-second (`cpu_split`), or – without one (older runs)."""
    if not split:
        return "–"
    return f"{split['speaking_s_per_session_s']:.3f} / {split['idle_s_per_session_s']:.3f}"


def _rows(rows: dict | None) -> str:
    """Translator rows per speaking session-second, and how many of them provisional, or – (not counted)."""
    if not rows or rows["speaking_s"] <= 0:
        return "–"
    return (f"{(rows['committed'] + rows['provisional']) / rows['speaking_s']:.1f} "
            f"({rows['provisional'] / rows['speaking_s']:.1f})")


def _pool(row: dict) -> str:
    """The pool threads' CPU per session-second, in the translator calls and the rest, or – (not counted)."""
    pool, session_s = row.get("pool_cpu"), row.get("session_s", 0.0)
    if not pool or session_s <= 0:
        return "–"
    return f"{pool['translator'] / session_s:.4f} / {pool['frames'] / session_s:.4f}"


def _times(value) -> str:
    return "–" if value is None else f"{value:.2f}×"


def _detail_table(runs: list[dict], largest: int, tolerance_ms: float) -> str:
    """One server's figures per N, every column."""
    lines = ["| N | late frames | lost | jitter p50 / p99 | behind schedule | delay p50 / p99 | server CPU s per "
             "session-s | speaking / idle | pool: translator / frames | translator rows per speaking session-s "
             "(provisional) | first frame p50 / p95 | barge-in p50 / p95 | audio packets | failed | load avg (1 min) "
             "before → after |",
             "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for row in runs:
        lines.append(f"| {row['n']} | {100 * row['late_share']:.1f}% ({row['late_frames']}/{row['frames_due']}) | "
                     f"{row['missing_frames']} | {_ms(row['jitter_p50_ms'])} / {_ms(row['jitter_p99_ms'])} ms | "
                     f"{100 * row['behind_share']:.1f}% | {_ms(row['delay_p50_ms'])} / {_ms(row['delay_p99_ms'])} "
                     f"ms | {_cpu(row['cpu_s_per_session_s'])} | {_split(row.get('cpu_split'))} | "
                     f"{_pool(row)} | {_rows(row.get('translator_rows'))} | "
                     f"{_ms(row['first_frame']['p50_ms'])} / "
                     f"{_ms(row['first_frame']['p95_ms'])} ms | {_ms(row['barge_in']['p50_ms'])} / "
                     f"{_ms(row['barge_in']['p95_ms'])} ms | {100 * row['audio_packets_per_expected']:.0f}% | "
                     f"{row['failed']} | {row['load_before'][0]:.2f} → {row['load_after'][0]:.2f} |")
    lines.append("")
    lines.append("Server CPU per session-second: the round's CPU over its sessions' seconds (offers' ramp and idle "
                 "tail included); speaking / idle: a least-squares split of the CPU read every "
                 f"{CPU_SAMPLE_S:g} s into a base and a cost per speaking and per idle session-second (`cpu_split`); "
                 "pool: what the client-render pool threads spent of it in the translator calls and in the rest of "
                 "their work (`gt_serve_pool_cpu_seconds_total`), the event loop's and the process's other threads' "
                 "being the remainder. "
                 "Translator rows: the voice frames the server's streaming translator calls made "
                 "(`gt_serve_translator_rows_total`) over the seconds the clients' voices spoke; provisional ones are "
                 "made again once their lookahead is in.")
    lines.append(f"Largest N with at most 5% late frames: **{largest}**. Late: a drive arriving more than "
                 f"{tolerance_ms:.0f} ms after the page's clock (the smallest arrival − pts of the last 2 s, which "
                 "follows the voice) would show it, or lost. Behind schedule: more than "
                 f"{tolerance_ms:.0f} ms after start + pts on the wall clock (driver stalls, which delay the voice "
                 "alike).")
    return "\n".join(lines)


def server_name(result: dict) -> str:
    """gt-serve as a table names it: one process, or its replicas behind nginx."""
    replicas = result.get("server", {}).get("replicas", 1)
    return "gt-serve" if replicas == 1 else f"{replicas} gt-serve replicas behind nginx"


def baseline_name(result: dict) -> str:
    """The baseline as a table names it: its commit's short hash, or its script."""
    baseline = result["baseline"]
    commit = baseline.get("commit")
    name = commit[:7] + commit[40:] if commit else baseline["script"]
    replicas = baseline.get("replicas", 1)
    return name if replicas == 1 else f"{name} ({replicas} replicas behind nginx)"


def _comparison_table(result: dict) -> str:
    """Per N: the baseline's row, gt-serve's, and gt-serve's over the baseline's."""
    old_name = f"{baseline_name(result)} {result['baseline'].get('name', 'live_server.py')}"
    lines = ["| N | server | late frames | first frame p50 | server CPU s per session-s | barge-in p50 | failed |",
             "|---:|---|---:|---:|---:|---:|---:|"]
    for old, new, ratio in zip(result["baseline"]["runs"], result["runs"], result["ratios"], strict=True):
        for name, row in ((old_name, old), (f"{server_name(result)} (tokens)", new)):
            lines.append(f"| {row['n']} | {name} | {100 * row['late_share']:.1f}% | "
                         f"{_ms(row['first_frame']['p50_ms'])} ms | {_cpu(row['cpu_s_per_session_s'])} | "
                         f"{_ms(row['barge_in']['p50_ms'])} ms | {row['failed']} |")
        lines.append(f"| {ratio['n']} | **new / old** | {_times(ratio['late_share'])} | "
                     f"{_times(ratio['first_frame_p50'])} | {_times(ratio['cpu_s_per_session_s'])} | "
                     f"{_times(ratio['barge_in_p50'])} | |")
    lines.append("")
    lines.append(f"{result['rounds']} round(s) of each server per N, alternating ({old_name} first); each figure "
                 "pools the clients of all its server's rounds (server CPU: summed over them). Every round's own "
                 "figures are in the JSON (`round_runs`).")
    return "\n".join(lines)


def live_clients_table(result: dict) -> str:
    """The report's tables: gt-serve's figures per N; with a baseline, the side-by-side comparison first and the
    baseline's own figures after."""
    tolerance = result["late_tolerance_ms"]
    new = _detail_table(result["runs"], result["largest_n_within_5pct_late"], tolerance)
    if not result.get("baseline"):
        return new
    old = _detail_table(result["baseline"]["runs"], result["baseline"]["largest_n_within_5pct_late"], tolerance)
    return (f"{_comparison_table(result)}\n\n{server_name(result)} (tokens on):\n\n{new}\n\n{baseline_name(result)} "
            f"{result['baseline'].get('name', 'live_server.py')}:\n\n{old}")
