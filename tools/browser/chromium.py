"""Headless Debian Chromium driven over the DevTools protocol on a pipe: no browser download, no extra package.

The browser player's harness (`gt-web`, docs/web.md) and the LAM web harness (docs/lam-web.md) use it; Chromium
reaches only 127.0.0.1. It needs nothing but the standard library.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import tempfile
import threading
from collections.abc import Sequence
from pathlib import Path

CHROMIUM = "/usr/bin/chromium"
INSTALL_CHROMIUM = "apt-get install -y chromium"

# WebGL2 without a GPU: ANGLE on SwiftShader (Chromium's CPU Vulkan), which newer Chromium only allows when told
# that the unsafe software path is wanted. docs/lam-web.md, "Chromium".
WEBGL_FLAGS = ("--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist")
# One device pixel per CSS pixel, no network but 127.0.0.1, nothing in the background.
BASE_FLAGS = (
    "--headless=new", "--no-sandbox", "--force-device-scale-factor=1", "--hide-scrollbars", "--mute-audio",
    "--no-first-run", "--no-default-browser-check", "--disable-background-networking", "--disable-component-update",
    "--disable-sync", "--disable-default-apps", "--disable-extensions", "--no-proxy-server",
    "--host-resolver-rules=MAP * ~NOTFOUND , EXCLUDE 127.0.0.1",
    "--disable-background-timer-throttling", "--disable-renderer-backgrounding",
    "--disable-backgrounding-occluded-windows",
)


class ChromiumMissing(RuntimeError):
    """Debian's chromium is not installed; the message says how to install it."""


class ChromiumError(RuntimeError):
    """The browser or the page failed; the message carries the page's error and its recent console lines."""


def chromium_path(path: str | os.PathLike | None = None) -> Path:
    """The Chromium executable to run (default /usr/bin/chromium), or ChromiumMissing with the install command."""
    exe = Path(path or CHROMIUM)
    if not (exe.is_file() and os.access(exe, os.X_OK)):
        raise ChromiumMissing(f"Chromium not found at {exe}: install Debian's package with `{INSTALL_CHROMIUM}` "
                              "(a downloaded browser build is not used)")
    return exe


