"""The browser player (web/, docs/web.md) in headless Chromium, driven from Python: what `gt-web render` and the
fidelity tests use.

`WebPlayerPage` serves web/ and the given files from a tiny http.server on 127.0.0.1 (a free port, nothing else
is reachable: tools/browser/chromium.py's flags), opens web/harness/index.html in one headless Chromium and calls the
page's `window.gtWeb` (web/harness/harness.js): load a bundle, make a drive from audio or a motion, render frames.
"""

from __future__ import annotations

import base64
import http.server
import json
import os
import threading
import time
import urllib.parse
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from .chromium import Chromium, chromium_path
from .web_assets import stale_message, web_root

ORT_MODULE = "node_modules/onnxruntime-web/dist/ort.wasm.bundle.min.mjs"
# The npm modules the pages' import maps name (web/harness/index.html), by package.
NPM_MODULES = {"onnxruntime-web": ORT_MODULE, "fflate": "node_modules/fflate/esm/browser.js"}
PAGE = "harness/index.html"
# Headless Chromium offers WebGPU (SwiftShader's software adapter) only with this flag.
WEBGPU_FLAGS = ("--enable-unsafe-webgpu",)
# Content types the page needs exactly: module scripts must be served as JavaScript, wasm as application/wasm.
CONTENT_TYPES = {".js": "text/javascript", ".mjs": "text/javascript", ".wasm": "application/wasm",
                 ".html": "text/html", ".json": "application/json", ".map": "application/json"}


class WebPlayerMissing(RuntimeError):
    """Something the browser player needs is not there; the message says how to install it."""


def check_web_player(root: Path | None = None) -> str | None:
    """None when web/ holds the player with its npm install and an up-to-date generated.js, else what is wrong."""
    root = root or web_root()
    if not (root / "src" / "player.js").is_file():
        return f"the browser player's sources are not at {root} (gt-web runs from a source checkout)"
    for package, module in NPM_MODULES.items():
        if not (root / module).is_file():
            return (f"{package} is not installed in {root / 'node_modules'}: run `npm ci` in {root} "
                    "(or `python -m tools.browser.web_cli install`)")
    return stale_message(root)


class _Handler(http.server.SimpleHTTPRequestHandler):
    """Serves /web/... from the web folder and /files/<name> from the registered files, nothing else."""

    web: Path = Path("/nonexistent")
    files: dict[str, Path] = {}
    extensions_map = {**http.server.SimpleHTTPRequestHandler.extensions_map, **CONTENT_TYPES}

    def translate_path(self, path: str) -> str:
        missing = str(Path("/nonexistent") / "missing")
        parts = urllib.parse.unquote(urllib.parse.urlsplit(path).path).lstrip("/").split("/", 1)
        if len(parts) < 2 or ".." in parts[1].split("/"):
            return missing
        if parts[0] == "web":
            return str(self.web / parts[1])
        if parts[0] == "files" and parts[1] in self.files:
            return str(self.files[parts[1]])
        return missing

    def end_headers(self) -> None:
        self.send_header("Cache-Control", "no-store")
        super().end_headers()

    def log_message(self, *args) -> None:  # quiet: the caller reports its own progress
        pass


class HarnessServer:
    """A threaded http.server on 127.0.0.1 (a free port) for one page: web/ and `files` ({url name: path})."""

    def __init__(self, web: Path, files: Mapping[str, Path]) -> None:
        handler = type("Handler", (_Handler,), {"web": web, "files": dict(files)})
        self.httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}"
        self.thread = threading.Thread(target=self.httpd.serve_forever, daemon=True)
        self.thread.start()

    def add(self, name: str, path: str | os.PathLike) -> str:
        """Serve `path` as /files/<name>; returns its URL."""
        self.httpd.RequestHandlerClass.files[name] = Path(path)
        return f"{self.url}/files/{urllib.parse.quote(name)}"

    def close(self) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()


