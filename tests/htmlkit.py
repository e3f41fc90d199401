"""Open an HTML file in a real headless browser and report what a reader would meet.

Chromium from the system's packages (Debian: ``apt-get install -y chromium``), driven over
the DevTools protocol on a pipe (``--remote-debugging-pipe``: JSON messages ending in a
NUL byte on file descriptors 3 and 4), with nothing but the standard library. The page
is loaded from a ``file://`` URL; the result lists the JavaScript exceptions, the console
errors and warnings, the browser's log errors (a resource that failed to load) and every
image with whether it decoded.

Tests call :func:`browser_or_skip` and then :func:`check_page`. Where no browser is
installed they skip with the reason, unless ``ESMM_REQUIRE_BROWSER=1`` (set by
``.ci/run``), where a missing browser fails.
"""

from __future__ import annotations

import fcntl
import json
import os
import shutil
import subprocess
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import pytest

BROWSERS = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")
FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
         "--disable-component-update", "--disable-sync", "--no-first-run", "--disable-extensions",
         "--remote-debugging-pipe")
#: JavaScript run in the page once it has loaded: every image, whether it decoded, and the text.
PROBE = ("JSON.stringify({images: Array.from(document.images).map(i => ({src: i.src.slice(0, 40), "
         "complete: i.complete, width: i.naturalWidth, height: i.naturalHeight})), "
         "title: document.title, text: document.body ? document.body.innerText : ''})")


def find_browser() -> str | None:
    for name in BROWSERS:
        path = shutil.which(name)
        if path:
            return path
    return None


def browser_or_skip() -> str:
    """The browser's path; a skip (or, with ESMM_REQUIRE_BROWSER=1, a failure) where there is none."""
    path = find_browser()
    if path is None:
        why = ("no headless browser: install Chromium from the system's packages "
               "(Debian/Ubuntu: apt-get install -y chromium) to check the HTML reports")
        if os.environ.get("ESMM_REQUIRE_BROWSER") == "1":
            pytest.fail(why + " (ESMM_REQUIRE_BROWSER=1)")
        pytest.skip(why)
    return path


@dataclass
class PageCheck:
    """What the browser met on one page."""

    title: str = ""
    text: str = ""
    images: list[dict] = field(default_factory=list)
    exceptions: list[str] = field(default_factory=list)
    console: list[str] = field(default_factory=list)   # console errors and warnings
    log: list[str] = field(default_factory=list)       # browser log entries of level error/warning

    @property
    def problems(self) -> list[str]:
        bad_images = [f"image {i['src']}... did not load" for i in self.images
                      if not (i["complete"] and i["width"] > 0 and i["height"] > 0)]
        return self.exceptions + self.console + self.log + bad_images


class _Pipe:
    """The DevTools protocol over the browser's pipe."""

    def __init__(self, proc, write_fd: int, read_fd: int):
        self.proc, self.w, self.r = proc, write_fd, read_fd
        self.buf = b""
        self.next_id = 0
        self.events: list[dict] = []

    def send(self, method: str, params: dict | None = None, session: str | None = None) -> int:
        self.next_id += 1
        msg = {"id": self.next_id, "method": method, "params": params or {}}
        if session:
            msg["sessionId"] = session
        os.write(self.w, json.dumps(msg).encode() + b"\0")
        return self.next_id

    def receive(self, deadline: float) -> dict:
        while b"\0" not in self.buf:
            if time.monotonic() > deadline:
                raise TimeoutError("the browser did not answer")
            chunk = os.read(self.r, 1 << 16)
            if not chunk:
                raise RuntimeError(f"the browser closed the pipe (exit {self.proc.poll()})")
            self.buf += chunk
        raw, _, self.buf = self.buf.partition(b"\0")
        return json.loads(raw)

    def call(self, method: str, params: dict | None = None, session: str | None = None,
             timeout: float = 60.0) -> dict:
        mid = self.send(method, params, session)
        deadline = time.monotonic() + timeout
        while True:
            msg = self.receive(deadline)
            if msg.get("id") == mid:
                if "error" in msg:
                    raise RuntimeError(f"{method}: {msg['error']}")
                return msg.get("result", {})
            self.events.append(msg)

    def wait_event(self, method: str, timeout: float = 60.0) -> dict:
        deadline = time.monotonic() + timeout
        for i, ev in enumerate(self.events):
            if ev.get("method") == method:
                return self.events.pop(i)
        while True:
            msg = self.receive(deadline)
            if msg.get("method") == method:
                return msg
            self.events.append(msg)