class Chromium:
    """One headless Chromium with one page, driven by DevTools commands sent over a pipe (fds 3 and 4)."""

    def __init__(self, executable: str | os.PathLike | None = None, window: tuple[int, int] = (1024, 1024),
                 extra_flags: Sequence[str] = ()) -> None:
        exe = chromium_path(executable)
        self._profile = tempfile.mkdtemp(prefix="gt-chromium-")
        to_browser_r, self._to_browser = os.pipe()
        self._from_browser, from_browser_w = os.pipe()
        flags = [*BASE_FLAGS, *WEBGL_FLAGS, *extra_flags, f"--user-data-dir={self._profile}",
                 f"--window-size={window[0]},{window[1]}", "--remote-debugging-pipe", "about:blank"]
        # The shell puts the pipe ends on the fds the protocol names, then becomes Chromium.
        script = f'exec "$0" "$@" 3<&{to_browser_r} 4>&{from_browser_w}'
        self.process = subprocess.Popen(["/bin/bash", "-c", script, str(exe), *flags],
                                        pass_fds=(to_browser_r, from_browser_w), stdin=subprocess.DEVNULL,
                                        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        os.close(to_browser_r)
        os.close(from_browser_w)
        self._next_id = 0
        self._lock = threading.Lock()
        self._replies: dict[int, dict] = {}
        self._reply_ready = threading.Condition(self._lock)
        self._closed = False
        self.console: list[str] = []
        self._stderr_tail: list[str] = []
        threading.Thread(target=self._read_loop, daemon=True).start()
        threading.Thread(target=self._stderr_loop, daemon=True).start()
        target = self.send("Target.createTarget", {"url": "about:blank"})["targetId"]
        self.session = self.send("Target.attachToTarget", {"targetId": target, "flatten": True})["sessionId"]
        self.send("Runtime.enable", session=True)
        self.send("Page.enable", session=True)

    def _stderr_loop(self) -> None:
        """Keep the last lines of Chromium's stderr for error messages."""
        for line in self.process.stderr:
            self._stderr_tail = (self._stderr_tail + [line.decode(errors="replace").rstrip()])[-20:]

    def _read_loop(self) -> None:
        """Split the browser's NUL-terminated JSON messages into replies (by id) and console events."""
        buffer = b""
        while True:
            try:
                chunk = os.read(self._from_browser, 1 << 20)
            except OSError:
                chunk = b""
            if not chunk:
                break
            buffer += chunk
            *messages, buffer = buffer.split(b"\0")
            for raw in messages:
                message = json.loads(raw)
                if "id" in message:
                    with self._lock:
                        self._replies[message["id"]] = message
                        self._reply_ready.notify_all()
                else:
                    self._event(message)
        with self._lock:
            self._closed = True
            self._reply_ready.notify_all()

    def _event(self, message: dict) -> None:
        """Record the page's console output and uncaught exceptions (the last 200 lines)."""
        params = message.get("params", {})
        if message.get("method") == "Runtime.consoleAPICalled":
            text = " ".join(str(arg.get("value", arg.get("description", ""))) for arg in params.get("args", []))
            self.console = (self.console + [f"[{params.get('type')}] {text}"])[-200:]
        elif message.get("method") == "Runtime.exceptionThrown":
            details = params.get("exceptionDetails", {})
            text = details.get("exception", {}).get("description") or details.get("text", "")
            self.console = (self.console + [f"[exception] {text}"])[-200:]

    def send(self, method: str, params: dict | None = None, session: bool = False, timeout: float = 600.0) -> dict:
        """Run one DevTools command (on the page's session when `session`) and return its result."""
        with self._lock:
            self._next_id += 1
            ident = self._next_id
        message = {"id": ident, "method": method, "params": params or {}}
        if session:
            message["sessionId"] = self.session
        data = json.dumps(message).encode() + b"\0"
        try:
            while data:
                data = data[os.write(self._to_browser, data):]
        except OSError as exc:
            raise ChromiumError(f"Chromium is gone ({exc}); its stderr ends:\n" + "\n".join(self._stderr_tail)) from exc
        with self._lock:
            if not self._reply_ready.wait_for(lambda: ident in self._replies or self._closed, timeout):
                raise ChromiumError(f"{method} got no answer in {timeout:.0f} s")
            reply = self._replies.pop(ident, None)
        if reply is None:
            raise ChromiumError(f"Chromium closed during {method}; its stderr ends:\n" + "\n".join(self._stderr_tail))
        if "error" in reply:
            raise ChromiumError(f"{method} failed: {reply['error']}")
        return reply.get("result", {})

    def evaluate(self, expression: str, timeout: float = 600.0):
        """The JSON value of `expression` in the page, awaiting a promise; ChromiumError with the console on a throw."""
        result = self.send("Runtime.evaluate", {"expression": expression, "awaitPromise": True,
                                                "returnByValue": True, "timeout": timeout * 1000.0},
                           session=True, timeout=timeout + 5.0)
        if "exceptionDetails" in result:
            details = result["exceptionDetails"]
            text = details.get("exception", {}).get("description") or details.get("text", "")
            raise ChromiumError(f"page error: {text}\nrecent console:\n" + "\n".join(self.console[-30:]))
        return result.get("result", {}).get("value")

    def navigate(self, url: str) -> None:
        """Open `url` in the page."""
        reply = self.send("Page.navigate", {"url": url}, session=True)
        if reply.get("errorText"):
            raise ChromiumError(f"navigating to {url} failed: {reply['errorText']}")

    def close(self) -> None:
        """End the browser and remove its temporary profile."""
        if self.process.poll() is None:
            try:
                self.send("Browser.close", timeout=10.0)
            except ChromiumError:
                pass
            try:
                self.process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        for fd in (self._to_browser, self._from_browser):
            try:
                os.close(fd)
            except OSError:
                pass
        shutil.rmtree(self._profile, ignore_errors=True)

    def __enter__(self) -> Chromium:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
