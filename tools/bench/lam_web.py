"""Ground-truth frames of a LAM avatar from the original web renderer, in headless Chromium (docs/lam-web.md).

`render_web_frames(avatar_zip, cameras, weights_frames)` serves the harness page (lam_web/), the npm renderer and
the zip on 127.0.0.1, drives the renderer one frame at a time with the skeleton frozen at its rest pose, and
returns the frames as HxWx3 uint8 arrays. `install()` puts what it needs in place: the npm package in a cache
folder and Debian's chromium.
"""

from __future__ import annotations

import base64
import http.server
import json
import os
import shutil
import subprocess
import threading
import time
import urllib.parse
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

import numpy as np

from gaussiantalker.sdk.camera import Camera
from gaussiantalker.sdk.rig import ARKIT_BLENDSHAPES
from tools.browser.chromium import INSTALL_CHROMIUM, Chromium, chromium_path

from .lam_web_camera import lam_default_camera, to_three

PACKAGE = "gaussian-splat-renderer-for-lam"
VERSION = "0.0.8"
MODULE = "gaussian-splat-renderer-for-lam.module.js"
PAGE_DIR = Path(__file__).with_name("lam_web")
CACHE_ENV = "GT_LAM_WEB_CACHE"
# The 52 ARKit blendshape names (a weight vector without names is read in this order: LAM's and the SDK's).
ARKIT_NAMES = ARKIT_BLENDSHAPES

Weights = Mapping[str, float] | Sequence[float]


class LamWebMissing(RuntimeError):
    """Something the harness needs is not installed; the message gives the command that installs it."""


def default_cache_dir() -> Path:
    """Where the npm renderer is installed: $GT_LAM_WEB_CACHE or ~/.cache/gaussiantalker/lam-web."""
    return Path(os.environ.get(CACHE_ENV) or Path.home() / ".cache" / "gaussiantalker" / "lam-web")


def install_command(cache_dir: Path | None = None) -> str:
    """The shell command that installs the npm renderer into the cache folder."""
    cache = cache_dir or default_cache_dir()
    return f"npm install --prefix {cache} --save-exact --no-audit --no-fund {PACKAGE}@{VERSION}"


def renderer_dir(cache_dir: Path | None = None) -> Path:
    """The installed renderer's build folder, or LamWebMissing with the commands that install it."""
    build = (cache_dir or default_cache_dir()) / "node_modules" / PACKAGE / "build"
    if not (build / MODULE).is_file():
        raise LamWebMissing(f"the npm package {PACKAGE}@{VERSION} is not installed in {build.parents[2]}: run "
                            f"`gt-bench lam-web --install` or `{install_command(cache_dir)}`")
    return build


def install(cache_dir: Path | None = None, source: str | None = None, chromium: bool = True) -> Path:
    """Install the npm renderer (from the registry, or `source`: a packed .tgz) and Debian's chromium if missing."""
    cache = cache_dir or default_cache_dir()
    cache.mkdir(parents=True, exist_ok=True)
    npm = shutil.which("npm")
    if npm is None:
        raise LamWebMissing("npm is not installed: `apt-get install -y npm`")
    spec = source or f"{PACKAGE}@{VERSION}"
    subprocess.run([npm, "install", "--prefix", str(cache), "--save-exact", "--no-audit", "--no-fund", spec],
                   check=True)
    if chromium:
        try:
            chromium_path()
        except RuntimeError:
            subprocess.run(["apt-get", "install", "-y", "chromium"], check=True)
    return renderer_dir(cache)


def check_installed(cache_dir: Path | None = None) -> str | None:
    """None when chromium and the npm renderer are installed, else the reason (with the install command)."""
    try:
        chromium_path()
        renderer_dir(cache_dir)
    except RuntimeError as exc:
        return str(exc)
    return None


class _Handler(http.server.SimpleHTTPRequestHandler):
    """Serves /page/ (the harness), /renderer/ (the npm build) and /avatar/<name>.zip, nothing else."""

    routes: dict[str, Path] = {}

    def translate_path(self, path: str) -> str:
        parts = urllib.parse.unquote(urllib.parse.urlsplit(path).path).lstrip("/").split("/", 1)
        root = self.routes.get(parts[0])
        if root is None or len(parts) < 2 or ".." in parts[1].split("/"):
            return str(Path("/nonexistent") / "missing")
        if root.is_file():
            return str(root) if parts[1] == root.name else str(Path("/nonexistent") / "missing")
        return str(root / parts[1])

    def end_headers(self) -> None:
        self.send_header("Cache-Control", "no-store")
        super().end_headers()

    def log_message(self, *args) -> None:  # quiet: the driver prints its own progress
        pass


class _Server:
    """A threaded http.server on 127.0.0.1 with a free port, for one harness session."""

    def __init__(self, routes: dict[str, Path]) -> None:
        handler = type("Handler", (_Handler,), {"routes": routes})
        self.httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}"
        self.thread = threading.Thread(target=self.httpd.serve_forever, daemon=True)
        self.thread.start()

    def close(self) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()


def weights_dict(weights: Weights | None) -> dict[str, float]:
    """Named weights from a mapping, or from a sequence of 52 in ARKIT_NAMES order; {} for None (neutral)."""
    if weights is None:
        return {}
    if isinstance(weights, Mapping):
        return {str(name): float(value) for name, value in weights.items()}
    values = [float(v) for v in weights]
    if len(values) != len(ARKIT_NAMES):
        raise ValueError(f"a weight vector needs {len(ARKIT_NAMES)} values in ARKit order, got {len(values)}")
    return dict(zip(ARKIT_NAMES, values, strict=True))


