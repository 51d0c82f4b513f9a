"""Who may connect: HS256 JSON Web Tokens (PyJWT), minted by the app's own backend with the secret it shares with
the servers, and checked by every route but /healthz and /readyz (docs/serve.md, "Tokens")."""

from __future__ import annotations

import secrets
import time
import uuid
from dataclasses import dataclass
from pathlib import Path

import jwt

AUDIENCE = "gaussiantalker-serve"  # a token minted for something else with the same secret is refused
ALGORITHM = "HS256"
MIN_SECRET_BYTES = 32  # HS256's key should be at least its hash's 256 bits
MAX_SECRET_BYTES = 4096
LEEWAY_S = 5.0  # clock skew allowed between the app's backend and the servers
MAX_TTL_S = 7 * 24 * 3600.0
MAX_TOKEN_CHARS = 4096  # longer is not a token this module made: refused before it is parsed


class TokenError(ValueError):
    """A token that is missing, malformed, expired, signed with another secret, or not for this server."""


@dataclass(frozen=True)
class Claims:
    """What a verified token grants: who (subject, the per-client limit's key), until when, for which bundle and
    page origin (None: any), and whether it may read /stats, /drives, /health and /metrics (admin)."""

    subject: str
    expires: float
    bundle: str | None = None
    origin: str | None = None
    admin: bool = False


def read_secret(path: Path) -> bytes:
    """The shared secret in `path` (its bytes, a trailing newline dropped); ValueError naming what is wrong."""
    try:
        size = path.stat().st_size
    except OSError as error:
        raise ValueError(f"--secret-file {path}: cannot read it ({error.strerror})") from None
    if size > MAX_SECRET_BYTES:
        raise ValueError(f"--secret-file {path}: {size} bytes, more than a secret ({MAX_SECRET_BYTES} at most)")
    secret = path.read_bytes().rstrip(b"\r\n")
    if len(secret) < MIN_SECRET_BYTES:
        raise ValueError(f"--secret-file {path}: {len(secret)} bytes, at least {MIN_SECRET_BYTES} are needed "
                         "(make one with `gt-serve secret -o FILE`)")
    return secret


def new_secret() -> str:
    """A fresh random secret (64 hex digits, 256 bits) for a secret file."""
    return secrets.token_hex(32)


def mint_token(secret: bytes | str, ttl_s: float = 300.0, *, subject: str | None = None, bundle: str | None = None,
               origin: str | None = None, admin: bool = False, now: float | None = None) -> str:
    """A signed token valid for `ttl_s` seconds: `subject` names the client (the per-client session limit counts
    by it; a random one by default), `bundle` the bundle file name a server must serve to accept it, `origin` the
    only page origin it is good for, `admin` whether it reads the server's counters."""
    if isinstance(secret, str):
        secret = secret.encode()
    if len(secret) < MIN_SECRET_BYTES:
        raise ValueError(f"the secret is {len(secret)} bytes: at least {MIN_SECRET_BYTES} are needed")
    if not (0 < ttl_s <= MAX_TTL_S):
        raise ValueError(f"ttl_s must be in (0, {MAX_TTL_S:g}] seconds, got {ttl_s!r}")
    issued = int(time.time() if now is None else now)
    claims: dict[str, object] = {"aud": AUDIENCE, "iat": issued, "exp": issued + max(1, round(ttl_s)),
                                 "sub": subject or uuid.uuid4().hex}
    if bundle is not None:
        claims["bundle"] = bundle
    if origin is not None:
        claims["origin"] = origin
    if admin:
        claims["admin"] = True
    return jwt.encode(claims, secret, algorithm=ALGORITHM)


def verify_token(token: str, secret: bytes) -> Claims:
    """The claims of a token this secret signed, unexpired; TokenError with one line otherwise (never the
    library's exception text, which can quote the token)."""
    if not token:
        raise TokenError("no token (give it as ?token=, Authorization: Bearer, or load the page with ?token=)")
    if len(token) > MAX_TOKEN_CHARS:
        raise TokenError("the token is too long")
    try:
        claims = jwt.decode(token, secret, algorithms=[ALGORITHM], audience=AUDIENCE, leeway=LEEWAY_S,
                            options={"require": ["exp", "iat", "aud", "sub"]})
    except jwt.ExpiredSignatureError:
        raise TokenError("the token has expired") from None
    except jwt.InvalidSignatureError:
        raise TokenError("the token is not signed with this server's secret") from None
    except jwt.InvalidAudienceError:
        raise TokenError("the token is not for gt-serve") from None
    except jwt.InvalidTokenError:
        raise TokenError("the token is malformed") from None
    values = (claims.get("sub"), claims.get("bundle"), claims.get("origin"))
    if not all(value is None or isinstance(value, str) for value in values) or not claims["sub"]:
        raise TokenError("the token's claims are malformed")
    return Claims(subject=claims["sub"][:200], expires=float(claims["exp"]), bundle=claims.get("bundle"),
                  origin=claims.get("origin"), admin=claims.get("admin") is True)


__all__ = ["AUDIENCE", "Claims", "MIN_SECRET_BYTES", "TokenError", "mint_token", "new_secret", "read_secret",
           "verify_token"]
