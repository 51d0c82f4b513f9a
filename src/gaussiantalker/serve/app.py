"""The aiohttp application of `gt-serve` (docs/serve.md): the access rules and one-line errors as middleware,
the mode's routes (pixel or client-render), the admin routes, and the operations routes /healthz, /readyz and
/metrics."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

from aiohttp import web

from .access import AccessPolicy, one_line_errors
from .keys import LIMITS, METRICS, SESSIONS
from .limits import Admission, ServeLimits
from .metrics import CONTENT_TYPE, ServeMetrics
from .sessions import Sessions
from .voices import VoiceFiles

SAMPLE_SPEECH = Path(__file__).resolve().parents[3] / "samples" / "demo_speech.wav"  # in a checkout


@dataclass(frozen=True)
class ServeOptions:
    """How a server runs its sessions: the mode, the live sessions' settings, and who may connect."""

    client_render: bool = False
    secret: bytes | None = None  # None: no tokens (a loopback address only; the command enforces it)
    allow_origins: tuple[str, ...] = ()  # page origins besides the server's own
    allow_hosts: tuple[str, ...] = ()  # Host names besides loopback's (the public name behind a proxy)
    debug: bool = False  # the admin routes without an admin token
    limits: ServeLimits = field(default_factory=ServeLimits)
    size: int = 256  # pixel mode: square frame size
    lookahead_ms: float = 160.0
    renderer: str = "auto"  # pixel mode: gl, cpu or auto
    audio: Path | None = None  # the "file" source's sound (default: the checkout's sample speech)
    batch_frames: int = 1  # client-render: frames per translator call at least
    context_ms: float = 1000.0  # client-render: past audio the translator sees
    web_root: Path | None = None  # client-render: the web player's folder (default: the checkout's web/)
    streaming: bool = True  # client-render: the bundle's streaming translator where it has one
    stream_delay_ms: float | None = None  # client-render: which of its streams (None: the main one; 80: the short one)
    drive_threads: int = 1  # client-render: threads that make the WebSocket sessions' frames (docs/live.md, "One pool
    # thread and the voice's MatMul graph")


def make_app(bundle: Path, options: ServeOptions | None = None) -> web.Application:
    """The server for `bundle`; ValueError naming a bad option."""
    options = options or ServeOptions()
    limits = options.limits
    limits.check()
    bundle = Path(bundle)
    if not bundle.is_file():
        raise ValueError(f"{bundle}: no such bundle file")
    metrics = ServeMetrics()
    policy = AccessPolicy(options.secret, bundle.name, allow_hosts=options.allow_hosts,
                          allow_origins=options.allow_origins, debug=options.debug, metrics=metrics)
    app = web.Application(middlewares=[one_line_errors, policy.middleware], client_max_size=limits.max_body_bytes)
    pixel = not options.client_render
    admission = Admission(limits.session_cap(pixel), limits.max_sessions_per_client)
    mode = "pixel" if pixel else "client-render"
    if pixel:
        from .pixel import PixelSession, add_pixel_routes

        sessions = Sessions(mode, PixelSession.THREAD_NAME, "render_threads", admission, metrics)
    else:
        from .client_render import add_client_render_routes
        from .drive_sessions import DriveSession

        sessions = Sessions(mode, DriveSession.THREAD_NAME, "driver_threads", admission, metrics)
    app[LIMITS], app[SESSIONS], app[METRICS] = limits, sessions, metrics
    audio = options.audio or SAMPLE_SPEECH
    files = VoiceFiles(audio)
    if pixel:
        add_pixel_routes(app, bundle, sessions, limits, metrics, files, size=options.size,
                         lookahead_ms=options.lookahead_ms, renderer=options.renderer)
    else:
        add_client_render_routes(app, bundle, sessions, limits, metrics, files, lookahead_ms=options.lookahead_ms,
                                 batch_frames=options.batch_frames, context_ms=options.context_ms,
                                 web_root=options.web_root, streaming=options.streaming,
                                 stream_delay_ms=options.stream_delay_ms, drive_threads=options.drive_threads)
    sessions.route(app)
    add_operations_routes(app, sessions, metrics)
    return app


def add_operations_routes(app: web.Application, sessions: Sessions, metrics: ServeMetrics) -> None:
    """/healthz (the process answers), /readyz (it takes sessions: not draining, not full) and /metrics."""

    async def healthz(request: web.Request) -> web.Response:
        return web.json_response({"ok": True})

    async def readyz(request: web.Request) -> web.Response:
        admission = sessions.admission
        if admission.draining:
            return web.json_response({"ready": False, "reason": "draining"}, status=503)
        if admission.open >= admission.total:
            return web.json_response({"ready": False, "reason": "full"}, status=503)
        return web.json_response({"ready": True, "sessions": admission.open, "capacity": admission.total})

    async def metrics_route(request: web.Request) -> web.Response:
        return web.Response(body=metrics.exposition(), headers={"Content-Type": CONTENT_TYPE})

    app.router.add_get("/healthz", healthz)
    app.router.add_get("/readyz", readyz)
    app.router.add_get("/metrics", metrics_route)


def listen_hosts(host: str, extra: Iterable[str]) -> tuple[str, ...]:
    """The Host names a server on `host` answers to: `extra`, and `host` itself unless it is a wildcard."""
    names = [name for name in extra]
    if host not in ("0.0.0.0", "::", ""):
        names.append(host)
    return tuple(names)


__all__ = ["SAMPLE_SPEECH", "ServeOptions", "add_operations_routes", "listen_hosts", "make_app"]