def check_page(path: str | os.PathLike, *, browser: str | None = None, timeout: float = 90.0) -> PageCheck:
    """Load *path* in headless Chromium; return what it met (:class:`PageCheck`)."""
    browser = browser or browser_or_skip()
    url = Path(path).resolve().as_uri()
    with tempfile.TemporaryDirectory(prefix="esmm-browser-") as profile:
        to_r, to_w = (_high(fd) for fd in os.pipe())      # we write, the browser reads (its fd 3)
        from_r, from_w = (_high(fd) for fd in os.pipe())  # the browser writes (its fd 4), we read

        def child_fds():  # in the child: its 3 and 4 survive the exec, the originals (close-on-exec) do not
            os.dup2(to_r, 3, inheritable=True)
            os.dup2(from_w, 4, inheritable=True)

        proc = subprocess.Popen([browser, *FLAGS, f"--user-data-dir={profile}", "about:blank"],
                                stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                preexec_fn=child_fds, close_fds=False)
        os.close(to_r)
        os.close(from_w)
        try:
            return _drive(_Pipe(proc, to_w, from_r), url, timeout)
        finally:
            os.close(to_w)
            os.close(from_r)
            try:
                proc.wait(timeout=15)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


def _high(fd: int) -> int:
    """*fd* moved to a number above 9, so that placing the child's 3 and 4 cannot overwrite it."""
    new = fcntl.fcntl(fd, fcntl.F_DUPFD_CLOEXEC, 10)
    os.close(fd)
    return new


def _drive(pipe: _Pipe, url: str, timeout: float) -> PageCheck:
    target = pipe.call("Target.createTarget", {"url": "about:blank"}, timeout=timeout)["targetId"]
    session = pipe.call("Target.attachToTarget", {"targetId": target, "flatten": True}, timeout=timeout)["sessionId"]
    for domain in ("Page", "Runtime", "Log"):
        pipe.call(f"{domain}.enable", session=session, timeout=timeout)
    pipe.call("Page.navigate", {"url": url}, session=session, timeout=timeout)
    pipe.wait_event("Page.loadEventFired", timeout=timeout)
    value = pipe.call("Runtime.evaluate", {"expression": PROBE, "returnByValue": True}, session=session,
                      timeout=timeout)["result"]["value"]
    page = json.loads(value)
    out = PageCheck(title=page["title"], text=page["text"], images=page["images"])
    for ev in pipe.events:
        method, params = ev.get("method"), ev.get("params", {})
        if method == "Runtime.exceptionThrown":
            det = params.get("exceptionDetails", {})
            out.exceptions.append(str(det.get("exception", {}).get("description") or det.get("text", params)))
        elif method == "Runtime.consoleAPICalled" and params.get("type") in ("error", "warning", "assert"):
            out.console.append(" ".join(str(a.get("value", a.get("description", ""))) for a in params.get("args", [])))
        elif method == "Log.entryAdded" and params.get("entry", {}).get("level") in ("error", "warning"):
            e = params["entry"]
            out.log.append(f"{e.get('source')}: {e.get('text')} {e.get('url', '')}".strip())
    try:
        pipe.call("Browser.close", timeout=10)
    except (RuntimeError, TimeoutError, OSError):
        pass
    return out
