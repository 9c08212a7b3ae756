"""A headless Chromium driven over the Chrome DevTools Protocol, to look at the live view.

The tests, ``bench/bench_view.py`` and the README's screenshot load the page in a real
browser with it: :class:`Chromium` starts ``chromium --headless --remote-debugging-port=0``
with a fresh profile, connects to the browser's DevTools WebSocket (aiohttp's client, the
library the view's server already uses), and :class:`Page` navigates, evaluates JavaScript
and takes PNG screenshots. Only the handful of protocol commands that needs is used
(``Target.createTarget`` / ``attachToTarget`` with flat sessions, ``Page.navigate``,
``Runtime.evaluate``, ``Emulation.setDeviceMetricsOverride``, ``Page.captureScreenshot``).

The browser is best-effort, like the view itself: it runs at :data:`DEFAULT_NICE` (added to
its niceness before it starts, so every process and thread it forks inherits it, and, as
root, without the capability chromium would use to put its drawing threads back at -8) and
with flags that cut its work (:data:`CHROMIUM_FLAGS`: no GPU, one raster thread, one renderer, no
background services). A page that draws only when new data arrives (the live view does)
then costs only its draws.

Command line: ``python -m clients.view.headless URL OUT.png [--wait-js EXPR]`` saves a
screenshot of a page (e.g. a running view) once ``EXPR`` is true.

Why not Playwright: its Python package drives a browser build it downloads itself, which
this project's machines cannot fetch; pointed at Debian's ``chromium`` it works, but then
pins a second protocol client (its bundled Node driver, ~100 MB) to a browser version it
does not test. The few commands above are stable parts of the protocol.
"""

from __future__ import annotations

import argparse
import asyncio
import base64
import contextlib
import itertools
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import aiohttp

#: Flags that work headless as root on a machine with no display, GPU or network, and keep
#: the browser's own work small (one raster thread, one renderer, no background features).
CHROMIUM_FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--num-raster-threads=1",
    "--renderer-process-limit=1",
    "--disable-features=Translate,MediaRouter,OptimizationHints,AutofillServerCommunication",
    "--disable-quic",
    "--no-first-run",
    "--no-default-browser-check",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--disable-extensions",
    "--disable-dev-shm-usage",
    "--hide-scrollbars",
    "--mute-audio",
)
#: Niceness added to the browser: it yields the CPU to the localiser on a shared machine.
DEFAULT_NICE = 10
_DEVTOOLS_RE = re.compile(r"DevTools listening on (ws://\S+)")


class BrowserError(RuntimeError):
    """The browser could not be started, or a protocol command failed."""


def find_chromium() -> str | None:
    """The Chromium executable: ``$SHAPELOC_CHROMIUM``, else ``chromium`` /
    ``chromium-browser`` / ``google-chrome`` on ``PATH``; ``None`` if there is none."""
    env = os.environ.get("SHAPELOC_CHROMIUM")
    if env:
        return env if Path(env).exists() or shutil.which(env) else None
    for name in ("chromium", "chromium-browser", "google-chrome"):
        path = shutil.which(name)
        if path:
            return path
    return None


class Page:
    """One tab of the browser, attached over a flat DevTools session."""

    def __init__(self, browser: Chromium, session_id: str, target_id: str) -> None:
        self.browser = browser
        self.session_id = session_id
        self.target_id = target_id

    async def send(self, method: str, params: dict[str, Any] | None = None) -> dict[str, Any]:
        """One protocol command in this tab; its result."""
        return await self.browser.send(method, params, session_id=self.session_id)

    async def navigate(self, url: str, width: int = 1400, height: int = 900) -> None:
        """Size the viewport and load ``url`` (returns once the navigation is committed)."""
        await self.send(
            "Emulation.setDeviceMetricsOverride",
            {"width": width, "height": height, "deviceScaleFactor": 1, "mobile": False},
        )
        got = await self.send("Page.navigate", {"url": url})
        if got.get("errorText"):
            raise BrowserError(f"navigating to {url}: {got['errorText']}")

    async def evaluate(self, expression: str) -> Any:
        """The value of a JavaScript expression (promises awaited), as JSON data."""
        got = await self.send(
            "Runtime.evaluate",
            {"expression": expression, "returnByValue": True, "awaitPromise": True},
        )
        if "exceptionDetails" in got:
            d = got["exceptionDetails"]
            text = (d.get("exception") or {}).get("description") or d.get("text")
            raise BrowserError(f"page script failed: {text}")
        return got.get("result", {}).get("value")

    async def wait_for(self, expression: str, timeout: float = 30.0, every: float = 0.1) -> Any:
        """Poll ``expression`` until it is truthy; its value. ``TimeoutError`` otherwise."""
        end = time.monotonic() + timeout
        while True:
            value = await self.evaluate(expression)
            if value:
                return value
            if time.monotonic() >= end:
                raise TimeoutError(f"{expression!r} still false after {timeout} s")
            await asyncio.sleep(every)

    async def screenshot(self, path: str | Path) -> Path:
        """Save the viewport as a PNG at ``path``."""
        got = await self.send("Page.captureScreenshot", {"format": "png"})
        out = Path(path)
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_bytes(base64.b64decode(got["data"]))
        return out


