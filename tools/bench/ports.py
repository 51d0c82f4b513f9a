"""Free loopback ports for the servers the benches and tests start (gt-serve, its replicas, nginx)."""

from __future__ import annotations

import os
import random
import socket

# Below Linux's ephemeral range (32768-60999), so that no outgoing connection (nginx to a replica, a browser, a load
# client) takes a port between its choice and the server's bind, and never the same one twice in a process (a port
# the kernel hands out with bind(0) can come back at the next call).
PORT_RANGE = (20000, 32000)
_handed_out: set[int] = set()
_ports = random.Random(os.getpid())


def free_port() -> int:
    """A loopback port nothing listens on now and no earlier call in this process returned."""
    for _ in range(1000):
        port = _ports.randrange(*PORT_RANGE)
        if port in _handed_out:
            continue
        with socket.socket() as sock:
            try:
                sock.bind(("127.0.0.1", port))
            except OSError:
                continue
        _handed_out.add(port)
        return port
    raise RuntimeError(f"no free loopback port in {PORT_RANGE}")


__all__ = ["PORT_RANGE", "free_port"]
