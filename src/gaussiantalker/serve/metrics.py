"""The server's Prometheus metrics (prometheus-client), in a registry of its own per app, served at /metrics:
sessions, frames and late frames, the time to make a frame's drive, and refusals by reason (docs/serve.md,
"Operations")."""

from __future__ import annotations

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, generate_latest

CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"


class ServeMetrics:
    """One server's counters; `exposition()` is the /metrics body."""

    def __init__(self) -> None:
        self.registry = CollectorRegistry(auto_describe=True)
        registry = self.registry
        self.sessions = Gauge("gt_serve_sessions", "Live sessions open now", ["mode"], registry=registry)
        self.sessions_started = Counter("gt_serve_sessions_started", "Live sessions started", ["mode"],
                                        registry=registry)
        self.frames = Counter("gt_serve_frames", "Frames made for clients", ["mode"], registry=registry)
        self.late_frames = Counter("gt_serve_late_frames", "Frames whose lookahead was late at their due time",
                                   ["mode"], registry=registry)
        self.frame_seconds = Histogram(
            "gt_serve_frame_seconds", "Time to make one frame's drive (client-render) or image (pixel)", ["mode"],
            buckets=(0.001, 0.002, 0.005, 0.01, 0.02, 0.04, 0.08, 0.16, 0.32, 0.64, 1.28), registry=registry)
        self.translator_batch = Histogram(
            "gt_serve_translator_batch_sessions", "Sessions whose frames one streaming translator call made (the "
            "pool runs every due session's call as one)", buckets=(1, 2, 4, 8, 16, 32, 64, 128, 256),
            registry=registry)
        self.translator_rows = Counter(
            "gt_serve_translator_rows", "Rows (voice frames) the pool's streaming translator calls made: committed "
            "(final) or provisional (lookahead not yet in: made again once it is)", ["kind"], registry=registry)
        self.pool_cpu = Counter(
            "gt_serve_pool_cpu_seconds", "CPU seconds the client-render pool threads spent, by part: translator (the "
            "streaming translator calls they ran) or frames (the rest: the voices' feeds, planning, making and handing "
            "out frames)", ["part"], registry=registry)
        self.refusals = Counter("gt_serve_refusals", "Requests or sessions refused, by reason", ["reason"],
                                registry=registry)
        self.connections = Gauge("gt_serve_connections", "TCP connections open now", registry=registry)
        self.draining = Gauge("gt_serve_draining", "1 while the server drains (SIGTERM)", registry=registry)

    def refuse(self, reason: str) -> None:
        self.refusals.labels(reason=reason).inc()

    def exposition(self) -> bytes:
        return generate_latest(self.registry)


__all__ = ["CONTENT_TYPE", "ServeMetrics"]
