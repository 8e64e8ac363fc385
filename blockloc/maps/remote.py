"""Map stores over HTTP(S) and object storage, with a checksum-validated on-disk cache.

:class:`RemoteMapFiles` has the interface of :class:`blockloc.maps.files.MapFiles` (``url``,
``read_bytes``, ``exists``, ``is_dir``, ``list_names``) for ``http(s)://`` and ``s3://`` URLs (any
fsspec protocol works; s3 needs the ``s3fs`` package). Every byte goes through fsspec; nothing
here opens a socket itself.

* **Cache.** When the manifest is read, the expected sha256 of every entry file is remembered; a
  later read of that file looks in a :class:`TileCache` first (content addressed: the key is the
  sha256, so maps and servers holding the same tile share it). Cached files are re-hashed on every
  read; a corrupt one is dropped and fetched again. The cache is bounded in bytes (least recently
  used goes first) and written atomically (temporary file, then rename), so several processes may
  share one directory.
* **Faults.** Each request has a timeout; a failed request (connection refused or reset, timeout,
  5xx) is retried with exponential backoff and jitter; a download whose sha256 does not match the
  manifest counts as a failed attempt and is fetched again. When every try fails the caller gets
  one :class:`~blockloc.errors.MapError` naming the URL and the last cause. The instance then
  counts the server as *offline*: later reads make a single attempt without waiting (so a
  prefetch thread is never stuck in backoff) until one succeeds, which resets the state.
* **Offline start.** The last manifest read from a URL is kept in the cache directory; when the
  server cannot be reached the store opens from it (a warning says so) and reads whatever tiles
  are cached.

Instances are thread-safe: the map provider's prefetch thread and the tracker may read at once;
concurrent reads of the same file share one download.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import random
import re
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any, Callable, TypeVar

from blockloc.cache import cache_root
from blockloc.errors import MapError
from blockloc.fileio import atomic_path, atomic_write_bytes

log = logging.getLogger(__name__)

MANIFEST_NAME = "manifest.json"  # == blockloc.maps.store.MANIFEST_NAME (store imports this module)
DEFAULT_CACHE_BYTES = 2 * 1024**3
_SHA256 = re.compile(r"^[0-9a-f]{64}$")
_T = TypeVar("_T")


def default_cache_dir() -> Path:
    """``$BLOCKLOC_MAP_CACHE``, else ``<$BLOCKLOC_CACHE or ~/.cache/blockloc>/remote-maps``."""
    env = os.environ.get("BLOCKLOC_MAP_CACHE")
    return Path(env).expanduser() if env else cache_root() / "remote-maps"


def is_url(url_or_path: str | os.PathLike) -> bool:
    """True for ``scheme://...`` other than ``file://``."""
    s = str(url_or_path)
    return "://" in s and not s.startswith("file://")


# ----------------------------------------------------------------------------- cache


