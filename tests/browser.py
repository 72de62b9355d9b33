"""Real headless Chromium driven over the DevTools protocol (CDP) with `websockets`."""

from __future__ import annotations

import base64
import json
import shutil
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Any

from websockets.sync.client import connect

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--window-size=1000,700",
         "--remote-debugging-port=0"]


class Browser:
    """One headless Chromium with one page; ``evaluate`` JS, ``screenshot`` PNG bytes."""

    def __init__(self, url: str, timeout: float = 30.0, console: bool = False,
                 flags: tuple[str, ...] = ()) -> None:
        if CHROMIUM is None:
            raise RuntimeError("chromium is not installed")
        self.dir = tempfile.mkdtemp(prefix="articast-chromium-")
        self.proc = subprocess.Popen([CHROMIUM, *FLAGS, *flags, f"--user-data-dir={self.dir}",
                                      "about:blank"], stdout=subprocess.DEVNULL,
                                     stderr=subprocess.DEVNULL)
        port_file = Path(self.dir) / "DevToolsActivePort"
        deadline = time.monotonic() + timeout
        while not (port_file.exists() and port_file.read_text().strip()):
            if time.monotonic() > deadline or self.proc.poll() is not None:
                self.close()
                raise RuntimeError("chromium did not start")
            time.sleep(0.05)
        port = int(port_file.read_text().split()[0])
        import urllib.request

        with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=5) as r:
            page = next(t for t in json.load(r) if t["type"] == "page")
        self._conn = connect(page["webSocketDebuggerUrl"], max_size=2**26, open_timeout=10)
        self.ws = self._conn.__enter__()
        self._id = 0
        self.events: list[dict[str, Any]] = []  # what Chromium reported meanwhile (enable() first)
        self.call("Page.enable")
        if console:
            self.call("Log.enable")
            self.call("Runtime.enable")
        self.call("Page.navigate", url=url)

    def call(self, method: str, **params: Any) -> dict[str, Any]:
        self._id += 1
        self.ws.send(json.dumps({"id": self._id, "method": method, "params": params}))
        while True:
            msg = json.loads(self.ws.recv(timeout=30))
            if msg.get("id") == self._id:
                if "error" in msg:
                    raise RuntimeError(f"{method}: {msg['error']}")
                return msg.get("result", {})
            if "method" in msg and len(self.events) < 10000:
                self.events.append(msg)

    def evaluate(self, expression: str) -> Any:
        r = self.call("Runtime.evaluate", expression=expression, returnByValue=True)
        return r.get("result", {}).get("value")

    def wait_for(self, expression: str, timeout: float = 30.0) -> Any:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            v = self.evaluate(expression)
            if v:
                return v
            time.sleep(0.1)
        raise TimeoutError(f"{expression!r} stayed false for {timeout} s")

    def console_errors(self) -> list[str]:
        """The errors the page's console showed so far (failed requests, exceptions,
        console.error): Log and Runtime must have been enabled before the page loaded, as
        ``Browser(url, console=True)`` does."""
        self.evaluate("0")  # collect what arrived meanwhile
        out = []
        for e in self.events:
            p = e.get("params", {})
            if e["method"] == "Log.entryAdded" and p["entry"]["level"] == "error":
                out.append(f"{p['entry'].get('url', '')}: {p['entry']['text']}")
            elif e["method"] == "Runtime.exceptionThrown":
                out.append(p["exceptionDetails"].get("exception", {}).get("description", "")
                           or p["exceptionDetails"]["text"])
            elif e["method"] == "Runtime.consoleAPICalled" and p["type"] == "error":
                out.append(" ".join(str(a.get("value", a.get("description", "")))
                                    for a in p["args"]))
        return out

    def screenshot(self) -> bytes:
        return base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])

    def close(self) -> None:
        conn = getattr(self, "_conn", None)
        if conn is not None:
            try:
                conn.__exit__(None, None, None)
            except Exception:  # noqa: BLE001 - closing anyway
                pass
        self.proc.terminate()
        try:
            self.proc.wait(10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
        shutil.rmtree(self.dir, ignore_errors=True)

    def __enter__(self) -> Browser:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()
