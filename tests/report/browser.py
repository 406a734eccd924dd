"""Headless Chromium driven over the DevTools protocol on a pipe (``--remote-debugging-pipe``): no
WebDriver, no extra Python package. Used by the report tests to open a page as a person would, collect
every console message and uncaught exception, evaluate expressions in the page, print it to PDF and take
a screenshot.

Messages are JSON objects separated by NUL bytes: Chromium reads commands on its fd 3 and writes
replies and events on its fd 4. Every wait is on a reply or an event, with a generous timeout that only
guards against a hung browser (never a sleep).
"""

from __future__ import annotations

import base64
import json
import os
import queue
import shutil
import subprocess
import tempfile
import threading
from pathlib import Path
from typing import Any

TIMEOUT_S = 180.0


def find_chromium() -> str | None:
    for name in ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable"):
        path = shutil.which(name)
        if path:
            return path
    return None


def ensure_chromium() -> tuple[str | None, str]:
    """(path to Chromium, "") or (None, why it cannot be had). Installs Debian's ``chromium`` with apt
    when it is missing and this runs as root (CI); otherwise says what to install."""
    path = find_chromium()
    if path:
        return path, ""
    if os.name != "posix" or os.geteuid() != 0 or not shutil.which("apt-get"):
        return None, "Chromium is not installed (Debian: apt-get install chromium) and this user cannot install it"
    env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
    for cmd in (["apt-get", "install", "-y", "--no-install-recommends", "chromium"],
                ["apt-get", "update"], ["apt-get", "install", "-y", "--no-install-recommends", "chromium"]):
        r = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=900)
        if cmd[1] == "install" and r.returncode == 0:
            break
    path = find_chromium()
    if path:
        return path, ""
    return None, f"apt-get install chromium failed: {(r.stderr or r.stdout).strip().splitlines()[-1:]}"


class Browser:
    """One headless Chromium with one page (``open`` navigates it)."""

    def __init__(self, exe: str) -> None:
        self._profile = tempfile.mkdtemp(prefix="report-chromium-")
        to_chrome_r, self._to_chrome = os.pipe()
        self._from_chrome, from_chrome_w = os.pipe()

        def child_fds() -> None:  # the protocol's fixed descriptors in the child (copies first: the
            a, b = os.dup(to_chrome_r), os.dup(from_chrome_w)  # pipe ends may themselves be 3 or 4)
            os.dup2(a, 3)
            os.dup2(b, 4)

        self.proc = subprocess.Popen(
            [exe, "--headless=new", "--remote-debugging-pipe", "--no-sandbox", "--disable-gpu",
             "--disable-dev-shm-usage", "--no-first-run", "--no-default-browser-check", "--disable-extensions",
             "--disable-background-networking", "--disable-component-update", "--disable-sync",
             f"--user-data-dir={self._profile}", "about:blank"],
            preexec_fn=child_fds, pass_fds=(3, 4, to_chrome_r, from_chrome_w),
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        os.close(to_chrome_r)
        os.close(from_chrome_w)
        self._id = 0
        self._replies: dict[int, queue.Queue] = {}
        self.events: queue.Queue = queue.Queue()
        self._lock = threading.Lock()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()
        target = self.call("Target.createTarget", url="about:blank")["targetId"]
        self.session = self.call("Target.attachToTarget", targetId=target, flatten=True)["sessionId"]
        for domain in ("Runtime", "Log", "Page"):
            self.call(f"{domain}.enable", session=True)

    def _read(self) -> None:
        buf = b""
        with os.fdopen(self._from_chrome, "rb", buffering=0) as f:
            while True:
                chunk = f.read(1 << 16)
                if not chunk:
                    self.events.put(None)
                    return
                buf += chunk
                while b"\0" in buf:
                    raw, buf = buf.split(b"\0", 1)
                    msg = json.loads(raw)
                    if "id" in msg and msg["id"] in self._replies:
                        self._replies[msg["id"]].put(msg)
                    else:
                        self.events.put(msg)

    def call(self, method: str, session: bool = False, **params: Any) -> dict[str, Any]:
        with self._lock:
            self._id += 1
            mid = self._id
            self._replies[mid] = queue.Queue()
        msg: dict[str, Any] = {"id": mid, "method": method, "params": params}
        if session:
            msg["sessionId"] = self.session
        os.write(self._to_chrome, json.dumps(msg).encode() + b"\0")
        reply = self._replies[mid].get(timeout=TIMEOUT_S)
        del self._replies[mid]
        if "error" in reply:
            raise RuntimeError(f"{method}: {reply['error']}")
        return reply.get("result", {})

    def open(self, path: Path, width: int = 1200, height: int = 900) -> list[str]:
        """Load ``path`` and wait for its load event; returns the console errors, warnings and uncaught
        exceptions reported while it loaded (one line each)."""
        self.call("Emulation.setDeviceMetricsOverride", session=True, width=width, height=height,
                  deviceScaleFactor=1, mobile=False)
        self.call("Page.navigate", session=True, url=Path(path).resolve().as_uri())
        problems = []
        while True:
            ev = self.events.get(timeout=TIMEOUT_S)
            if ev is None:
                raise RuntimeError("Chromium exited while loading the page")
            problems += _problem(ev)
            if ev.get("method") == "Page.loadEventFired":
                break
        # what arrived with the load event (console calls are delivered in order before it or with it)
        self.evaluate("1")
        while not self.events.empty():
            ev = self.events.get_nowait()
            if ev is not None:
                problems += _problem(ev)
        return problems

    def evaluate(self, expression: str) -> Any:
        r = self.call("Runtime.evaluate", session=True, expression=expression, returnByValue=True)
        if "exceptionDetails" in r:
            raise RuntimeError(f"{expression}: {r['exceptionDetails'].get('text')}")
        return r["result"].get("value")

    def screenshot(self, path: Path, width: int = 1200, height: int = 2400) -> Path:
        """PNG of the top ``height`` CSS pixels of the page at ``width``."""
        self.call("Emulation.setDeviceMetricsOverride", session=True, width=width, height=height,
                  deviceScaleFactor=1, mobile=False)
        data = self.call("Page.captureScreenshot", session=True, format="png",
                         clip={"x": 0, "y": 0, "width": width, "height": height, "scale": 1})["data"]
        Path(path).write_bytes(base64.b64decode(data))
        return Path(path)

    def pdf(self) -> bytes:
        return base64.b64decode(self.call("Page.printToPDF", session=True, printBackground=False)["data"])

    def close(self) -> None:
        try:
            self.call("Browser.close")
        except Exception:
            pass
        try:
            self.proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        os.close(self._to_chrome)
        shutil.rmtree(self._profile, ignore_errors=True)

    def __enter__(self) -> Browser:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def _problem(ev: dict[str, Any]) -> list[str]:
    m, p = ev.get("method"), ev.get("params", {})
    if m == "Runtime.exceptionThrown":
        d = p.get("exceptionDetails", {})
        return [f"exception: {d.get('text')} {d.get('exception', {}).get('description', '')}".strip()]
    if m == "Runtime.consoleAPICalled" and p.get("type") in ("error", "warning", "assert"):
        return [f"console.{p['type']}: " + " ".join(str(a.get("value", a.get("description", ""))) for a in p["args"])]
    if m == "Log.entryAdded" and p.get("entry", {}).get("level") in ("error", "warning"):
        e = p["entry"]
        return [f"{e.get('source')} {e['level']}: {e.get('text')} {e.get('url', '')}".strip()]
    return []