def page_camera(camera: Camera | None, size: tuple[int, int]) -> dict | None:
    """The camera as the page takes it (None: the renderer's own); ValueError on a size mismatch or no conversion."""
    if camera is None:
        return None
    if (camera.width, camera.height) != tuple(size):
        raise ValueError(f"camera is {camera.width}x{camera.height} but frames are {size[0]}x{size[1]}: "
                         "pass camera.resized(...)")
    return to_three(camera).to_page()


class LamWebRenderer:
    """One headless Chromium with the original renderer and one avatar loaded; `render` draws one frame."""

    def __init__(self, avatar_zip: str | os.PathLike, size: tuple[int, int] = (512, 512),
                 background: Sequence[float] = (1.0, 1.0, 1.0), cache_dir: Path | None = None,
                 chromium: str | os.PathLike | None = None) -> None:
        zip_path = Path(avatar_zip).resolve()
        if not zip_path.is_file():
            raise FileNotFoundError(f"avatar zip not found: {zip_path}")
        build = renderer_dir(cache_dir)
        chromium_path(chromium)
        self.size = (int(size[0]), int(size[1]))
        self.background = tuple(float(c) for c in background)
        self.server = _Server({"page": PAGE_DIR, "renderer": build, "avatar": zip_path})
        try:
            self.browser = Chromium(chromium, window=(max(self.size[0], 64), max(self.size[1], 64)))
        except BaseException:
            self.server.close()
            raise
        try:
            start = time.perf_counter()
            self.browser.navigate(f"{self.server.url}/page/index.html")
            self.browser.evaluate("new Promise((resolve, reject) => { const t0 = performance.now(); "
                                  "(function poll() { if (window.gtLamWeb) resolve(true); "
                                  "else if (performance.now() - t0 > 60000) reject(new Error('harness page did "
                                  "not start')); else setTimeout(poll, 10); })(); })")
            url = f"{self.server.url}/avatar/{urllib.parse.quote(zip_path.name)}"
            self.info = self.browser.evaluate(
                f"window.gtLamWeb.load({{url: {url!r}, width: {self.size[0]}, height: {self.size[1]}, "
                f"background: {list(self.background)}}})")
            self.load_seconds = time.perf_counter() - start
        except BaseException:
            self.close()
            raise

    def render(self, camera: Camera | None = None, weights: Weights | None = None,
               background: Sequence[float] | None = None) -> np.ndarray:
        """One frame (HxWx3 uint8): `camera` (None: the renderer's own), raw ARKit `weights`, `background` RGB."""
        request = {"weights": weights_dict(weights), "camera": page_camera(camera, self.size),
                   "background": list(background if background is not None else self.background),
                   "width": self.size[0], "height": self.size[1]}
        reply = self.browser.evaluate(f"window.gtLamWeb.render({json.dumps(request)})")
        self.last = {k: v for k, v in reply.items() if k != "rgba"}
        if reply["restPoseError"] > 1e-6:
            raise RuntimeError(f"the skeleton left its rest pose (error {reply['restPoseError']:.3g})")
        rgba = np.frombuffer(base64.b64decode(reply["rgba"]), np.uint8).reshape(reply["height"], reply["width"], 4)
        self.last["alpha_min"] = int(rgba[..., 3].min())  # 255: the canvas shows RGB as read (docs/lam-web.md)
        return np.ascontiguousarray(rgba[::-1, :, :3])

    def close(self) -> None:
        """End the browser and the server."""
        if getattr(self, "browser", None) is not None:
            self.browser.close()
            self.browser = None
        if getattr(self, "server", None) is not None:
            self.server.close()
            self.server = None

    def __enter__(self) -> LamWebRenderer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def render_web_frames(avatar_zip: str | os.PathLike, cameras_or_camera: Camera | Sequence[Camera | None] | None,
                      weights_frames: Sequence[Weights | None], background: Sequence[float] = (1.0, 1.0, 1.0),
                      size: tuple[int, int] | None = None, cache_dir: Path | None = None,
                      progress: Callable[[int, float], None] | None = None) -> list[np.ndarray]:
    """Frames of `avatar_zip` drawn by the original web renderer: one per entry of `weights_frames`.

    `cameras_or_camera`: one Camera for every frame, a list with one per frame, or None for the renderer's own
    camera; `size` (W, H) defaults to the camera's (512x512 with the renderer's camera). `progress(i, seconds)`
    is called after each frame.
    """
    frames = list(weights_frames)
    if cameras_or_camera is None or isinstance(cameras_or_camera, Camera):
        cameras = [cameras_or_camera] * len(frames)
    else:
        cameras = list(cameras_or_camera)
        if len(cameras) != len(frames):
            raise ValueError(f"{len(cameras)} cameras for {len(frames)} weight frames")
    if size is None:
        first = next((c for c in cameras if c is not None), None)
        size = (first.width, first.height) if first is not None else (512, 512)
    for camera in cameras:
        page_camera(camera, size)  # refuse before starting a browser
    out = []
    with LamWebRenderer(avatar_zip, size, background, cache_dir) as renderer:
        for index, (camera, weights) in enumerate(zip(cameras, frames, strict=True)):
            start = time.perf_counter()
            out.append(renderer.render(camera, weights))
            if progress is not None:
                progress(index, time.perf_counter() - start)
    return out


__all__ = ["ARKIT_NAMES", "INSTALL_CHROMIUM", "LamWebMissing", "LamWebRenderer", "check_installed",
           "default_cache_dir", "install", "install_command", "lam_default_camera", "render_web_frames",
           "renderer_dir", "weights_dict"]
