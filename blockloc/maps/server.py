"""``blockloc map serve``: a read-only HTTP server for a map store (or a directory of stores).

Built on aiohttp. Serves GET and HEAD of regular files inside the root directory and nothing
else (other methods get 405):

* path safety: every URL path segment is percent-decoded on its own; ``.``/``..``, NUL,
  backslashes and hidden names (``.x``; except the ``.incomplete`` build marker) give 404; a path
  that resolves (through symlinks) outside the root gives 403;
* aiohttp's ``FileResponse`` gives ``ETag`` / ``Last-Modified`` with conditional GET (304),
  ``Range`` (206) and ``HEAD``; responses carry ``Cache-Control: no-cache`` so clients revalidate;
* a directory answers with a small HTML index of its files (what static servers do, and what
  fsspec's HTTP file system reads to list a directory).

:class:`MapServer` runs the server on its own thread and event loop (tests, benchmarks);
:func:`serve` runs it in the foreground until SIGINT/SIGTERM (the CLI).
"""

from __future__ import annotations

import asyncio
import html
import logging
import os
import signal
import threading
from pathlib import Path
from urllib.parse import quote, unquote

from blockloc.errors import MapError

log = logging.getLogger(__name__)

_ALLOWED_HIDDEN = {".incomplete"}  # blockloc.maps.store.INCOMPLETE_MARKER


def check_root(path: str | Path) -> tuple[Path, list[str]]:
    """(resolved root, relative paths of the map stores in it: "" for the root itself).

    MapError when ``path`` is not a directory or holds no map store (itself or one level down).
    """
    root = Path(path)
    if not root.exists():
        raise MapError(f"{path}: no such map directory")
    if not root.is_dir():
        raise MapError(f"{path}: not a directory (expected a map store directory)")
    root = root.resolve()

    def is_store(d: Path) -> bool:
        return (d / "manifest.json").is_file() or (d / "CentroidCloud.pcd").is_file()

    if is_store(root):
        return root, [""]
    stores = sorted(d.name for d in root.iterdir()
                    if d.is_dir() and not d.name.startswith(".") and is_store(d))
    if not stores:
        raise MapError(f"{path}: not a map store, nor a directory of map stores (no manifest.json)")
    return root, stores


def _resolve(root: Path, raw_path: str) -> tuple[int, Path | None]:
    """(status, file system path) of a raw (still percent-encoded) URL path under ``root``.

    status 200: inside the root (may not exist); 404: a forbidden name; 403: escapes the root.
    """
    raw_path = raw_path.split("?", 1)[0].split("#", 1)[0]
    parts = []
    for seg in raw_path.split("/"):
        if not seg:
            continue  # '//' and the leading '/': a path is always taken relative to the root
        name = unquote(seg, errors="strict") if "%" in seg else seg
        if name in (".", "..") or "/" in name or "\\" in name or "\x00" in name:
            return 404, None
        if name.startswith(".") and name not in _ALLOWED_HIDDEN:
            return 404, None
        parts.append(name)
    target = root.joinpath(*parts)
    real = Path(os.path.realpath(target))
    if real != root and root not in real.parents:
        return 403, None
    return 200, real


def make_app(root: str | Path):
    """The aiohttp application serving ``root`` (an existing directory) read-only."""
    from aiohttp import web

    root = Path(root).resolve()
    extra_headers = {"Cache-Control": "no-cache", "X-Content-Type-Options": "nosniff"}

    async def handle(request: web.Request) -> web.StreamResponse:
        try:
            status, path = _resolve(root, request.raw_path)
        except UnicodeDecodeError:
            status, path = 404, None
        if status == 403:
            log.warning("refused %s %s: outside the served directory", request.method, request.raw_path)
            raise web.HTTPForbidden(text="403: outside the served directory\n")
        if path is None or not path.exists():
            raise web.HTTPNotFound(text="404: not found\n")
        if path.is_dir():
            return web.Response(text=_index_html(root, path), content_type="text/html",
                                headers=extra_headers)
        if not path.is_file():
            raise web.HTTPForbidden(text="403: not a regular file\n")
        return web.FileResponse(path, headers=extra_headers)

    app = web.Application()
    app.router.add_get("/{tail:.*}", handle)  # also answers HEAD; other methods get 405
    return app


