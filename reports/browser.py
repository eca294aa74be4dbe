"""Drive Debian's headless Chromium over the DevTools protocol (``--remote-debugging-pipe``,
standard library only): open a report from ``file://``, collect JavaScript console errors,
exceptions and every network request, wait until all figures are drawn, evaluate
expressions in the page and take screenshots. Used by the report tests, the size/render
benchmark and the documentation screenshot; never downloads a browser.
"""

from __future__ import annotations

import base64
import json
import os
import select
import shutil
import subprocess
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

CHROMIUM_CANDIDATES = ("/usr/bin/chromium", "/usr/bin/chromium-browser")

FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-default-browser-check",
    "--disable-dev-shm-usage",
    "--hide-scrollbars",
    "--mute-audio",
    "--disable-extensions",
    "--force-device-scale-factor=1",
    "--disable-features=Translate,MediaRouter,OptimizationHints",
)


class BrowserError(RuntimeError):
    pass


def _high_fd(fd: int) -> int:
    """Move a pipe end above 9 (close-on-exec), so the child's dup2 onto 3 and 4 can never
    clobber the other end or be a no-op that keeps close-on-exec."""
    import fcntl

    hi = fcntl.fcntl(fd, fcntl.F_DUPFD_CLOEXEC, 10)
    os.close(fd)
    return hi


def find_chromium() -> str | None:
    env = os.environ.get("MIMUCAL_CHROMIUM")
    if env:
        return env if os.access(env, os.X_OK) else None
    for c in CHROMIUM_CANDIDATES:
        if os.access(c, os.X_OK):
            return c
    return shutil.which("chromium")


@dataclass
class PageLog:
    console_errors: list[str] = field(default_factory=list)
    console_warnings: list[str] = field(default_factory=list)
    exceptions: list[str] = field(default_factory=list)
    log_errors: list[str] = field(default_factory=list)
    requests: list[str] = field(default_factory=list)

    @property
    def errors(self) -> list[str]:
        return self.console_errors + self.exceptions + self.log_errors

    @property
    def external_requests(self) -> list[str]:
        return [u for u in self.requests if not u.startswith(("file:", "data:", "about:", "blob:"))]


