"""`gt-serve BUNDLE [--client-render] [--host H] [--port P] [--secret-file F] [--allow-origin O]...
[--max-sessions N]`: live sessions for many clients (docs/serve.md). `gt-serve token --secret-file F` mints a
token, `gt-serve secret -o F` writes a new secret file."""

from __future__ import annotations

import json
import logging
import os
import sys
from pathlib import Path

import typer

SUBCOMMANDS = ("token", "secret")
serve_command = typer.Typer(add_completion=False)
token_command = typer.Typer(add_completion=False)
secret_command = typer.Typer(add_completion=False)


def _require_serve_extra() -> None:
    """Exit with one line when the `serve` extra is not installed."""
    missing = []
    for module in ("aiohttp", "jwt", "prometheus_client"):
        try:
            __import__(module)
        except ImportError:
            missing.append(module)
    if missing:
        sys.stderr.write(f"gt-serve: needs the 'serve' extra ({', '.join(missing)} not installed): "
                         "pip install \"gaussiantalker-sdk[serve]\"\n")
        raise SystemExit(2)


@serve_command.command()
def serve(
    bundle: Path = typer.Argument(..., help="a speaker bundle with a translator (.gtb)"),
    client_render: bool = typer.Option(False, "--client-render", help="stream drives, not pixels: the page "
                                       "renders the head with the web player"),
    host: str = typer.Option("127.0.0.1", "--host", help="address to listen on"),
    port: int = typer.Option(8080, "--port", min=0, max=65535, help="port (0: any free one)"),
    secret_file: Path = typer.Option(None, "--secret-file", help="the HS256 secret tokens are signed with; "
                                     "required on any address but loopback"),
    allow_origin: list[str] = typer.Option([], "--allow-origin", help="a page origin allowed besides the server's "
                                           "own (repeatable), e.g. https://app.example.com"),
    allow_host: list[str] = typer.Option([], "--allow-host", help="a Host name the server answers to besides "
                                         "loopback's and --host (repeatable): its public name behind a proxy"),
    max_sessions: int = typer.Option(None, "--max-sessions", min=1, help="sessions at once [default: 100 "
                                     "client-rendered, 2 a core in pixel mode]"),
    max_sessions_per_client: int = typer.Option(4, "--max-sessions-per-client", min=1, help="sessions at once "
                                                "per token subject (or address, without tokens)"),
    max_connections: int = typer.Option(512, "--max-connections", min=1, help="TCP connections at once"),
    drain_s: float = typer.Option(30.0, "--drain-s", min=0.1, help="on SIGTERM, how long open sessions may "
                                  "finish before they are closed"),
    debug: bool = typer.Option(False, "--debug", help="open /stats, /drives, /health and /metrics without an "
                               "admin token"),
    size: int = typer.Option(256, "--size", min=16, help="pixel mode: square frame size"),
    lookahead_ms: float = typer.Option(160.0, "--lookahead-ms", min=0.0, help="the live sessions' lookahead"),
    audio: Path = typer.Option(None, "--audio", help="the sound the pages' 'file' source plays [default: the "
                               "checkout's samples/demo_speech.wav]"),
    renderer: str = typer.Option("auto", "--renderer", help="pixel mode: gl, cpu or auto"),
    batch_frames: int = typer.Option(1, "--batch-frames", min=1, max=8, help="client-render: frames per "
                                     "translator call at least (docs/live.md)"),
    context_ms: float = typer.Option(1000.0, "--context-ms", min=0.0, help="client-render: past audio the "
                                     "translator sees"),
    stream: bool = typer.Option(True, "--stream/--no-stream", help="client-render: run the bundle's streaming "
                                "translator where it has one, every due session's frame in one call (docs/live.md, "
                                "\"Streaming translators\"); --no-stream: the windowed translator"),
    stream_delay_ms: float = typer.Option(None, "--stream-delay-ms", min=0.0, help="client-render: which of the "
                                          "translator's streams to run, by how far its rows lag the audio [default: "
                                          "its main one]; 80: a trained speaker's short stream, cheaper below 160 ms "
                                          "of lookahead and less accurate (docs/live.md)"),
    web_root: Path = typer.Option(None, "--web-root", help="client-render: the web player's folder (web/ with "
                                  "its npm install) [default: the checkout's]"),
    drive_threads: int = typer.Option(1, "--drive-threads", min=1, max=64, help="client-render: threads that make "
                                      "the WebSocket sessions' frames (Python under one interpreter lock: for more "
                                      "cores run a replica per core, docs/serve.md)"),
) -> None:
    """Serve live talking-head sessions: pixels over WebRTC, or drives for pages that render (--client-render).
    Also `gt-serve secret -o FILE` (a new secret) and `gt-serve token --secret-file FILE` (a token; docs/serve.md)."""
    _require_serve_extra()
    from gaussiantalker.sdk.errors import GaussianTalkerError
    from gaussiantalker.serve import ServeLimits, read_secret
    from gaussiantalker.serve.access import is_loopback
    from gaussiantalker.serve.app import ServeOptions, listen_hosts, make_app
    from gaussiantalker.serve.logs import install_filter
    from gaussiantalker.serve.server import run

    logging.basicConfig(format="%(asctime)s %(levelname)s %(name)s: %(message)s", level=logging.WARNING)
    logging.getLogger("gaussiantalker.serve").setLevel(logging.INFO)  # a line per session start and end
    install_filter()
    log = logging.getLogger("gaussiantalker.serve")
    if not bundle.is_file():
        raise typer.BadParameter(f"{bundle}: no such file", param_hint="BUNDLE")
    if audio is not None and not audio.is_file():
        raise typer.BadParameter(f"{audio}: no such file", param_hint="--audio")
    secret = None
    if secret_file is not None:
        try:
            secret = read_secret(secret_file)
        except ValueError as error:
            raise typer.BadParameter(str(error), param_hint="--secret-file") from None
    elif not is_loopback(host):
        raise typer.BadParameter(f"{host} is not a loopback address: a server others can reach needs tokens "
                                 "(--secret-file; make one with `gt-serve secret -o FILE`)", param_hint="--host")
    else:
        log.warning("no --secret-file: anyone on this machine may connect without a token (loopback only)")
    limits = ServeLimits(max_sessions=max_sessions, max_sessions_per_client=max_sessions_per_client,
                         max_connections=max_connections, drain_s=drain_s)
    options = ServeOptions(client_render=client_render, secret=secret, allow_origins=tuple(allow_origin),
                           allow_hosts=listen_hosts(host, allow_host), debug=debug, limits=limits, size=size,
                           lookahead_ms=lookahead_ms, renderer=renderer, audio=audio, batch_frames=batch_frames,
                           context_ms=context_ms, web_root=web_root, streaming=stream,
                           stream_delay_ms=stream_delay_ms, drive_threads=drive_threads)
    try:
        app = make_app(bundle, options)
    except (ValueError, GaussianTalkerError) as error:
        sys.stderr.write(f"gt-serve: {error}\n")
        raise SystemExit(2) from None

    def listening(bound: int) -> None:
        url_host = f"[{host}]" if ":" in host else host
        print(json.dumps({"url": f"http://{url_host}:{bound}/", "bundle": str(bundle),
                          "mode": "client-render" if client_render else "pixel", "tokens": secret is not None}),
              flush=True)

    run(app, host, port, on_listening=listening)


