"""Logging a server under attack can afford: a repeated traceback is logged once per interval, and the records
between keep one line each, so a client that makes the same error fail a thousand times writes one traceback, not
a thousand (docs/serve.md, "Errors and logs")."""

from __future__ import annotations

import logging
import threading
import time

log = logging.getLogger("gaussiantalker.serve")


class RepeatedTracebacks(logging.Filter):
    """Keeps the traceback of the first record of each (exception type, where raised), then of at most one each
    `interval_s`; the records between keep their line, without the traceback, saying it was logged before."""

    def __init__(self, interval_s: float = 60.0) -> None:
        super().__init__()
        self.interval_s = interval_s
        self._seen: dict[tuple, float] = {}  # key -> when its traceback was last logged
        self._lock = threading.Lock()

    def filter(self, record: logging.LogRecord) -> bool:
        if not record.exc_info or record.exc_info[1] is None:
            return True
        error = record.exc_info[1]
        frame = error.__traceback__
        while frame is not None and frame.tb_next is not None:
            frame = frame.tb_next
        key = (type(error), frame.tb_frame.f_code.co_filename if frame else "", frame.tb_lineno if frame else 0)
        now = time.monotonic()
        with self._lock:
            last = self._seen.get(key)
            if last is not None and now - last < self.interval_s:
                record.msg = f"{record.msg} ({type(error).__name__}: {error}; its traceback as logged before)"
                record.exc_info, record.exc_text = None, None
                return True
            self._seen[key] = now
            if len(self._seen) > 1000:  # bounded: forget the oldest kinds
                for old in sorted(self._seen, key=self._seen.get)[:500]:
                    del self._seen[old]
        return True


def install_filter(interval_s: float = 60.0) -> RepeatedTracebacks:
    """Put a RepeatedTracebacks filter on the server's logger and aiohttp's (where its handlers log)."""
    repeated = RepeatedTracebacks(interval_s)
    for name in ("gaussiantalker.serve", "aiohttp.server", "aiohttp.web", "aiohttp.access", "asyncio"):
        logging.getLogger(name).addFilter(repeated)
    return repeated


__all__ = ["RepeatedTracebacks", "install_filter", "log"]