class TileCache:
    """Content-addressed, size-bounded on-disk cache of map files, keyed by sha256.

    Layout: ``root/ab/abcdef...`` (the full hex digest, under its first two characters). Least
    recently used entries are evicted once the total exceeds ``max_bytes``; recency survives
    restarts through the files' mtimes. Every :meth:`get` re-hashes the file and drops it when it
    no longer matches its name. Thread-safe; several processes may share ``root`` (writes are
    atomic renames; each process keeps its own size account, so the bound is per process).
    """

    def __init__(self, root: str | Path, max_bytes: int = DEFAULT_CACHE_BYTES):
        if max_bytes < 0:
            raise MapError(f"map cache size {max_bytes}: expected >= 0 bytes")
        self.root = Path(root)
        self.max_bytes = int(max_bytes)
        self._lock = threading.Lock()
        self._index: OrderedDict[str, int] = OrderedDict()  # sha -> size, oldest first
        self._bytes = 0
        self.corrupt_dropped = 0
        try:
            self.root.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise MapError(f"{self.root}: cannot create the map cache directory ({exc})") from None
        self._scan()

    def _scan(self) -> None:
        found = []
        for sub in self.root.iterdir():
            if not (sub.is_dir() and len(sub.name) == 2):
                continue
            for p in sub.iterdir():
                if _SHA256.match(p.name):
                    try:
                        st = p.stat()
                    except OSError:
                        continue
                    found.append((st.st_mtime_ns, p.name, st.st_size))
        for _, sha, size in sorted(found):
            self._index[sha] = size
            self._bytes += size
        self._evict()

    def _path(self, sha256: str) -> Path:
        if not _SHA256.match(sha256):
            raise ValueError(f"not a lowercase hex sha256: {sha256!r}")
        return self.root / sha256[:2] / sha256

    @property
    def bytes_used(self) -> int:
        """Bytes of the entries this process knows of."""
        return self._bytes

    def __len__(self) -> int:
        return len(self._index)

    def __contains__(self, sha256: str) -> bool:
        return sha256 in self._index

    def get(self, sha256: str) -> bytes | None:
        """The cached bytes whose sha256 is ``sha256``, or None (absent, or corrupt: dropped)."""
        path = self._path(sha256)
        try:
            data = path.read_bytes()
        except OSError:  # absent, or evicted by another process
            with self._lock:
                if not path.exists():  # (not re-added by a put meanwhile)
                    self._forget(sha256)
            return None
        if hashlib.sha256(data).hexdigest() != sha256:
            log.warning("%s: cached map file is corrupt; dropped, it will be fetched again", path)
            with self._lock:
                self.corrupt_dropped += 1
                self._forget(sha256)
            _unlink(path)
            return None
        with self._lock:
            if sha256 not in self._index:
                # Written by another process, or evicted by another thread since the read: only a
                # file still on disk counts (else the account would exceed what the disk holds).
                if not path.exists():
                    return data
                self._index[sha256] = len(data)
                self._bytes += len(data)
                self._evict()
            if sha256 in self._index:
                self._index.move_to_end(sha256)
        try:
            os.utime(path)  # recency for the next process that scans
        except OSError:
            pass
        return data

    def put(self, sha256: str, data: bytes) -> bool:
        """Store ``data`` (whose sha256 the caller has verified) atomically; False when too big."""
        if len(data) > self.max_bytes:
            return False
        path = self._path(sha256)
        try:
            # the rename and the index change under one lock (eviction unlinks)
            with self._lock:
                with atomic_path(path) as tmp:
                    tmp.write_bytes(data)
                self._forget(sha256)
                self._index[sha256] = len(data)
                self._bytes += len(data)
                self._evict()
        except OSError as exc:
            log.warning("%s: cannot write to the map cache (%s)", path, exc)
            return False
        return True

    def clear(self) -> None:
        with self._lock:
            for sha in list(self._index):
                _unlink(self._path(sha))
            self._index.clear()
            self._bytes = 0

    def _forget(self, sha256: str) -> None:
        size = self._index.pop(sha256, None)
        if size is not None:
            self._bytes -= size

    def _evict(self) -> None:
        while self._bytes > self.max_bytes and self._index:
            sha, size = self._index.popitem(last=False)
            self._bytes -= size
            _unlink(self._path(sha))


def _unlink(path: Path) -> None:
    try:
        path.unlink()
    except OSError:
        pass


# ----------------------------------------------------------------------------- remote files


@dataclass(frozen=True)
class RetryPolicy:
    """Per-request timeout and retry schedule.

    timeout_s: limit of one request (connect + transfer), seconds. retries: further attempts after
    the first. Attempt k (k >= 1) waits ``min(backoff_max_s, backoff_s * 2**(k-1))`` seconds, times
    a random factor in [0.5, 1] so that many robots do not retry in step.
    """

    timeout_s: float = 10.0
    retries: int = 3
    backoff_s: float = 0.25
    backoff_max_s: float = 4.0

    def __post_init__(self) -> None:
        if self.timeout_s <= 0 or self.retries < 0 or self.backoff_s < 0 or self.backoff_max_s < 0:
            raise MapError(f"retry policy {self}: expected timeout > 0, retries >= 0, backoff >= 0")

    def delay(self, attempt: int, rng: random.Random) -> float:
        return min(self.backoff_max_s, self.backoff_s * 2 ** (attempt - 1)) * rng.uniform(0.5, 1.0)


@dataclass
class RemoteStats:
    """Counters of one :class:`RemoteMapFiles` (a snapshot; see ``RemoteMapFiles.stats``)."""

    requests: int = 0          # requests sent (all attempts)
    fetched_files: int = 0     # successful downloads
    fetched_bytes: int = 0
    cache_hits: int = 0        # entry files served from the on-disk cache
    cache_misses: int = 0      # entry files with a known sha256 that had to be fetched
    retries: int = 0           # attempts after a failed one
    corrupt_downloads: int = 0  # downloads whose sha256 did not match the manifest
    failures: int = 0          # calls that raised MapError after all tries
    offline_manifest: int = 0  # manifest answered from the cached copy

    @property
    def hit_rate(self) -> float:
        n = self.cache_hits + self.cache_misses
        return self.cache_hits / n if n else 0.0


class _Corrupt(Exception):
    pass