@token_command.command()
def token(
    secret_file: Path = typer.Option(..., "--secret-file", help="the secret the servers share"),
    ttl_s: float = typer.Option(300.0, "--ttl-s", min=1.0, help="seconds the token is valid (a session admitted "
                                "before it expires runs on)"),
    subject: str = typer.Option(None, "--subject", help="the client it names: sessions are counted per subject "
                                "[default: a random one]"),
    bundle: str = typer.Option(None, "--bundle", help="the bundle file name a server must serve to accept it"),
    origin: str = typer.Option(None, "--origin", help="the only page origin it is good for"),
    admin: bool = typer.Option(False, "--admin", help="may read /stats, /drives, /health and /metrics"),
) -> None:
    """Print a signed token (what an app's backend mints with gaussiantalker.serve.mint_token)."""
    _require_serve_extra()
    from gaussiantalker.serve import mint_token, read_secret

    try:
        secret = read_secret(secret_file)
        print(mint_token(secret, ttl_s, subject=subject, bundle=bundle, origin=origin, admin=admin))
    except ValueError as error:
        raise typer.BadParameter(str(error)) from None


@secret_command.command()
def secret(output: Path = typer.Option(..., "-o", "--output", help="the secret file to write (mode 600)")) -> None:
    """Write a new random secret file for --secret-file (refuses to overwrite one)."""
    from gaussiantalker.serve.tokens import new_secret

    try:
        descriptor = os.open(output, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except FileExistsError:
        raise typer.BadParameter(f"{output} exists: remove it first to replace the secret") from None
    with os.fdopen(descriptor, "w") as file:
        file.write(new_secret() + "\n")
    print(f"wrote {output}")


def main() -> None:
    """`gt-serve`: the server, or its `token` and `secret` subcommands."""
    if len(sys.argv) > 1 and sys.argv[1] in SUBCOMMANDS:
        name = sys.argv.pop(1)
        command = {"token": token_command, "secret": secret_command}[name]
        command(prog_name=f"gt-serve {name}")
    else:
        serve_command(prog_name="gt-serve")


if __name__ == "__main__":
    main()
