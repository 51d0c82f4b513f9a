"""The typed keys under which a gt-serve app keeps its parts (aiohttp's AppKey and RequestKey)."""

from __future__ import annotations

from aiohttp import web

from .limits import ServeLimits
from .metrics import ServeMetrics

LIMITS = web.AppKey("gt_limits", ServeLimits)
METRICS = web.AppKey("gt_metrics", ServeMetrics)
SESSIONS = web.AppKey("gt_sessions", object)  # a sessions.Sessions
DRIVER = web.AppKey("gt_driver", object)  # client-render: the shared runtime Driver
# The request's access.Client (RequestKey where this aiohttp has it, a plain key before).
CLIENT = web.RequestKey("gt_client", object) if hasattr(web, "RequestKey") else "gt_client"

__all__ = ["CLIENT", "DRIVER", "LIMITS", "METRICS", "SESSIONS"]
