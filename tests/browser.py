"""Headless Chromium for the tests and benchmarks that load a page the way a user's browser does: the page is
served over http from a local folder (browsers load ES modules over http, not from file://) and driven through
the DevTools protocol over a pipe (--remote-debugging-pipe: no websocket library, no network), waiting until the
page says it is done (its title) - virtual time does not wait for WebAssembly or streams."""
from __future__ import annotations

import base64
import functools
import http.server
import json
import os
import shutil
import subprocess
import tempfile
import threading
import time
from contextlib import contextmanager
from pathlib import Path


def chromium() -> str | None:
    for name in ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable"):
        if shutil.which(name):
            return shutil.which(name)
    return None


@contextmanager
def serve(folder: Path):
    """An http server on 127.0.0.1 (a free port) serving ``folder``; yields its base URL."""
    handler = functools.partial(_Quiet, directory=str(folder))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}"
    finally:
        server.shutdown()
        server.server_close()


class _Quiet(http.server.SimpleHTTPRequestHandler):
    def log_message(self, *args):
        pass


class _Pipe:
    """The DevTools protocol over Chromium's fds 3 (commands in) and 4 (replies out), NUL-terminated JSON."""

    def __init__(self, proc, write_fd: int, read_fd: int):
        self.proc, self.w, self.r, self.buf, self.next = proc, write_fd, read_fd, b"", 0

    def call(self, method: str, params: dict | None = None, session: str | None = None, timeout: float = 60.0):
        self.next += 1
        msg = {"id": self.next, "method": method, "params": params or {}}
        if session:
            msg["sessionId"] = session
        os.write(self.w, json.dumps(msg).encode() + b"\0")
        end = time.monotonic() + timeout
        while True:
            while b"\0" not in self.buf:
                if time.monotonic() > end or self.proc.poll() is not None:
                    raise TimeoutError(f"chromium: no reply to {method} (rc {self.proc.poll()})")
                import select

                ready, _, _ = select.select([self.r], [], [], 0.5)
                if ready:
                    chunk = os.read(self.r, 1 << 20)
                    if not chunk:
                        raise RuntimeError(f"chromium closed the pipe during {method}")
                    self.buf += chunk
            raw, self.buf = self.buf.split(b"\0", 1)
            reply = json.loads(raw)
            if reply.get("id") == self.next:
                if "error" in reply:
                    raise RuntimeError(f"chromium {method}: {reply['error']}")
                return reply.get("result", {})


def screenshot(url: str, width: int, height: int, timeout: float = 120.0, value: str | None = None):
    """(PNG bytes, the page's title) of ``url`` at width x height, once its title is "ready" or "error"; with
    ``value`` (a JavaScript expression) (PNG, title, the expression's JSON value then)."""
    exe = chromium()
    if exe is None:
        raise RuntimeError("headless Chromium not found (install it: `apt-get install -y chromium`; setup.sh does)")
    to_chrome_r, to_chrome_w = os.pipe()
    from_chrome_r, from_chrome_w = os.pipe()
    profile = tempfile.mkdtemp(prefix="volcap-chromium-")

    def fds():
        os.dup2(to_chrome_r, 3)
        os.dup2(from_chrome_w, 4)

    proc = subprocess.Popen([exe, "--headless", "--no-sandbox", "--remote-debugging-pipe", "--use-angle=swiftshader",
                             "--enable-unsafe-swiftshader", "--disable-gpu-sandbox", "--no-first-run", "--hide-scrollbars",
                             "--disable-background-networking", "--disable-component-update", "--disable-sync",
                             f"--user-data-dir={profile}", "about:blank"],
                            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            preexec_fn=fds, pass_fds=(3, 4))
    os.close(to_chrome_r)
    os.close(from_chrome_w)
    pipe = _Pipe(proc, to_chrome_w, from_chrome_r)
    try:
        target = pipe.call("Target.createTarget", {"url": "about:blank"})["targetId"]
        s = pipe.call("Target.attachToTarget", {"targetId": target, "flatten": True})["sessionId"]
        pipe.call("Emulation.setDeviceMetricsOverride", {"width": width, "height": height, "deviceScaleFactor": 1,
                                                          "mobile": False}, s)
        pipe.call("Page.enable", {}, s)
        pipe.call("Page.navigate", {"url": url}, s)
        end, title = time.monotonic() + timeout, ""
        while time.monotonic() < end:
            title = pipe.call("Runtime.evaluate", {"expression": "document.title", "returnByValue": True}, s)
            title = title.get("result", {}).get("value", "")
            if title in ("ready", "error"):
                break
            time.sleep(0.2)
        detail = ""
        if title == "error":
            detail = pipe.call("Runtime.evaluate", {"expression": "document.getElementById('error').textContent",
                                                    "returnByValue": True}, s).get("result", {}).get("value", "")
        elif title != "ready":
            raise TimeoutError(f"{url}: the page did not get ready in {timeout} s (title {title!r})")
        shot = pipe.call("Page.captureScreenshot", {"format": "png"}, s)["data"]
        out = (base64.b64decode(shot), title + (f": {detail}" if detail else ""))
        if value is not None:
            got = pipe.call("Runtime.evaluate", {"expression": value, "returnByValue": True}, s)
            out += (got.get("result", {}).get("value"),)
        return out
    finally:
        try:
            pipe.call("Browser.close", timeout=5)
        except Exception:  # noqa: BLE001 - closing a browser that is gone
            pass
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
        os.close(to_chrome_w)
        os.close(from_chrome_r)
        shutil.rmtree(profile, ignore_errors=True)