def _index_html(root: Path, directory: Path) -> str:
    rel = directory.relative_to(root).as_posix()
    base = "/" if rel == "." else f"/{quote(rel)}/"
    rows = []
    for p in sorted(directory.iterdir()):
        if p.name.startswith(".") and p.name not in _ALLOWED_HIDDEN:
            continue
        real = Path(os.path.realpath(p))
        if real != root and root not in real.parents:
            continue  # a symlink escaping the root is not listed either
        slash = "/" if p.is_dir() else ""
        rows.append(f'<a href="{base}{quote(p.name)}{slash}">{html.escape(p.name)}{slash}</a><br>')
    title = html.escape(base)
    return (f"<!DOCTYPE html><html><head><title>{title}</title></head><body><h1>{title}</h1>\n"
            + "\n".join(rows) + "\n</body></html>\n")


class MapServer:
    """The server on a background thread::

        with MapServer(map_dir) as srv:      # port 0: a free port is chosen
            store = open_map(srv.url)

    ``url``: ``http://host:port`` (no trailing slash). ``stop()`` closes the listening socket and
    open connections and joins the thread; ``start()`` may be called again afterwards (on the same
    port when it was chosen), which tests use to kill and revive a server.
    """

    def __init__(self, root: str | Path, host: str = "127.0.0.1", port: int = 0):
        self.root, self.stores = check_root(root)
        self.host = host
        self.port = port
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._runner = None
        self._stopped: asyncio.Event | None = None

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}"

    def start(self, timeout_s: float = 10.0) -> str:
        """Start serving; returns :attr:`url`. MapError when the port cannot be bound."""
        if self._thread is not None:
            return self.url
        ready = threading.Event()
        failure: list[BaseException] = []
        self._thread = threading.Thread(target=self._run, args=(ready, failure),
                                        name=f"map-server-{self.port}", daemon=True)
        self._thread.start()
        if not ready.wait(timeout_s):
            raise MapError(f"{self.url}: the map server did not start within {timeout_s} s")
        if failure:
            self._thread.join(timeout_s)
            self._thread = None
            raise MapError(f"{self.host}:{self.port}: cannot serve ({failure[0]})")
        return self.url

    def _run(self, ready: threading.Event, failure: list) -> None:
        loop = asyncio.new_event_loop()
        self._loop = loop
        try:
            loop.run_until_complete(self._main(ready, failure))
        finally:
            loop.close()
            self._loop = None

    async def _main(self, ready: threading.Event, failure: list) -> None:
        from aiohttp import web

        self._stopped = asyncio.Event()
        runner = web.AppRunner(make_app(self.root), access_log=None, shutdown_timeout=2.0)
        try:
            await runner.setup()
            site = web.TCPSite(runner, self.host, self.port, reuse_address=True)
            await site.start()
        except OSError as exc:
            failure.append(exc)
            await runner.cleanup()
            ready.set()
            return
        self.port = runner.addresses[0][1]
        self._runner = runner
        ready.set()
        await self._stopped.wait()
        await runner.cleanup()

    def stop(self, timeout_s: float = 10.0) -> None:
        """Stop serving and join the thread (no-op when not running)."""
        thread, loop = self._thread, self._loop
        if thread is None:
            return
        if loop is not None and self._stopped is not None:
            try:
                loop.call_soon_threadsafe(self._stopped.set)
            except RuntimeError:
                pass  # loop already closed
        thread.join(timeout_s)
        self._thread = None

    def __enter__(self) -> "MapServer":
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()


def serve(root: str | Path, host: str = "127.0.0.1", port: int = 8765,
          on_ready=None) -> int:
    """Serve ``root`` in the foreground until SIGINT or SIGTERM, then shut down cleanly; returns
    the signal's number (the CLI exits 128 + it, as every command stopped by a signal does).

    ``on_ready(url, stores)`` is called once listening (the CLI prints the URLs there).
    """
    server = MapServer(root, host, port)
    done = threading.Event()
    previous = {}
    received = []

    def _stop(signum, frame) -> None:
        received.append(signum)
        done.set()

    for sig in (signal.SIGINT, signal.SIGTERM):
        previous[sig] = signal.signal(sig, _stop)
    try:
        server.start()
        if host not in ("127.0.0.1", "localhost", "::1"):
            log.warning("serving %s on %s: reachable from other machines", server.root, host)
        if on_ready is not None:
            on_ready(server.url, server.stores)
        while not done.wait(0.5):
            if server._thread is None or not server._thread.is_alive():
                raise MapError(f"{server.url}: the map server stopped unexpectedly")
    finally:
        server.stop()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        log.info("map server on %s stopped", server.url)
    return received[0]
