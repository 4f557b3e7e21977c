"""Headless Chromium driven over the DevTools protocol: open a page, evaluate JavaScript, take screenshots.

Used by the viewer's browser test and ``benchmarks/viewer.py`` (and by anyone who wants a picture of the
viewer without a display). Chromium draws WebGL in software (SwiftShader), so no GPU is needed. Only the
protocol's ``Page`` and ``Runtime`` domains are used, over the ``websockets`` client that viser depends on.
"""

from __future__ import annotations

import base64
import itertools
import json
import os
import shutil
import socket
import subprocess
import tempfile
import time
import urllib.request
from pathlib import Path

#: Executable names tried in order (Debian's package installs ``chromium``).
CHROMIUM_NAMES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on now (for a test or benchmark server)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def find_chromium() -> str | None:
    """Path of a Chromium executable (``$BCMOCAP_CHROMIUM`` first, then :data:`CHROMIUM_NAMES` on PATH)."""
    given = os.environ.get("BCMOCAP_CHROMIUM")
    if given:
        return given if Path(given).is_file() else None
    for name in CHROMIUM_NAMES:
        path = shutil.which(name)
        if path:
            return path
    return None


class Browser:
    """One headless Chromium process with one page; a context manager that ends the process on exit.

    Args:
        width, height: the window (CSS px).
        executable: Chromium's path (default: :func:`find_chromium`).
        timeout: seconds to wait for Chromium to start and for each protocol answer.
    """

    def __init__(self, width: int = 1280, height: int = 800, executable: str | None = None, timeout: float = 30.0):
        self.executable = executable or find_chromium()
        if self.executable is None:
            raise RuntimeError("no Chromium found (install Debian's 'chromium' package or set BCMOCAP_CHROMIUM)")
        self.width, self.height, self.timeout = width, height, timeout
        self._profile = tempfile.mkdtemp(prefix="bcmocap-chromium-")
        self._ids = itertools.count(1)
        self._process = None
        self._socket = None

    def __enter__(self) -> Browser:
        args = [self.executable, "--headless=new", "--no-sandbox", "--no-first-run", "--no-default-browser-check",
                "--disable-dev-shm-usage", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
                "--ignore-gpu-blocklist", "--disable-background-timer-throttling",
                "--disable-renderer-backgrounding", "--disable-backgrounding-occluded-windows",
                f"--window-size={self.width},{self.height}", "--remote-debugging-address=127.0.0.1",
                "--remote-debugging-port=0", f"--user-data-dir={self._profile}", "about:blank"]
        self._process = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                         stdin=subprocess.DEVNULL)
        try:
            self._connect()
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _connect(self) -> None:
        from websockets.sync.client import connect

        port_file = Path(self._profile) / "DevToolsActivePort"
        deadline = time.monotonic() + self.timeout
        while not (port_file.is_file() and port_file.read_text().strip()):
            if self._process.poll() is not None:
                raise RuntimeError(f"Chromium exited with code {self._process.returncode} before it listened")
            if time.monotonic() > deadline:
                raise TimeoutError(f"Chromium did not open its DevTools port within {self.timeout:g} s")
            time.sleep(0.05)
        port = int(port_file.read_text().split()[0])
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=self.timeout) as answer:
            pages = [t for t in json.loads(answer.read()) if t.get("type") == "page"]
        if not pages:
            raise RuntimeError("Chromium opened no page")
        self._socket = connect(pages[0]["webSocketDebuggerUrl"], max_size=None, open_timeout=self.timeout)
        self.call("Page.enable")
        self.call("Runtime.enable")

    def call(self, method: str, **params) -> dict:
        """Send one protocol command and return its result (events received meanwhile are dropped)."""
        ident = next(self._ids)
        self._socket.send(json.dumps({"id": ident, "method": method, "params": params}))
        deadline = time.monotonic() + self.timeout
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise TimeoutError(f"Chromium did not answer {method} within {self.timeout:g} s")
            message = json.loads(self._socket.recv(timeout=remaining))
            if message.get("id") == ident:
                if "error" in message:
                    raise RuntimeError(f"Chromium: {method}: {message['error'].get('message')}")
                return message.get("result", {})

    def open(self, url: str) -> None:
        """Load ``url`` and wait until its document has loaded (the page's scripts run on)."""
        self.call("Page.navigate", url=url)
        deadline = time.monotonic() + self.timeout
        while time.monotonic() < deadline:
            try:
                if self.evaluate("document.readyState === 'complete' && location.href") == url:
                    return
            except RuntimeError:  # the old document is gone, the new one not attached yet
                pass
            time.sleep(0.05)
        raise TimeoutError(f"Chromium did not load {url} within {self.timeout:g} s")

    def evaluate(self, expression: str, await_promise: bool = False):
        """The JSON value of a JavaScript expression in the page."""
        result = self.call("Runtime.evaluate", expression=expression, returnByValue=True, awaitPromise=await_promise)
        if "exceptionDetails" in result:
            raise RuntimeError(f"JavaScript error: {result['exceptionDetails'].get('text')}")
        return result.get("result", {}).get("value")

    def screenshot(self, path: str | os.PathLike | None = None) -> bytes:
        """A PNG of the window (written to ``path`` if given)."""
        data = base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])
        if path is not None:
            Path(path).write_bytes(data)
        return data

    def dismiss_notifications(self) -> int:
        """Close the page's toast notifications (viser warns that WebGL runs in software); returns how many."""
        return int(self.evaluate(
            "(() => { const b = document.querySelectorAll('.mantine-Notification-closeButton');"
            " b.forEach(x => x.click()); return b.length; })()") or 0)

    def animation_frame_rate(self, seconds: float = 2.0) -> float:
        """Frames per second the page drew over ``seconds`` (requestAnimationFrame callbacks)."""
        ms = int(seconds * 1000)
        return float(self.evaluate(
            "new Promise(done => { let n = 0; const t0 = performance.now();"
            " const tick = now => { n++; if (now - t0 < %d) requestAnimationFrame(tick);"
            " else done(1000 * n / (now - t0)); }; requestAnimationFrame(tick); })" % ms, await_promise=True))

    def close(self) -> None:
        """End Chromium (only the process this object started) and remove its profile."""
        if self._socket is not None:
            try:
                self._socket.close()
            except Exception:  # noqa: BLE001 - closing a dead socket
                pass
            self._socket = None
        if self._process is not None and self._process.poll() is None:
            self._process.terminate()
            try:
                self._process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self._process.kill()
                self._process.wait()
        shutil.rmtree(self._profile, ignore_errors=True)


def colour_pixels(png: bytes, rgb, tolerance: int = 24, left_fraction: float = 1.0) -> int:
    """Pixels of a PNG screenshot within ``tolerance`` (per channel) of colour ``rgb``, counted in the left
    ``left_fraction`` of the image (to leave out a panel on the right)."""
    import cv2
    import numpy as np

    image = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    if image is None:
        return 0
    image = image[:, : int(image.shape[1] * left_fraction), ::-1].astype(int)
    return int((np.abs(image - np.asarray(rgb)).max(axis=-1) <= tolerance).sum())