class Chromium:
    """One headless browser with one page. Use as a context manager."""

    def __init__(
        self, executable: str | None = None, width: int = 1400, height: int = 900, timeout_s: float = 60.0
    ) -> None:
        self.executable = executable or find_chromium()
        if not self.executable:
            raise BrowserError("chromium not found (install Debian's package: tools/install-browser.sh)")
        self.width, self.height, self.timeout_s = width, height, timeout_s
        self.log = PageLog()
        self._id = 0
        self._buf = b""
        self._events: list[dict] = []

    # -- process and pipe
    def __enter__(self) -> Chromium:
        self._profile = tempfile.mkdtemp(prefix="mimucal-chromium-")
        to_child_r, self._to_child = (_high_fd(fd) for fd in os.pipe())
        self._from_child, from_child_w = (_high_fd(fd) for fd in os.pipe())

        def wire() -> None:  # runs in the child: the protocol pipes are fds 3 and 4
            os.dup2(to_child_r, 3)
            os.dup2(from_child_w, 4)

        cmd = [
            self.executable,
            *FLAGS,
            f"--user-data-dir={self._profile}",
            f"--window-size={self.width},{self.height}",
            "--remote-debugging-pipe",
            "about:blank",
        ]
        self._stderr = tempfile.TemporaryFile()
        self.proc = subprocess.Popen(
            cmd,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=self._stderr,
            preexec_fn=wire,
            close_fds=False,
        )
        os.close(to_child_r)
        os.close(from_child_w)
        try:
            targets = self.send("Target.getTargets")["targetInfos"]
            page = next((t for t in targets if t["type"] == "page"), None)
            if page is None:
                page = {"targetId": self.send("Target.createTarget", url="about:blank")["targetId"]}
            self.session = self.send("Target.attachToTarget", targetId=page["targetId"], flatten=True)[
                "sessionId"
            ]
            for domain in ("Page", "Runtime", "Log", "Network"):
                self.send(f"{domain}.enable", session=True)
            self.send(
                "Emulation.setDeviceMetricsOverride",
                session=True,
                width=self.width,
                height=self.height,
                deviceScaleFactor=1,
                mobile=False,
            )
        except BaseException:
            self.__exit__(None, None, None)
            raise
        return self

    def __exit__(self, *exc: Any) -> None:
        try:
            if self.proc.poll() is None:
                try:
                    self.send("Browser.close", timeout_s=5)
                except Exception:
                    pass
                try:
                    self.proc.wait(timeout=5)
                except subprocess.TimeoutExpired:
                    self.proc.kill()
                    self.proc.wait(timeout=5)
        finally:
            for fd in (self._to_child, self._from_child):
                try:
                    os.close(fd)
                except OSError:
                    pass
            shutil.rmtree(self._profile, ignore_errors=True)

    def stderr_text(self) -> str:
        self._stderr.seek(0)
        return self._stderr.read().decode(errors="replace")

    def send(self, method: str, session: bool = False, timeout_s: float | None = None, **params: Any) -> dict:
        self._id += 1
        msg: dict[str, Any] = {"id": self._id, "method": method, "params": params}
        if session:
            msg["sessionId"] = self.session
        os.write(self._to_child, json.dumps(msg).encode() + b"\0")
        deadline = time.monotonic() + (timeout_s or self.timeout_s)
        while True:
            m = self._read(deadline)
            if m.get("id") == self._id:
                if "error" in m:
                    raise BrowserError(f"{method}: {m['error']}")
                return m.get("result", {})
            self._event(m)

    def _read(self, deadline: float) -> dict:
        while b"\0" not in self._buf:
            left = deadline - time.monotonic()
            if left <= 0:
                raise BrowserError("timed out waiting for chromium")
            r, _, _ = select.select([self._from_child], [], [], min(left, 0.5))
            if r:
                chunk = os.read(self._from_child, 1 << 20)
                if not chunk:
                    raise BrowserError(f"chromium exited: {self.stderr_text()[-2000:]}")
                self._buf += chunk
        msg, self._buf = self._buf.split(b"\0", 1)
        return json.loads(msg)

    def _event(self, m: dict) -> None:
        method, p = m.get("method", ""), m.get("params", {})
        if method == "Runtime.consoleAPICalled":
            text = " ".join(str(a.get("value", a.get("description", ""))) for a in p.get("args", []))
            if p.get("type") in ("error", "assert"):
                self.log.console_errors.append(text)
            elif p.get("type") == "warning":
                self.log.console_warnings.append(text)
        elif method == "Runtime.exceptionThrown":
            d = p.get("exceptionDetails", {})
            self.log.exceptions.append(
                d.get("exception", {}).get("description") or d.get("text", "exception")
            )
        elif method == "Log.entryAdded":
            e = p.get("entry", {})
            if e.get("level") == "error":
                self.log.log_errors.append(f"{e.get('source')}: {e.get('text')} {e.get('url', '')}")
        elif method == "Network.requestWillBeSent":
            self.log.requests.append(p.get("request", {}).get("url", ""))
        self._events.append(m)

    def pump(self, seconds: float) -> None:
        """Process incoming events for a while (console messages arrive asynchronously)."""
        deadline = time.monotonic() + seconds
        while True:
            try:
                self._event(self._read(deadline))
            except BrowserError as e:
                if "timed out" in str(e):
                    return
                raise

    # -- page helpers
    def open(self, path: str | Path) -> float:
        """Navigate to a local file and wait for its load event; returns seconds taken."""
        url = Path(path).resolve().as_uri()
        self._events.clear()
        t0 = time.monotonic()
        self.send("Page.navigate", session=True, url=url)
        deadline = t0 + self.timeout_s
        while not any(e.get("method") == "Page.loadEventFired" for e in self._events):
            self._event(self._read(deadline))
        return time.monotonic() - t0

    def evaluate(self, expression: str, await_promise: bool = False) -> Any:
        r = self.send(
            "Runtime.evaluate",
            session=True,
            expression=expression,
            returnByValue=True,
            awaitPromise=await_promise,
        )
        if "exceptionDetails" in r:
            raise BrowserError(
                f"evaluate failed: {r['exceptionDetails'].get('text')}: "
                f"{r['exceptionDetails'].get('exception', {}).get('description')}"
            )
        return r.get("result", {}).get("value")

    def wait_for(self, expression: str, timeout_s: float | None = None, poll_s: float = 0.05) -> float:
        """Poll a JS expression until truthy; returns seconds waited."""
        t0 = time.monotonic()
        deadline = t0 + (timeout_s or self.timeout_s)
        while not self.evaluate(expression):
            if time.monotonic() > deadline:
                raise BrowserError(f"timed out waiting for: {expression}")
            self.pump(poll_s)
        return time.monotonic() - t0

    def wait_figures(self, timeout_s: float | None = None) -> float:
        """Wait until every figure the page could draw so far has been drawn or has failed."""
        return self.wait_for(
            "document.querySelectorAll('.figure[data-state=drawing]').length === 0 && "
            "document.querySelectorAll('.figure:not([data-state])').length === "
            "Array.from(document.querySelectorAll('.figure:not([data-state])'))"
            ".filter(function(e){return e.closest('details:not([open])');}).length",
            timeout_s,
        )

    def screenshot(
        self,
        path: str | Path,
        full_page: bool = False,
        max_height: int = 16000,
        clip_selector: str | None = None,
    ) -> Path:
        params: dict[str, Any] = {"format": "png"}
        if clip_selector:
            box = self.evaluate(
                f"(function(){{var r=document.querySelector({json.dumps(clip_selector)})"
                ".getBoundingClientRect();"
                "return [r.left + window.scrollX, r.top + window.scrollY, r.width, r.height];})()"
            )
            params.update(
                clip={
                    "x": box[0],
                    "y": box[1],
                    "width": box[2],
                    "height": min(box[3], max_height),
                    "scale": 1,
                },
                captureBeyondViewport=True,
            )
        elif full_page:
            h = int(self.evaluate("document.documentElement.scrollHeight"))
            params.update(
                clip={"x": 0, "y": 0, "width": self.width, "height": min(h, max_height), "scale": 1},
                captureBeyondViewport=True,
            )
        data = self.send("Page.captureScreenshot", session=True, **params)["data"]
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(base64.b64decode(data))
        return path
