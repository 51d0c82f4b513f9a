"""gt-serve replicas behind nginx, as docs/serve.md ("Replicas behind a load balancer") deploys them:
deploy/nginx.conf with its ports replaced, for the load bench (`gt-bench live-clients --replicas K`) and the
replica tests."""

from __future__ import annotations

import os
import re
import shutil
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
NGINX_CONF = ROOT / "deploy" / "nginx.conf"
_REPLICA_LINE = re.compile(r"^(\s*server 127\.0\.0\.1:)(8081)(\b[^\n]*\n)", re.M)


def nginx_binary() -> str | None:
    """nginx's path (Debian puts it in /usr/sbin, off a user's PATH), or None when it is not installed."""
    return shutil.which("nginx") or ("/usr/sbin/nginx" if os.access("/usr/sbin/nginx", os.X_OK) else None)


def nginx_config(listen: int, replicas: list[int], backend: int) -> str:
    """deploy/nginx.conf listening on `listen`, its upstream the `replicas` (one `server` line each, as its 8081
    line is written) and its token backend on `backend` (its 8090)."""
    if not replicas:
        raise ValueError("nginx needs at least one replica")
    text = NGINX_CONF.read_text()
    found = _REPLICA_LINE.search(text)
    if found is None or not re.search(r"^\s*server 127\.0\.0\.1:8082\b[^\n]*\n", text, re.M):
        raise ValueError(f"{NGINX_CONF} no longer lists its replicas as 127.0.0.1:8081 and :8082")
    lines = "".join(f"{found.group(1)}{port}{found.group(3)}" for port in replicas)
    text = re.sub(r"^\s*server 127\.0\.0\.1:8082\b[^\n]*\n", "", text, count=1, flags=re.M)
    text = _REPLICA_LINE.sub(lambda _: lines, text, count=1)
    for old, new in (("8080", listen), ("8090", backend)):
        text, count = re.subn(rf"127\.0\.0\.1:{old}\b", f"127.0.0.1:{new}", text)
        if not count:
            raise ValueError(f"{NGINX_CONF} no longer has 127.0.0.1:{old}")
    return text


__all__ = ["NGINX_CONF", "nginx_binary", "nginx_config"]