class _Flight:
    """One download in progress, shared by the threads asking for the same file."""

    def __init__(self) -> None:
        self.done = threading.Event()
        self.data: bytes | None = None
        self.error: BaseException | None = None


def _is_permanent(exc: BaseException) -> bool:
    """Refusals worth no retry: PermissionError, and 4xx other than 404 (handled apart), 408, 429."""
    if isinstance(exc, PermissionError):
        return True
    status = getattr(exc, "status", None)  # aiohttp.ClientResponseError
    if status is None:
        response = getattr(exc, "response", None)  # botocore ClientError
        if isinstance(response, dict):
            status = response.get("ResponseMetadata", {}).get("HTTPStatusCode")
    return isinstance(status, int) and 400 <= status < 500 and status not in (408, 429)


_TRANSPORT_MODULES = ("aiohttp", "botocore", "aiobotocore", "s3fs", "fsspec", "urllib3", "requests")


def _is_transport_error(exc: BaseException) -> bool:
    """Errors of the network stack (worth classifying and retrying), as opposed to bugs."""
    if isinstance(exc, (OSError, TimeoutError, EOFError)):
        return True
    return any(c.__module__.split(".")[0] in _TRANSPORT_MODULES for c in type(exc).__mro__)


def _describe(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


class RemoteMapFiles:
    """Read-only access to the files of a store at a URL (``http(s)://``, ``s3://``, ...).

    Same interface as :class:`blockloc.maps.files.MapFiles`. ``cache_dir``: directory of the
    shared :class:`TileCache` (None: :func:`default_cache_dir`; False: no cache); ``cache_bytes``:
    its bound. ``storage_options``: extra fsspec options (e.g. ``{"client_kwargs":
    {"endpoint_url": ...}}`` for an S3-compatible server; ``AWS_ENDPOINT_URL`` works too).
    """

    is_remote = True

    def __init__(self, url: str, *, cache_dir: str | Path | None | bool = None,
                 cache_bytes: int = DEFAULT_CACHE_BYTES, retry: RetryPolicy | None = None,
                 storage_options: dict[str, Any] | None = None, seed: int | None = None):
        if not is_url(url):
            raise MapError(f"{url}: not a URL (expected http://, https:// or s3://...)")
        self.root = str(url).rstrip("/")
        self.retry = retry or RetryPolicy()
        self._fs, self._fs_root = _make_fs(self.root, self.retry, storage_options or {})
        self._protocol = self.root.split("://", 1)[0].lower()
        if cache_dir is False:
            self.cache: TileCache | None = None
            self._manifest_copy: Path | None = None
        else:
            cdir = default_cache_dir() if cache_dir in (None, True) else Path(cache_dir)
            self.cache = TileCache(cdir, cache_bytes)
            key = hashlib.sha256(self.root.encode()).hexdigest()[:32]
            self._manifest_copy = cdir / "manifests" / f"{key}.json"
        self._lock = threading.Lock()
        self._expected: dict[str, str] = {}  # file name -> sha256, from the manifest
        self._flights: dict[str, _Flight] = {}
        self._stats = RemoteStats()
        self._offline = False
        self._rng = random.Random(seed)

    # -- the MapFiles interface -------------------------------------------------------------

    def __repr__(self) -> str:
        return f"RemoteMapFiles({self.root!r})"

    def url(self, name: str) -> str:
        """Full URL of a file of the store (for messages)."""
        return f"{self.root}/{name}"

    def read_bytes(self, name: str) -> bytes:
        """Bytes of ``name``: from the cache when its sha256 is known and cached, else fetched.

        MapError when the file is missing, or when every try failed (unreachable server,
        timeouts, checksum mismatches).
        """
        self._check_name(name)
        if name == MANIFEST_NAME:
            return self._read_manifest()
        sha = self._expected.get(name)
        if sha is not None and self.cache is not None:
            data = self.cache.get(sha)
            with self._lock:
                if data is not None:
                    self._stats.cache_hits += 1
                    return data
                self._stats.cache_misses += 1
        return self._shared_fetch(name, sha)

    def exists(self, name: str) -> bool:
        """Whether ``name`` exists; answered from the cached manifest when the server is down."""
        self._check_name(name)
        try:
            return self._with_retries(self.url(name), lambda: self._remote_exists(name))
        except MapError:
            manifest = self._cached_manifest()
            try:
                names = _manifest_files(manifest) if manifest is not None else None
            except ValueError:  # also a JSON decode error: an unusable copy
                names = None
            if names is None:
                raise
            log.warning("%s: server unreachable; answering from the cached manifest", self.url(name))
            return name == MANIFEST_NAME or name in names

    def is_dir(self) -> bool:
        """True when the URL holds a manifest (or lists as a directory)."""
        if self.exists(MANIFEST_NAME):
            return True
        return bool(self._with_retries(self.root, lambda: self._fs.isdir(self._fs_root)))

    def list_names(self) -> list[str]:
        """Names of the files directly at the URL (HTTP: the links of its index page)."""
        listing = self._with_retries(self.root, lambda: self._fs.ls(self._fs_root, detail=False))
        root = self._fs_root.rstrip("/")
        names = set()
        for p in listing:
            p = str(p).rstrip("/")
            if p.startswith(root + "/") and "/" not in p[len(root) + 1:]:
                names.add(p[len(root) + 1:])
        return sorted(names)

    # -- extras ------------------------------------------------------------------------------

    @property
    def stats(self) -> RemoteStats:
        """A copy of the counters."""
        with self._lock:
            return RemoteStats(**{f.name: getattr(self._stats, f.name) for f in fields(RemoteStats)})

    @property
    def online(self) -> bool:
        """False after a call failed on every try, until the next success."""
        return not self._offline

    def expect(self, name: str, sha256: str) -> None:
        """Record the sha256 of ``name`` (done automatically for the files of the manifest)."""
        if _SHA256.match(sha256 or ""):
            with self._lock:
                self._expected[name] = sha256

    # -- internals ---------------------------------------------------------------------------

    def _check_name(self, name: str) -> None:
        parts = name.split("/")
        if not name or name.startswith("/") or "\\" in name or any(p in ("", ".", "..") for p in parts):
            raise MapError(f"{self.root}: file name {name!r} is not a plain relative name")

    def _path(self, name: str) -> str:
        return f"{self._fs_root.rstrip('/')}/{name}"

    def _read_manifest(self) -> bytes:
        try:
            data = self._shared_fetch(MANIFEST_NAME, None)
        except MapError as exc:
            cached = self._cached_manifest()
            if cached is None or "missing map file" in str(exc):
                raise
            log.warning("%s; opening the map from the manifest cached at %s", exc, self._manifest_copy)
            with self._lock:
                self._stats.offline_manifest += 1
            data = cached
        else:
            self._save_manifest(data)
        try:
            for file, sha in _manifest_files(data).items():
                self.expect(file, sha)
        except ValueError:
            pass  # not a manifest we understand: the store's parser names the problem
        return data

    def _cached_manifest(self) -> bytes | None:
        if self._manifest_copy is None:
            return None
        try:
            return self._manifest_copy.read_bytes()
        except OSError:
            return None

    def _save_manifest(self, data: bytes) -> None:
        if self._manifest_copy is None:
            return
        try:
            atomic_write_bytes(self._manifest_copy, data)
        except OSError as exc:
            log.debug("cannot keep a copy of the manifest (%s)", exc)

    def _shared_fetch(self, name: str, sha: str | None) -> bytes:
        """Fetch ``name``; a thread asking for a file already in flight waits for that download."""
        with self._lock:
            flight = self._flights.get(name)
            owner = flight is None
            if owner:
                flight = self._flights[name] = _Flight()
        if not owner:
            # The owner's loop is bounded by its timeouts and backoff; wait a bit longer than that.
            budget = (self.retry.retries + 1) * (self.retry.timeout_s + self.retry.backoff_max_s) + 5
            if not flight.done.wait(budget):
                raise MapError(f"{self.url(name)}: timed out waiting for a concurrent download")
            if flight.error is not None:
                raise MapError(str(flight.error))
            return flight.data  # type: ignore[return-value]
        try:
            data = None
            if sha is not None and self.cache is not None:
                data = self.cache.get(sha)  # a flight that ended after our cache look-up
            if data is None:
                data = self._fetch(name, sha)
                if sha is not None and self.cache is not None:
                    self.cache.put(sha, data)  # before the flight ends: later readers hit
            flight.data = data
            return data
        except BaseException as exc:
            flight.error = exc
            raise
        finally:
            with self._lock:
                self._flights.pop(name, None)
            flight.done.set()

    def _fetch(self, name: str, sha: str | None) -> bytes:
        url = self.url(name)

        def once() -> bytes:
            data = self._fs.cat_file(self._path(name))
            if sha is not None:
                got = hashlib.sha256(data).hexdigest()
                if got != sha:
                    with self._lock:
                        self._stats.corrupt_downloads += 1
                    log.warning("%s: downloaded file is corrupt (sha256 %s..., manifest says %s...);"
                                " fetching it again", url, got[:12], sha[:12])
                    raise _Corrupt(f"checksum mismatch (sha256 {got[:12]}..., manifest says {sha[:12]}...)")
            return data

        data = self._with_retries(url, once)
        with self._lock:
            self._stats.fetched_files += 1
            self._stats.fetched_bytes += len(data)
        return data

    def _remote_exists(self, name: str) -> bool:
        try:
            if self._protocol in ("http", "https"):
                # strict: a refused connection or a 5xx raises instead of reading as "absent"
                return bool(self._fs.exists(self._path(name), strict=True))
            self._fs.info(self._path(name))
            return True
        except FileNotFoundError:
            return False

    def _with_retries(self, url: str, call: Callable[[], _T]) -> _T:
        """Run ``call`` with the retry policy; MapError after the last try (see module doc)."""
        attempts = 1 if self._offline else self.retry.retries + 1
        last: BaseException | None = None
        corrupt_only = True
        for attempt in range(attempts):
            if attempt:
                with self._lock:
                    self._stats.retries += 1
                    delay = self.retry.delay(attempt, self._rng)
                time.sleep(delay)
            with self._lock:
                self._stats.requests += 1
            try:
                result = call()
            except FileNotFoundError:
                self._mark_online()
                raise MapError(f"{url}: missing map file") from None
            except _Corrupt as exc:
                last = exc
                continue
            except Exception as exc:  # network layers raise many types; classify, then retry
                if not _is_transport_error(exc):
                    raise  # a bug, not a network fault
                if _is_permanent(exc):
                    self._mark_online()
                    raise MapError(f"{url}: refused by the server ({_describe(exc)})") from None
                log.debug("%s: attempt %d failed (%s)", url, attempt + 1, _describe(exc))
                last, corrupt_only = exc, False
                continue
            self._mark_online()
            return result
        with self._lock:
            self._stats.failures += 1
        if corrupt_only:
            raise MapError(f"{url}: {last} on all {attempts} tries; the server's copy differs "
                           "from the manifest")
        if not self._offline:
            log.warning("%s: map server unreachable after %d tries (%s); reads now make one "
                        "attempt each until it answers", url, attempts, _describe(last))
        self._offline = True
        extra = "" if attempts > 1 else " (server offline: one try)"
        raise MapError(f"{url}: unreachable after {attempts} tries{extra} ({_describe(last)})")

    def _mark_online(self) -> None:
        if self._offline:
            log.warning("%s: map server answers again", self.root)
            self._offline = False


def _manifest_files(data: bytes) -> dict[str, str]:
    """file name -> sha256 of the entries of a manifest (ValueError when not one)."""
    doc = json.loads(data.decode("utf-8"))
    if not isinstance(doc, dict) or not isinstance(doc.get("entries"), list):
        raise ValueError("not a manifest")
    out = {}
    for e in doc["entries"]:
        if isinstance(e, dict) and isinstance(e.get("file"), str) and isinstance(e.get("sha256"), str):
            out[e["file"]] = e["sha256"]
    return out


def _make_fs(url: str, retry: RetryPolicy, storage_options: dict[str, Any]):
    """(fsspec file system, path of the root inside it) with timeouts and no hidden retries."""
    try:
        import fsspec
    except ImportError:
        raise MapError(f"{url}: reading maps from URLs needs the fsspec package") from None
    protocol = url.split("://", 1)[0].lower()
    opts: dict[str, Any] = {"skip_instance_cache": True}
    if protocol in ("http", "https"):
        import aiohttp

        opts["client_kwargs"] = {"timeout": aiohttp.ClientTimeout(
            total=retry.timeout_s, sock_connect=min(retry.timeout_s, 5.0))}
    elif protocol in ("s3", "s3a"):
        # our RetryPolicy is the only retry loop: botocore's and s3fs's are switched off
        opts["config_kwargs"] = {"connect_timeout": min(retry.timeout_s, 5.0),
                                 "read_timeout": retry.timeout_s,
                                 "retries": {"max_attempts": 1, "mode": "standard"}}
    for key, value in storage_options.items():
        if isinstance(value, dict) and isinstance(opts.get(key), dict):
            opts[key] = {**opts[key], **value}
        else:
            opts[key] = value
    try:
        fs, root = fsspec.core.url_to_fs(url, **opts)
    except ImportError as exc:
        need = "s3fs" if protocol.startswith("s3") else str(exc)
        raise MapError(f"{url}: reading {protocol}:// maps needs the {need} package") from None
    except ValueError as exc:
        raise MapError(f"{url}: unsupported map URL ({exc})") from None
    if protocol in ("s3", "s3a"):
        fs.retries = 1  # s3fs's own retry loop (an attribute, not a constructor option)
    return fs, root