class Chromium:
    """A headless Chromium process and its DevTools connection (``async with`` it).

    ``executable``: default :func:`find_chromium`. ``extra_flags`` are added to
    :data:`CHROMIUM_FLAGS`. ``nice`` (0-19) is added to the browser's niceness (0: as this
    process). The profile is a fresh temporary directory, removed on close.
    """

    def __init__(
        self,
        executable: str | None = None,
        extra_flags: tuple[str, ...] = (),
        start_timeout: float = 60.0,
        nice: int = DEFAULT_NICE,
    ) -> None:
        if not 0 <= nice <= 19:
            raise ValueError(f"nice must be in 0..19, got {nice}")
        self.nice = nice
        self.executable = executable or find_chromium()
        if self.executable is None:
            raise BrowserError("no chromium found (apt-get install chromium)")
        self.extra_flags = extra_flags
        self.start_timeout = start_timeout
        self.proc: subprocess.Popen[bytes] | None = None
        self._profile: tempfile.TemporaryDirectory[str] | None = None
        self._http: aiohttp.ClientSession | None = None
        self._ws: aiohttp.ClientWebSocketResponse | None = None
        self._reader: asyncio.Task[None] | None = None
        self._ids = itertools.count(1)
        self._pending: dict[int, asyncio.Future[dict[str, Any]]] = {}
        self.log_lines: list[str] = []

    @property
    def pid(self) -> int | None:
        """The browser's process id (its renderers are its children)."""
        return None if self.proc is None else self.proc.pid

    async def start(self) -> None:
        """Start the browser and connect to its DevTools WebSocket."""
        self._profile = tempfile.TemporaryDirectory(prefix="shapeloc-chromium-")
        cmd = [
            str(self.executable),
            *CHROMIUM_FLAGS,
            *self.extra_flags,
            f"--user-data-dir={self._profile.name}",
            "--remote-debugging-address=127.0.0.1",
            "--remote-debugging-port=0",
            "about:blank",
        ]
        self.proc = subprocess.Popen(
            [*self._lowered(), *cmd],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            start_new_session=True,
        )
        url = await asyncio.get_running_loop().run_in_executor(None, self._devtools_url)
        self._http = aiohttp.ClientSession()
        self._ws = await self._http.ws_connect(url, max_msg_size=0)
        self._reader = asyncio.create_task(self._read())

    def _lowered(self) -> list[str]:
        """The command prefix that starts the browser ``nice``-d and unable to undo it.

        Chromium sets the niceness of its threads itself (0, and -8 for the ones that draw:
        browser UI, compositors, IO), which as root it may: the nice it was started with is
        then lost. So, as root, ``setpriv`` first drops the capability to raise a priority
        (CAP_SYS_NICE) from what the browser may ever hold; its own calls then fail and every
        thread keeps the niceness it inherited. ``nice`` and ``setpriv`` exec the next
        command: the process started is the browser itself."""
        if not self.nice:
            return []
        nice, setpriv = shutil.which("nice"), shutil.which("setpriv")
        if nice is None:
            self.log_lines.append("headless: no nice(1): the browser runs at normal priority")
            return []
        out = [nice, "-n", str(self.nice)]
        if os.geteuid() == 0:
            if setpriv is None:
                self.log_lines.append("headless: no setpriv(1): chromium may raise its priority")
            else:
                out += [setpriv, "--inh-caps=-sys_nice", "--bounding-set=-sys_nice"]
        return out

    def _devtools_url(self) -> str:
        assert self.proc is not None and self.proc.stderr is not None
        end = time.monotonic() + self.start_timeout
        while time.monotonic() < end:
            line = self.proc.stderr.readline()
            if not line:
                break
            text = line.decode(errors="replace").rstrip()
            self.log_lines.append(text)
            m = _DEVTOOLS_RE.search(text)
            if m:
                # keep reading stderr in the background so the browser never blocks on it
                threading.Thread(target=self._drain_stderr, daemon=True).start()
                return m.group(1)
        raise BrowserError(
            "chromium did not print its DevTools address:\n" + "\n".join(self.log_lines[-20:])
        )

    def _drain_stderr(self) -> None:
        assert self.proc is not None and self.proc.stderr is not None
        for line in self.proc.stderr:
            if len(self.log_lines) < 2000:
                self.log_lines.append(line.decode(errors="replace").rstrip())

    async def _read(self) -> None:
        assert self._ws is not None
        async for msg in self._ws:
            if msg.type != aiohttp.WSMsgType.TEXT:
                continue
            data = json.loads(msg.data)
            fut = self._pending.pop(data.get("id", -1), None)
            if fut is None or fut.done():
                continue
            if "error" in data:
                fut.set_exception(BrowserError(f"{data['error']}"))
            else:
                fut.set_result(data.get("result", {}))
        for fut in self._pending.values():
            if not fut.done():
                fut.set_exception(BrowserError("the DevTools connection closed"))

    async def send(
        self,
        method: str,
        params: dict[str, Any] | None = None,
        *,
        session_id: str | None = None,
        timeout: float = 30.0,
    ) -> dict[str, Any]:
        """One protocol command (browser-wide, or in ``session_id``); its result."""
        if self._ws is None:
            raise BrowserError("not started")
        mid = next(self._ids)
        msg: dict[str, Any] = {"id": mid, "method": method, "params": params or {}}
        if session_id is not None:
            msg["sessionId"] = session_id
        fut: asyncio.Future[dict[str, Any]] = asyncio.get_running_loop().create_future()
        self._pending[mid] = fut
        await self._ws.send_str(json.dumps(msg))
        return await asyncio.wait_for(fut, timeout)

    async def new_page(self) -> Page:
        """A new tab (blank), attached."""
        target = await self.send("Target.createTarget", {"url": "about:blank"})
        tid = target["targetId"]
        att = await self.send("Target.attachToTarget", {"targetId": tid, "flatten": True})
        return Page(self, att["sessionId"], tid)

    async def close(self) -> None:
        """Close the browser (politely, then by force) and remove its profile."""
        with contextlib.suppress(Exception):
            if self._ws is not None and not self._ws.closed:
                await asyncio.wait_for(self.send("Browser.close", timeout=5.0), 5.0)
        if self._reader is not None:
            self._reader.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await self._reader
        if self._ws is not None:
            await self._ws.close()
        if self._http is not None:
            await self._http.close()
        if self.proc is not None:
            try:
                self.proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait(timeout=5)
        if self._profile is not None:
            with contextlib.suppress(OSError):
                self._profile.cleanup()

    async def __aenter__(self) -> Chromium:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()


