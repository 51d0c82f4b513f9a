"""An app's backend for `gt-serve` (docs/serve.md, "The token flow"): it decides who may talk to the avatar and
hands each of them a short-lived token signed with the secret it shares with the servers.

    gt-serve secret -o secret.txt
    gt-serve out/speaker.gtb --client-render --secret-file secret.txt --port 8080 &
    python samples/token_backend.py --secret-file secret.txt --port 8081 --bundle speaker.gtb

GET /token answers a fresh token as text (the page's ?token_url=, which it asks again when its server goes away);
GET / sends the browser to the server's page with one. A real backend checks its own login first; this one asks
nobody, so keep it on loopback.
"""

from __future__ import annotations

from pathlib import Path
from urllib.parse import urlsplit

import typer
from aiohttp import web

from gaussiantalker.serve import mint_token, read_secret


def make_backend(secret: bytes, server_url: str, bundle: str | None, ttl_s: float) -> web.Application:
    """GET /token: a fresh token; GET /: the server's page, with a token and this /token as its token_url."""

    parts = urlsplit(server_url)
    server_origin = f"{parts.scheme}://{parts.netloc}"  # the page's origin: it may read /token across origins

    async def token(request: web.Request) -> web.Response:
        return web.Response(text=mint_token(secret, ttl_s, bundle=bundle),
                            headers={"Cache-Control": "no-store", "Access-Control-Allow-Origin": server_origin,
                                     "Vary": "Origin"})

    async def page(request: web.Request) -> web.Response:
        fresh = mint_token(secret, ttl_s, bundle=bundle)
        token_url = f"{request.scheme}://{request.host}/token"
        raise web.HTTPFound(f"{server_url}?token={fresh}&token_url={token_url}")

    app = web.Application()
    app.router.add_get("/token", token)
    app.router.add_get("/", page)
    return app


def main(secret_file: Path = typer.Option(..., "--secret-file", help="the secret gt-serve was started with"),
         port: int = typer.Option(8081, "--port", help="port on 127.0.0.1"),
         server: str = typer.Option("http://127.0.0.1:8080/", "--server", help="the gt-serve page's URL"),
         bundle: str = typer.Option(None, "--bundle", help="the bundle file name the tokens are for"),
         ttl_s: float = typer.Option(60.0, "--ttl-s", help="seconds each token is valid")) -> None:
    """Mint tokens for pages of a gt-serve server."""
    web.run_app(make_backend(read_secret(secret_file), server, bundle, ttl_s), host="127.0.0.1", port=port)


if __name__ == "__main__":
    typer.run(main)
