"""A headless Chromium driven over the DevTools protocol (websocket), for tests that
look at pages the way a person does: console errors, loaded images, screenshots.

Only ``websocket-client`` is needed besides Debian's ``chromium``.
"""
from __future__ import annotations

import base64
import json
import os
import shutil
import subprocess
import tempfile
import time
import urllib.request
from pathlib import Path

import pytest

from conftest import require_tool

REPO = Path(__file__).resolve().parents[1]
# Screenshots the tests keep (results/ is ignored by git); CI can collect them from here.
SCREENSHOTS = Path(os.environ.get("GEARBENCH_SCREENSHOTS", REPO / "results" / "screenshots"))


def chromium_path() -> str:
    for name in ("chromium", "chromium-browser", "google-chrome"):
        if shutil.which(name):
            return shutil.which(name)
    return require_tool("chromium", "install it: apt-get install chromium")


class Browser:
    """One headless Chromium with one page; ``errors`` collects console errors and
    uncaught exceptions as they happen."""

    def __init__(self, *, width: int = 1280, height: int = 900, webgl: bool = False):
        import websocket   # websocket-client (test dependency)

        self.profile = tempfile.mkdtemp(prefix="gearbench-chromium-")
        args = [chromium_path(), "--headless=new", "--no-sandbox", "--no-first-run",
                "--no-default-browser-check", "--disable-extensions", "--disable-dev-shm-usage",
                "--remote-debugging-port=0", "--remote-allow-origins=*",
                # a headless page counts as hidden: without these its timers and animation
                # frames are throttled, and a WebAssembly app (Rerun) ingests one frame at a time
                "--disable-background-timer-throttling", "--disable-renderer-backgrounding",
                "--disable-backgrounding-occluded-windows",
                f"--user-data-dir={self.profile}", f"--window-size={width},{height}"]
        if webgl:   # software WebGL (SwiftShader), the default where there is no GPU;
            # not --use-angle=swiftshader: with it headless frames drop to ~2 per second
            args += ["--enable-unsafe-swiftshader"]
        else:
            args += ["--disable-gpu"]
        self.proc = subprocess.Popen(args + ["about:blank"], stdout=subprocess.DEVNULL,
                                     stderr=subprocess.DEVNULL)
        port_file = Path(self.profile) / "DevToolsActivePort"
        deadline = time.monotonic() + 60
        while not (port_file.exists() and port_file.read_text().strip()):
            if self.proc.poll() is not None or time.monotonic() > deadline:
                self.close()
                raise RuntimeError("chromium did not start its DevTools endpoint")
            time.sleep(0.1)
        port = int(port_file.read_text().split()[0])
        targets = json.load(urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=10))
        page = next(t for t in targets if t.get("type") == "page")
        self.ws = websocket.create_connection(page["webSocketDebuggerUrl"], timeout=120,
                                              suppress_origin=True)
        self._id = 0
        self.events: list[dict] = []
        self.errors: list[str] = []
        for domain in ("Page", "Runtime", "Log"):
            self.call(f"{domain}.enable")

    def _on_event(self, msg: dict) -> None:
        self.events.append(msg)
        method, p = msg.get("method"), msg.get("params", {})
        if method == "Runtime.consoleAPICalled" and p.get("type") in ("error", "assert"):
            self.errors.append("console: " + " ".join(str(a.get("value", a.get("description", "")))
                                                      for a in p.get("args", [])))
        elif method == "Runtime.exceptionThrown":
            d = p.get("exceptionDetails", {})
            self.errors.append("exception: " + str(d.get("exception", {}).get("description") or d.get("text")))
        elif method == "Log.entryAdded" and p.get("entry", {}).get("level") == "error":
            e = p["entry"]
            self.errors.append(f"log: {e.get('text')} {e.get('url', '')}".strip())

    def call(self, method: str, **params) -> dict:
        self._id += 1
        self.ws.send(json.dumps({"id": self._id, "method": method, "params": params}))
        while True:
            msg = json.loads(self.ws.recv())
            if msg.get("id") == self._id:
                if "error" in msg:
                    raise RuntimeError(f"{method}: {msg['error']}")
                return msg.get("result", {})
            self._on_event(msg)

    def pump(self, seconds: float) -> None:
        """Receive events for ``seconds`` (console errors arriving late)."""
        end = time.monotonic() + seconds
        self.ws.settimeout(0.2)
        try:
            while time.monotonic() < end:
                try:
                    self._on_event(json.loads(self.ws.recv()))
                except Exception:   # websocket timeout: nothing arrived
                    pass
        finally:
            self.ws.settimeout(120)

    def navigate(self, url: str, timeout_s: float = 60.0) -> None:
        n0 = len(self.events)
        self.call("Page.navigate", url=url)
        deadline = time.monotonic() + timeout_s
        while not any(e.get("method") == "Page.loadEventFired" for e in self.events[n0:]):
            if time.monotonic() > deadline:
                raise TimeoutError(f"{url}: no load event in {timeout_s:.0f} s")
            self.pump(0.2)

    def evaluate(self, expression: str):
        r = self.call("Runtime.evaluate", expression=expression, returnByValue=True, awaitPromise=True)
        if "exceptionDetails" in r:
            raise RuntimeError(f"evaluate: {r['exceptionDetails']}")
        return r["result"].get("value")

    def screenshot(self, path: Path, *, full_page: bool = False) -> Path:
        params = {"format": "png"}
        if full_page:
            m = self.call("Page.getLayoutMetrics")["cssContentSize"]
            params.update(captureBeyondViewport=True,
                          clip={"x": 0, "y": 0, "width": m["width"], "height": m["height"], "scale": 1})
        data = base64.b64decode(self.call("Page.captureScreenshot", **params)["data"])
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data)
        return path

    def close(self) -> None:
        try:
            self.ws.close()
        except Exception:
            pass
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
        shutil.rmtree(self.profile, ignore_errors=True)


@pytest.fixture
def browser_factory():
    opened = []

    def make(**kw) -> Browser:
        pytest.importorskip("websocket", reason="pip install websocket-client (a test dependency)")
        chromium_path()
        b = Browser(**kw)
        opened.append(b)
        return b

    yield make
    for b in opened:
        b.close()