async def screenshot(
    url: str,
    out: str | Path,
    *,
    wait_js: str = "true",
    settle_s: float = 0.0,
    width: int = 1400,
    height: int = 900,
    timeout: float = 60.0,
) -> Path:
    """Load ``url`` headless, wait until ``wait_js`` is true (and ``settle_s`` more), save
    a PNG screenshot at ``out``."""
    async with Chromium() as browser:
        page = await browser.new_page()
        await page.navigate(url, width, height)
        await page.wait_for(wait_js, timeout)
        await asyncio.sleep(settle_s)
        return await page.screenshot(out)


if __name__ == "__main__":
    ap = argparse.ArgumentParser(prog="python -m clients.view.headless", description=__doc__)
    ap.add_argument("url")
    ap.add_argument("out", type=Path)
    ap.add_argument("--wait-js", default="window.shapelocView && window.shapelocView.frames > 5")
    ap.add_argument("--settle", type=float, default=0.5, help="seconds after --wait-js")
    ap.add_argument("--width", type=int, default=1400)
    ap.add_argument("--height", type=int, default=900)
    a = ap.parse_args()
    try:
        path = asyncio.run(
            screenshot(
                a.url, a.out, wait_js=a.wait_js, settle_s=a.settle, width=a.width, height=a.height
            )
        )
    except (BrowserError, TimeoutError) as exc:
        print(f"headless: {exc}", file=sys.stderr)
        sys.exit(1)
    print(path)