class WebPlayerPage:
    """One headless Chromium with the player's harness page open; `load`, `drive`, `render` call the player."""

    def __init__(self, web: Path | None = None, chromium: str | os.PathLike | None = None,
                 window: tuple[int, int] = (256, 256), extra_flags: tuple[str, ...] = ()) -> None:
        """`extra_flags`: more Chromium flags (WEBGPU_FLAGS offers the page a WebGPU adapter)."""
        self.web = (web or web_root()).resolve()
        chromium_path(chromium)
        problem = check_web_player(self.web)
        if problem is not None:
            raise WebPlayerMissing(problem)
        self.server = HarnessServer(self.web, {})
        self.browser = None
        self._count = 0
        try:
            self.browser = Chromium(chromium, window=window, extra_flags=extra_flags)
            self.browser.navigate(f"{self.server.url}/web/{PAGE}")
            self.browser.evaluate("new Promise((resolve, reject) => { const t0 = performance.now(); "
                                  "(function poll() { if (window.gtWebReady) resolve(true); "
                                  "else if (performance.now() - t0 > 60000) reject(new Error('the harness page did "
                                  "not start')); else setTimeout(poll, 10); })(); })")
        except BaseException:
            self.close()
            raise

    def serve(self, path: str | os.PathLike) -> str:
        """URL of a local file served to the page (its name kept, so errors name it)."""
        self._count += 1
        return self.server.add(f"{self._count}/{Path(path).name}", path)

    def call(self, expression: str, timeout: float = 600.0):
        return self.browser.evaluate(expression, timeout=timeout)

    def check(self, bundle: str | os.PathLike) -> str | None:
        """None when the player accepts the bundle file, else its error ("BundleError: <name>: ...")."""
        url = self.serve(bundle)
        return self.call(f"window.gtWeb.check({json.dumps(url)}, {json.dumps(Path(bundle).name)})")

    def load(self, bundle: str | os.PathLike, size: tuple[int, int] | None = None, camera: dict | None = None,
             background=None, settings: dict | None = None, composite: bool | None = None) -> dict:
        """Load a bundle into the player (the output `size` resizes the camera; `settings` overrides the bundle's
        runtime defaults: renderTarget, renderScale, sortKeyBits, sortInterval; `composite`: the player's option,
        None its default); returns what the page reports (`composited`: whether audio's frames are composited)."""
        request = {"url": self.serve(bundle), "name": Path(bundle).name, "camera": camera, "settings": settings,
                   "background": None if background is None else [float(c) for c in background],
                   "composite": composite}
        if size is not None:
            request.update(width=int(size[0]), height=int(size[1]))
        start = time.perf_counter()
        info = self.call(f"window.gtWeb.load({json.dumps(request)})")
        info["load_seconds"] = time.perf_counter() - start
        return info

    def decode(self, bundle: str | os.PathLike, buffer: str) -> np.ndarray:
        """Buffer `buffer` of a bundle file as the player decodes it (float16: its raw half bits as float16)."""
        url = self.serve(bundle)
        reply = self.call(f"window.gtWeb.decode({json.dumps(url)}, {json.dumps(Path(bundle).name)}, "
                          f"{json.dumps(buffer)})")
        return np.frombuffer(base64.b64decode(reply["data"]), reply["dtype"]).reshape(reply["shape"])

    def drive_rows(self) -> np.ndarray:
        """The page's drive rows, float32 [frames, width] (FLAME: expression then jaw; ARKit: the 52 weights)."""
        reply = self.call("window.gtWeb.driveRows()")
        return np.frombuffer(base64.b64decode(reply["data"]), np.float32).reshape(reply["frames"], reply["width"])

    def set_camera(self, camera: dict) -> None:
        self.call(f"window.gtWeb.setCamera({json.dumps(camera)})")

    def drive(self, audio: str | os.PathLike | None = None, motion: str | os.PathLike | None = None,
              weights: np.ndarray | None = None, fps: float | None = None) -> dict:
        """Make the page's drive from an audio file, a motion file, ARKit `weights` [T, 52] at `fps`, or (none of
        them) the bundle's own motion."""
        request = {"audio": None if audio is None else self.serve(audio),
                   "motion": None if motion is None else self.serve(motion),
                   "weights": None if weights is None else {"rows": np.asarray(weights, np.float64).tolist(),
                                                            "fps": fps}}
        return self.call(f"window.gtWeb.drive({json.dumps(request)})")

    def stream_drive(self, audio: str | os.PathLike, chunk: int) -> dict:
        """Make the page's drive by pushing an audio file through its streaming translator, `chunk` samples at a
        time (at the speaker's rate), then ending the stream: {frames, ready (frames after each push), delay}."""
        request = {"audio": self.serve(audio), "chunk": int(chunk)}
        return self.call(f"window.gtWeb.streamDrive({json.dumps(request)})")

    def render(self, index: int, output: str = "uint8") -> tuple[np.ndarray, dict]:
        """Frame `index` of the drive: uint8 [H, W, 3] (output "float": float32), and its per-step timings (s)."""
        reply = self.call(f"window.gtWeb.render({int(index)}, {json.dumps(output)})")
        dtype = np.uint8 if output == "uint8" else np.float32
        channels = 4 if output == "rgba_float" else 3
        frame = np.frombuffer(base64.b64decode(reply["data"]), dtype).reshape(reply["height"], reply["width"], channels)
        return frame, {**reply["timings"], "splats": reply["splats"]}

    def close(self) -> None:
        if self.browser is not None:
            self.browser.close()
            self.browser = None
        if getattr(self, "server", None) is not None:
            self.server.close()
            self.server = None

    def __enter__(self) -> WebPlayerPage:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


__all__ = ["HarnessServer", "WebPlayerMissing", "WebPlayerPage", "check_web_player"]
