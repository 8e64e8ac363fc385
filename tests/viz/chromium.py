"""Headless Chromium driven over the DevTools protocol (aiohttp websocket), for the report tests.

``render(url, png)`` loads a page in a fresh profile, records console errors, uncaught exceptions,
log errors and every network request, runs optional JavaScript, and saves a full-page screenshot.
"""

from __future__ import annotations

import asyncio
import base64
import json
import os
import re
import shutil
import subprocess
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
         "--disable-component-update", "--disable-sync", "--no-first-run", "--no-default-browser-check",
         "--disable-extensions", "--mute-audio", "--hide-scrollbars", "--remote-debugging-port=0"]


def chromium_binary() -> str | None:
    for name in ("chromium", "chromium-browser", "google-chrome", "chrome"):
        path = shutil.which(name)
        if path:
            return path
    return None


@dataclass
class PageResult:
    errors: list[str] = field(default_factory=list)  # console errors, exceptions, log errors
    requests: list[str] = field(default_factory=list)  # every URL the page asked for
    values: dict = field(default_factory=dict)  # results of the evaluated expressions
    png: Path | None = None


class _Cdp:
    def __init__(self, ws) -> None:
        self.ws, self.next_id, self.pending, self.events = ws, 0, {}, asyncio.Queue()

    async def pump(self) -> None:
        async for msg in self.ws:
            body = json.loads(msg.data)
            if "id" in body and body["id"] in self.pending:
                self.pending.pop(body["id"]).set_result(body)
            else:
                await self.events.put(body)

    async def call(self, method: str, params: dict | None = None, session: str | None = None, timeout: float = 60.0):
        self.next_id += 1
        fut = asyncio.get_running_loop().create_future()
        self.pending[self.next_id] = fut
        msg = {"id": self.next_id, "method": method, "params": params or {}}
        if session:
            msg["sessionId"] = session
        await self.ws.send_str(json.dumps(msg))
        body = await asyncio.wait_for(fut, timeout)
        if "error" in body:
            raise RuntimeError(f"{method}: {body['error']}")
        return body.get("result", {})


async def _render(url: str, png: Path, width: int, scripts: dict, settle_s: float, ws_url: str) -> PageResult:
    import aiohttp

    out = PageResult()
    async with aiohttp.ClientSession() as http:
        async with http.ws_connect(ws_url, max_msg_size=0) as ws:
            cdp = _Cdp(ws)
            pump = asyncio.create_task(cdp.pump())
            target = (await cdp.call("Target.createTarget", {"url": "about:blank"}))["targetId"]
            sid = (await cdp.call("Target.attachToTarget", {"targetId": target, "flatten": True}))["sessionId"]
            for domain in ("Page", "Runtime", "Log", "Network"):
                await cdp.call(f"{domain}.enable", session=sid)
            await cdp.call("Emulation.setDeviceMetricsOverride",
                           {"width": width, "height": 900, "deviceScaleFactor": 1, "mobile": False}, session=sid)
            await cdp.call("Page.navigate", {"url": url}, session=sid)

            loaded = False
            deadline = time.monotonic() + 60.0

            def collect(ev: dict) -> None:
                nonlocal loaded
                m, p = ev.get("method"), ev.get("params", {})
                if m == "Page.loadEventFired":
                    loaded = True
                elif m == "Runtime.exceptionThrown":
                    d = p.get("exceptionDetails", {})
                    out.errors.append(f"exception: {d.get('text')} {d.get('exception', {}).get('description', '')}")
                elif m == "Runtime.consoleAPICalled" and p.get("type") in ("error", "assert"):
                    out.errors.append("console.error: " + " ".join(str(a.get("value", a.get("description")))
                                                                for a in p.get("args", [])))
                elif m == "Log.entryAdded" and p.get("entry", {}).get("level") == "error":
                    out.errors.append(f"log: {p['entry'].get('text')} ({p['entry'].get('url', '')})")
                elif m == "Network.requestWillBeSent":
                    out.requests.append(p["request"]["url"])

            while not loaded and time.monotonic() < deadline:
                try:
                    collect(await asyncio.wait_for(cdp.events.get(), 1.0))
                except asyncio.TimeoutError:
                    pass
            if not loaded:
                out.errors.append("page did not finish loading in 60 s")
            await asyncio.sleep(settle_s)
            for name, expr in scripts.items():
                res = await cdp.call("Runtime.evaluate", {"expression": expr, "returnByValue": True,
                                                          "awaitPromise": True}, session=sid)
                if "exceptionDetails" in res:
                    out.errors.append(f"evaluate {name}: {res['exceptionDetails'].get('text')}")
                out.values[name] = res.get("result", {}).get("value")
            height = (await cdp.call("Runtime.evaluate", {"expression": "document.documentElement.scrollHeight",
                                                          "returnByValue": True}, session=sid))["result"]["value"]
            await cdp.call("Emulation.setDeviceMetricsOverride",
                           {"width": width, "height": int(height), "deviceScaleFactor": 1, "mobile": False}, session=sid)
            await asyncio.sleep(settle_s)
            shot = await cdp.call("Page.captureScreenshot", {"format": "png", "captureBeyondViewport": True},
                                  session=sid)
            png.write_bytes(base64.b64decode(shot["data"]))
            out.png = png
            while not cdp.events.empty():
                collect(cdp.events.get_nowait())
            await cdp.call("Browser.close")
            pump.cancel()
    return out


def render(url: str, png: Path, *, width: int = 1280, scripts: dict | None = None, settle_s: float = 1.0) -> PageResult:
    """Load ``url`` in headless Chromium with a fresh profile; see the module docstring."""
    binary = chromium_binary()
    if binary is None:
        raise FileNotFoundError("no chromium binary on PATH")
    profile = tempfile.mkdtemp(prefix="blockloc-chromium-")
    proc = subprocess.Popen([binary, *FLAGS, f"--user-data-dir={profile}", "about:blank"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "HOME": profile})
    try:
        ws_url = None
        t0 = time.monotonic()
        while ws_url is None and time.monotonic() - t0 < 60.0:
            line = proc.stderr.readline()
            if not line and proc.poll() is not None:
                raise RuntimeError(f"chromium exited with code {proc.returncode}")
            m = re.search(r"DevTools listening on (ws://\S+)", line)
            if m:
                ws_url = m.group(1)
        if ws_url is None:
            raise RuntimeError("chromium did not print its DevTools address in 60 s")
        # Keep reading its stderr so a chatty browser never blocks on a full pipe.
        threading.Thread(target=lambda: [None for _ in proc.stderr], daemon=True).start()
        return asyncio.run(_render(url, png, width, scripts or {}, settle_s, ws_url))
    finally:
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        shutil.rmtree(profile, ignore_errors=True)
