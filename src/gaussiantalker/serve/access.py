"""Who may use which route: the Host and Origin allow-lists, the token (query, Authorization header or the page's
cookie), the admin routes, and CORS for the origins allowed; one aiohttp middleware applies them all before any
handler runs (docs/serve.md, "Who may connect")."""

from __future__ import annotations

import ipaddress
import time
from collections.abc import Iterable
from dataclasses import dataclass
from urllib.parse import urlsplit

from aiohttp import web

from .keys import CLIENT
from .logs import log
from .metrics import ServeMetrics
from .tokens import Claims, TokenError, verify_token

PUBLIC_ROUTES = frozenset({"/healthz", "/readyz"})  # load-balancer probes: no token, no Host check
ADMIN_ROUTES = frozenset({"/stats", "/drives", "/health", "/metrics"})
COOKIE = "gt_serve_token"  # set when a page is loaded with ?token=: its modules, bundle and socket carry it
LOOPBACK_NAMES = frozenset({"localhost", "127.0.0.1", "::1"})


def is_loopback(host: str) -> bool:
    """Whether `host` (a name or an address) is this machine only."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def origin_of(url: str) -> str:
    """`scheme://host[:port]`, lower case, of a URL or an origin; ValueError for one that is not http(s)."""
    parts = urlsplit(url.strip())
    if parts.scheme not in ("http", "https") or not parts.hostname:
        raise ValueError(f"{url!r} is not an http(s) origin")
    port = f":{parts.port}" if parts.port else ""
    host = f"[{parts.hostname}]" if ":" in parts.hostname else parts.hostname
    return f"{parts.scheme}://{host}{port}".lower()


def _hostname(host_header: str) -> str:
    """The name in a Host header, without its port, lower case ('' for one that cannot be read)."""
    try:
        return (urlsplit(f"//{host_header}").hostname or "").lower()
    except ValueError:
        return ""


@dataclass(frozen=True)
class Client:
    """Who a request comes from: `key` counts its sessions (the token's subject, or its address where no token is
    asked), `admin` whether it may read the counters."""

    key: str
    admin: bool
    claims: Claims | None


class AccessPolicy:
    """The server's rules: `secret` None serves without tokens (loopback only, enforced by the command);
    `allow_hosts` the Host names it answers to besides loopback's; `allow_origins` page origins besides its own;
    `bundle` the bundle's file name, which a token's bundle claim must name; `debug` opens the admin routes."""

    def __init__(self, secret: bytes | None, bundle: str, *, allow_hosts: Iterable[str] = (),
                 allow_origins: Iterable[str] = (), debug: bool = False, metrics: ServeMetrics | None = None) -> None:
        self.secret, self.bundle, self.debug, self.metrics = secret, bundle, debug, metrics
        self.allow_hosts = set(LOOPBACK_NAMES) | {_hostname(h) or h.lower() for h in allow_hosts}
        self.allow_origins = {origin_of(o) for o in allow_origins}
        # The page's token is in its URL: no Referer carries it away; only the server's own and the allowed origins
        # may frame the pages (a page elsewhere could otherwise frame one and trick a click on its microphone).
        self.page_headers = {"Referrer-Policy": "no-referrer", "X-Content-Type-Options": "nosniff",
                             "Content-Security-Policy": "frame-ancestors " + " ".join(["'self'",
                                                                                       *sorted(self.allow_origins)])}

    # -- the checks ---------------------------------------------------------------------------------------------
    def _refuse(self, reason: str, status: type[web.HTTPException], text: str) -> web.HTTPException:
        if self.metrics is not None:
            self.metrics.refuse(reason)
        return status(text=text)

    def origin_allowed(self, request: web.Request) -> tuple[bool, str | None]:
        """(allowed, the Origin header). Same origin (the Origin's host and port are the Host's) or listed."""
        origin = request.headers.get("Origin")
        if origin is None:
            # A request without Origin is a navigation or a same-origin GET, or not from a browser; a browser marks
            # a cross-site one (an <img>, a <script>) with Sec-Fetch-Site.
            return request.headers.get("Sec-Fetch-Site", "same-origin") != "cross-site", None
        try:
            normal = origin_of(origin)
        except ValueError:
            return False, origin
        same = urlsplit(normal).netloc == request.host.lower()
        return same or normal in self.allow_origins, origin

    def client_of(self, request: web.Request) -> Client:
        """The request's Client after the token check; raises the HTTP error that refuses it."""
        if self.secret is None:
            return Client(key=f"address {request.remote}", admin=self.debug, claims=None)
        token = request.query.get("token") or _bearer(request.headers.get("Authorization", "")) \
            or request.cookies.get(COOKIE, "")
        try:
            claims = verify_token(token, self.secret)
        except TokenError as error:
            raise self._refuse("token", web.HTTPUnauthorized, str(error)) from None
        if claims.bundle is not None and claims.bundle != self.bundle:
            raise self._refuse("token", web.HTTPForbidden, "the token is for another bundle")
        origin = request.headers.get("Origin")
        if claims.origin is not None and origin is not None and origin_of(origin) != origin_of(claims.origin):
            raise self._refuse("token", web.HTTPForbidden, "the token is for another origin")
        return Client(key=f"subject {claims.subject}", admin=claims.admin or self.debug, claims=claims)

    # -- the middleware -----------------------------------------------------------------------------------------
    @web.middleware
    async def middleware(self, request: web.Request, handler) -> web.StreamResponse:
        if request.path in PUBLIC_ROUTES:
            return await handler(request)
        if _hostname(request.host) not in self.allow_hosts:
            raise self._refuse("host", web.HTTPForbidden, "this server does not answer to that Host")
        allowed, origin = self.origin_allowed(request)
        if not allowed:
            raise self._refuse("origin", web.HTTPForbidden, "requests from that origin are not allowed")
        if request.method == "OPTIONS" and origin is not None:  # a CORS preflight from an allowed origin
            return web.Response(status=204, headers=_cors(origin) | {
                "Access-Control-Allow-Methods": "GET, POST", "Access-Control-Max-Age": "600",
                "Access-Control-Allow-Headers": "Authorization, Content-Type"})
        client = self.client_of(request)
        if request.path in ADMIN_ROUTES and not client.admin:
            raise self._refuse("admin", web.HTTPForbidden, "this route needs an admin token (or gt-serve --debug)")
        request[CLIENT] = client
        response = await handler(request)
        if not response.prepared:
            response.headers.update(self.page_headers)
        if origin is not None and not response.prepared:
            response.headers.update(_cors(origin))
        if request.path == "/" and "token" in request.query and client.claims is not None \
                and not response.prepared:
            max_age = max(1, int(client.claims.expires - time.time()))
            response.set_cookie(COOKIE, request.query["token"], max_age=max_age, httponly=True, samesite="Strict",
                                secure=request.secure)
        return response


def _bearer(header: str) -> str:
    scheme, _, value = header.partition(" ")
    return value.strip() if scheme.lower() == "bearer" else ""


def _cors(origin: str) -> dict[str, str]:
    return {"Access-Control-Allow-Origin": origin, "Vary": "Origin"}


@web.middleware
async def one_line_errors(request: web.Request, handler) -> web.StreamResponse:
    """Every error answers one line with no exception text or path: HTTP errors keep their own (one-line) text,
    anything else is logged (RepeatedTracebacks keeps repeats out of the log) and answers 500."""
    try:
        return await handler(request)
    except web.HTTPException as error:
        if error.status >= 400 and error.text and "\n" in error.text.strip():
            error.text = error.text.strip().splitlines()[0]
        raise
    except Exception as error:  # the handler's own failure: the client hears only that it happened
        log.error("%s %s failed", request.method, request.path, exc_info=error)
        raise web.HTTPInternalServerError(text="internal error") from None


__all__ = ["ADMIN_ROUTES", "AccessPolicy", "COOKIE", "Client", "PUBLIC_ROUTES", "is_loopback", "one_line_errors",
           "origin_of"]
