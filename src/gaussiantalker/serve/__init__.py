"""`gaussiantalker.serve`: live sessions for many clients over the network (docs/serve.md). `gt-serve BUNDLE`
runs it; an app's backend mints the tokens its pages connect with (`mint_token`). Needs the `serve` extra
(aiohttp, aiortc, PyJWT, prometheus-client), loaded only when a name below is asked for, so that the wire format
(`gaussiantalker.serve.wire`) imports without it; imports nothing of the exporter."""

from __future__ import annotations

import importlib

# Each public name and the module that defines it.
_HOMES = {"ServeLimits": "limits", "Claims": "tokens", "TokenError": "tokens", "mint_token": "tokens",
          "new_secret": "tokens", "read_secret": "tokens", "verify_token": "tokens", "make_app": "app",
          "ServeOptions": "app", "serve_app": "server"}

__all__ = sorted(_HOMES)


def __getattr__(name: str):
    """The public names, imported from their modules on first use."""
    if name in _HOMES:
        return getattr(importlib.import_module(f".{_HOMES[name]}", __name__), name)
    raise AttributeError(f"module 'gaussiantalker.serve' has no attribute {name!r}")
