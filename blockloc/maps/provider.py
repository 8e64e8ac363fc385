"""The map provider: pose in, local map out, with loading and target building off the tracking loop.

``MapProvider.update(position_map, velocity_map, stamp)`` returns the :class:`LocalMap` to register
against. A policy (:mod:`blockloc.maps.policies`: block, grid, srt, global) names the region that
should be resident; a background thread loads its blocks/tiles (through an LRU cache bounded in MB)
and builds the registration target. The first call waits for its map; later calls never wait on
disk: while the wanted region is still being built the previous one is served, and the region
the robot heads into (``position + velocity * lookahead``) is prefetched so it is usually ready
when needed. Regions are swapped double-buffered: the target being used is never modified; an
incremental target (``add_tile``/``remove_tile``) is updated only in the spare buffer.

A block/tile that is missing or corrupt while tracking is logged, counted (``failed_loads``) and
treated as unmapped; tracking is not stopped. So is a region whose registration target cannot be
built (``target_failures``).

Thread contract: a LocalMap's ``target`` stays valid until the next ``update`` call returns.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any

import numpy as np

from blockloc.errors import MapError
from blockloc.maps.policies import Region
from blockloc.maps.store import MapStore

log = logging.getLogger(__name__)

_MB = 1024.0 * 1024.0


@dataclass(frozen=True)
class LocalMap:
    """The resident local map.

    target: the engine's registration target for ``points`` (None when nothing is mapped here or no
    builder was given). points: (N, 3) float32 map frame, metres (read-only; do not modify).
    region_id: a readable name of the region; entry_ids: its blocks/tiles. switched: True exactly
    on the update at which the active region changed to one that does not hold every entry of the
    last (False on the first update: no previous map). block_id: the block the robot is in (block
    backend) else None.
    version: increases at every swap. missing: entries that failed to load (treated as unmapped).
    """

    target: Any
    points: np.ndarray
    region_id: str
    entry_ids: tuple
    switched: bool
    block_id: str | None
    version: int
    num_points: int
    missing: tuple = ()


@dataclass
class _Buffer:
    region: Region
    name: str
    points: np.ndarray
    target: Any
    tiles: set
    missing: tuple
    nbytes: int
    prefetched: bool = False


class MapProvider:
    """Serve the local map for the current pose from ``store`` under a policy.

    policy: which region should be resident (:func:`blockloc.maps.policies.make_policy`).
    engine: the registration engine whose targets are built (``build_target(points)``; when
    ``engine.incremental``, grid/srt/global regions are built with ``build_tiled_target(tiles)``
    and updated by tile with ``update_tiles``: see :mod:`blockloc.registration.engines`), or None
    to serve points only. prefetch: build the region the robot will need next if it keeps its
    velocity for ``lookahead_s`` seconds (at least ``min_lookahead_m`` metres). cache_mb: bound on
    resident map memory (entry cache plus region buffers; the active region is never evicted).
    retry_missing_s: while entries of the active region are missing (a file failed to load, e.g.
    a map server went away), it is rebuilt in the background every this many seconds of sensor
    time and swapped in once more of it loads.
    """

    def __init__(self, store: MapStore, policy, *, engine=None, prefetch: bool = True,
                 lookahead_s: float = 5.0, min_lookahead_m: float = 2.0, cache_mb: float = 1024.0,
                 max_spare_regions: int = 2, retry_missing_s: float = 5.0):
        if len(store.entries) == 0:
            raise MapError(f"{store.path}: the map has no blocks or tiles")
        if not cache_mb > 0:
            raise MapError(f"map cache {cache_mb!r} MB: expected a positive number")
        self.store = store
        self.policy = policy
        self.backend = policy.name
        self.engine = engine
        # Block regions are one or two whole blocks: rebuilt, never patched by tile.
        self.incremental = bool(engine is not None and getattr(engine, "incremental", False)
                                and self.backend != "block")
        self.prefetch = bool(prefetch)
        self.lookahead_s = float(lookahead_s)
        self.min_lookahead_m = float(min_lookahead_m)
        self.cache_bytes = float(cache_mb) * _MB
        self.max_spare_regions = int(max_spare_regions)
        self.retry_missing_s = float(retry_missing_s)
        self._last_retry = -np.inf
        self._rebuilding: set[Region] = set()  # the active region, being rebuilt to fill gaps

        self._lock = threading.Condition()
        self._cache: OrderedDict[str, np.ndarray] = OrderedDict()  # entry id -> points (N, 3)
        self._cache_nbytes = 0
        self._failed: set[str] = set()
        self._active: _Buffer | None = None
        self._ready: OrderedDict[Region, _Buffer] = OrderedDict()  # built, not active
        self._busy: set[Region] = set()  # being built
        self._queue: list[tuple[int, Region, bool]] = []  # (priority 0 demand / 1 prefetch, ...)
        self._wanted: Region | None = None
        self._version = 0
        self._closed = False
        self._warned_budget = False
        self._stats = dict(loads=0, cache_hits=0, evictions=0, switches=0, builds=0,
                           prefetch_builds=0, prefetch_hits=0, late_frames=0, failed_loads=0,
                           waits_ms=0.0, max_wait_ms=0.0, build_ms=0.0, updates=0)
        self._errors: list[BaseException] = []
        self._thread = threading.Thread(target=self._run, name="blockloc-map-provider", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ public API
    def update(self, position_map: np.ndarray, velocity_map: np.ndarray | None,
               stamp: float) -> LocalMap:
        """The local map for the robot at ``position_map`` (3,) metres, moving at ``velocity_map``
        (3,) m/s (or None), at time ``stamp`` s. Blocks only on the first call."""
        if self._closed:
            raise MapError("map provider is closed")
        self._raise_worker_error()
        position = np.asarray(position_map, np.float64).reshape(3)
        velocity = None if velocity_map is None else np.asarray(velocity_map, np.float64).reshape(3)
        if not np.all(np.isfinite(position)):
            if self._active is None:
                raise MapError(f"map provider: non-finite position {position} on the first update")
            log.warning("non-finite position %s: keeping the current map", position)
            return self._local(False)
        wanted = self.policy.select(position, velocity, stamp)
        switched = False
        with self._lock:
            self._stats["updates"] += 1
            self._wanted = wanted
            if self._active is None:
                self._wait_for(wanted)
            if self._errors:
                pass
            elif self._active is None or wanted != self._active.region:
                if wanted in self._ready:
                    # The first map is no switch, nor a region that only adds to the last one
                    # (a blended block pair after its first block): the window keeps its states.
                    switched = self._active is not None and not set(wanted) >= set(self._active.region)
                    self._swap(wanted)
                else:
                    self._stats["late_frames"] += 1
                    self._submit(wanted, demand=True)
            if not self._errors:
                self._retry_missing(wanted, stamp)
            if self.prefetch and velocity is not None and not self._errors:
                horizon = float(np.linalg.norm(velocity[:2])) * self.lookahead_s
                ahead = self.policy.ahead(position, velocity, max(horizon, self.min_lookahead_m))
                if ahead is not None and ahead != self._active.region:
                    self._submit(ahead, demand=False)
        self._raise_worker_error()
        return self._local(switched)

    def _wait_for(self, wanted) -> None:
        """Load ``wanted`` on demand and block until it is ready or a load failed (the lock is
        held); the wait counts in the stats."""
        t0 = time.perf_counter()
        self._submit(wanted, demand=True)
        while wanted not in self._ready and not self._errors:
            self._lock.wait(0.05)
        wait_ms = (time.perf_counter() - t0) * 1e3
        self._stats["waits_ms"] += wait_ms
        self._stats["max_wait_ms"] = max(self._stats["max_wait_ms"], wait_ms)

    def relocate(self, position_map: np.ndarray, velocity_map: np.ndarray | None, stamp: float) -> LocalMap:
        """The robot is elsewhere now (a relocalization, a kidnap): the map at ``position_map`` (3,)
        metres, chosen afresh (no switch hysteresis) and waited for, as on the first call.

        Why: ``update`` keeps serving the old region while a new one loads (a late frame), which is
        right while driving (prefetch has it ready) but not after a jump: seen on the small world,
        the first scan after a 47 m recovery registered against the block it came from (0.33 m off,
        reported ok)."""
        if self._closed:
            raise MapError("map provider is closed")
        position = np.asarray(position_map, np.float64).reshape(3)
        if not np.all(np.isfinite(position)):
            raise MapError(f"map provider: non-finite position {position} to relocate to")
        reset = getattr(self.policy, "reset", None)
        if reset is not None:
            reset()
        wanted = self.policy.select(position, velocity_map, stamp)
        with self._lock:
            self._wanted = wanted
            if self._active is None or wanted != self._active.region:
                self._wait_for(wanted)
                if not self._errors:
                    self._swap(wanted)
        self._raise_worker_error()
        return self._local(True)

    def current(self) -> LocalMap | None:
        """The local map served now (None before the first ``update``); does not change state."""
        with self._lock:
            return None if self._active is None else self._local(False)

    def stats(self) -> dict:
        """Counters: resident_mb (entry cache + region buffers), active_mb / active_points (the
        served local map's points), cache_mb (the bound), loads,
        cache_hits, evictions, switches, builds, prefetch_builds, prefetch_hits, late_frames (frames
        served the previous region because the wanted one was not built yet), failed_loads,
        waits_ms (total time update waited), max_wait_ms, build_ms."""
        with self._lock:
            out = dict(self._stats)
            out["resident_mb"] = self._resident_bytes() / _MB
            out["active_mb"] = 0.0 if self._active is None else self._active.points.nbytes / _MB
            out["active_points"] = 0 if self._active is None else len(self._active.points)
            out["cache_mb"] = self.cache_bytes / _MB
            out["cached_entries"] = len(self._cache)
            out["ready_regions"] = len(self._ready)
        return out

    def close(self) -> None:
        """Stop the background thread (idempotent)."""
        with self._lock:
            self._closed = True
            self._lock.notify_all()
        self._thread.join(timeout=10)

    def __enter__(self) -> "MapProvider":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------------ internals (lock held)
    def _local(self, switched: bool) -> LocalMap:
        b = self._active
        return LocalMap(target=b.target, points=b.points, region_id=b.name, entry_ids=b.region,
                        switched=switched,
                        block_id=self._block_id(b.region) if self.backend == "block" else None,
                        version=self._version, num_points=len(b.points), missing=b.missing)

    def _block_id(self, region: Region) -> str:
        """The block the robot is in, when the served region holds it (a blended pair holds two)."""
        primary = self.policy.primary
        return primary if primary in region else region[0]

    def _swap(self, region: Region) -> None:
        new = self._ready.pop(region)
        new.name = self.policy.region_name(region)
        old = self._active
        self._active = new
        self._version += 1
        if old is not None:
            self._stats["switches"] += 1
            if new.prefetched:
                self._stats["prefetch_hits"] += 1
            self._ready[old.region] = old  # becomes the spare buffer
            self._ready.move_to_end(old.region, last=False)
        self._trim_ready()
        log.info("map region -> %s (%d entries, %d points)", new.name, len(new.region), len(new.points))

    def _retry_missing(self, wanted: Region, stamp: float) -> None:
        """Refill the active region's missing entries: collect a finished rebuild, or start one."""
        active = self._active
        if active is None or not active.missing or wanted != active.region:
            return
        if wanted in self._ready and wanted not in self._rebuilding:
            fresh = self._ready.pop(wanted)
            if len(fresh.missing) < len(active.missing):
                fresh.name = active.name
                self._active = fresh
                self._version += 1
                log.warning("map region %s reloaded: %d of its entries still missing", fresh.name,
                            len(fresh.missing))
            return
        if stamp - self._last_retry >= self.retry_missing_s and wanted not in self._rebuilding:
            self._last_retry = stamp
            self._rebuilding.add(wanted)
            self._queue.append((1, wanted, True))
            self._queue.sort(key=lambda q: q[0])
            self._lock.notify_all()

    def _trim_ready(self, keep: Region | None = None) -> None:
        """At most ``max_spare_regions`` built regions besides the active one, then the bound."""
        while len(self._ready) > self.max_spare_regions:
            victim = next((r for r in self._ready if r not in (keep, self._wanted)), None)
            if victim is None:
                break
            self._ready.pop(victim)
        self._enforce_budget(keep)

    def _submit(self, region: Region, demand: bool) -> None:
        if region in self._busy or region in self._ready or (
                self._active is not None and self._active.region == region):
            return
        prio = 0 if demand else 1
        self._queue = [q for q in self._queue if not (q[1] == region)]
        if demand:  # a newer demand supersedes older ones
            self._queue = [q for q in self._queue if q[0] != 0]
        else:
            self._queue = [q for q in self._queue if q[0] != 1]
        self._queue.append((prio, region, not demand))
        self._queue.sort(key=lambda q: q[0])
        self._lock.notify_all()

    def _resident_bytes(self) -> int:
        """Bytes of distinct point arrays held (cache and region buffers) plus targets' ``nbytes``."""
        arrays = {id(a): a.nbytes for a in self._cache.values()}
        total_targets = 0
        for b in ([self._active] if self._active else []) + list(self._ready.values()):
            arrays.setdefault(id(b.points), b.points.nbytes)
            total_targets += int(getattr(b.target, "nbytes", 0) or 0)
        return sum(arrays.values()) + total_targets

    def _enforce_budget(self, keep: Region | None = None) -> None:
        """Evict least-recently-used cache entries, then the oldest spare regions, until the
        resident bytes fit the bound. Never evicted: the active region, ``keep`` (a region just
        built) and the region the robot currently wants."""
        protected = {r for r in (keep, self._wanted) if r is not None}
        if self._active is not None:
            protected.add(self._active.region)
        pinned = set().union(*protected) if protected else set()
        while self._resident_bytes() > self.cache_bytes:
            victim = next((k for k in self._cache if k not in pinned), None)
            if victim is not None:
                arr = self._cache.pop(victim)
                self._cache_nbytes -= arr.nbytes
                self._stats["evictions"] += 1
                continue
            spare = next((r for r in self._ready if r not in protected), None)
            if spare is not None:
                self._ready.pop(spare)
                continue
            if not self._warned_budget:
                log.warning("map cache bound %.0f MB is smaller than the regions in use (%.0f MB)",
                            self.cache_bytes / _MB, self._resident_bytes() / _MB)
                self._warned_budget = True
            break

    # ------------------------------------------------------------------ worker thread
    def _run(self) -> None:
        while True:
            with self._lock:
                while not self._queue and not self._closed:
                    self._lock.wait()
                if self._closed:
                    return
                _, region, is_prefetch = self._queue.pop(0)
                rebuild = region in self._rebuilding
                if not rebuild and (region in self._ready or (
                        self._active is not None and self._active.region == region)):
                    continue
                self._busy.add(region)
                spare = None if rebuild else self._take_spare(region)
            try:
                buf = self._build(region, spare, is_prefetch)
            except BaseException as exc:  # noqa: BLE001 - handed to the caller of update()
                log.error("map provider: building region %s failed: %s", region, exc)
                with self._lock:
                    self._busy.discard(region)
                    self._rebuilding.discard(region)
                    self._errors.append(exc)
                    self._lock.notify_all()
                return
            with self._lock:
                self._busy.discard(region)
                self._rebuilding.discard(region)
                self._ready[region] = buf
                self._stats["builds"] += 1
                if is_prefetch:
                    self._stats["prefetch_builds"] += 1
                self._trim_ready(keep=region)
                self._lock.notify_all()

    def _take_spare(self, region: Region) -> _Buffer | None:
        """A non-active built buffer to update incrementally (removed from ``_ready``)."""
        if not self.incremental or not self._ready:
            return None
        spares = [b for b in self._ready.values() if b.region != self._wanted]
        if not spares:
            return None
        best = max(spares, key=lambda b: len(b.tiles & set(region)))
        return self._ready.pop(best.region)

    def _load_entry(self, entry_id: str) -> np.ndarray | None:
        with self._lock:
            if entry_id in self._cache:
                self._cache.move_to_end(entry_id)
                self._stats["cache_hits"] += 1
                return self._cache[entry_id]
        try:
            points, _ = self.store.load(entry_id)
        except MapError as exc:
            with self._lock:
                self._stats["failed_loads"] += 1
                first = entry_id not in self._failed
                self._failed.add(entry_id)
            if first:
                log.error("%s; its region is treated as unmapped", exc)
            return None
        points.setflags(write=False)
        with self._lock:
            if entry_id in self._failed:
                self._failed.discard(entry_id)
                log.warning("map entry %s loaded again after earlier failures", entry_id)
            self._stats["loads"] += 1
            self._cache[entry_id] = points
            self._cache_nbytes += points.nbytes
        return points

    def _build(self, region: Region, spare: _Buffer | None, is_prefetch: bool) -> _Buffer:
        t0 = time.perf_counter()
        tiles: dict[str, np.ndarray] = {}
        missing = []
        for eid in region:
            pts = self._load_entry(eid)
            if pts is None:
                missing.append(eid)
            elif len(pts):
                tiles[eid] = pts
        parts = list(tiles.values())
        if len(parts) == 1:
            points = parts[0]  # shared with the cache: no copy
        elif parts:
            points = np.concatenate(parts)
            points.setflags(write=False)
        else:
            points = np.zeros((0, 3), np.float32)
        target = None
        if len(points):
            try:
                target = self._build_target(tiles, points, spare)
            except Exception as exc:  # noqa: BLE001 - a bad region must not stop tracking
                log.error("region %s: building the registration target failed (%s: %s); treated "
                          "as unmapped", region, type(exc).__name__, exc)
                with self._lock:
                    self._stats["target_failures"] = self._stats.get("target_failures", 0) + 1
        elif missing:
            log.warning("region %s: nothing loaded, treated as unmapped", region)
        build_ms = (time.perf_counter() - t0) * 1e3
        with self._lock:
            self._stats["build_ms"] += build_ms
        log.debug("built region %s (%d points) in %.0f ms%s", region, len(points), build_ms,
                  " (prefetch)" if is_prefetch else "")
        nbytes = 0 if len(parts) == 1 else points.nbytes
        return _Buffer(region, self.policy.region_name(region), points, target, set(tiles),
                       tuple(missing), nbytes, prefetched=is_prefetch)

    def _build_target(self, tiles: dict, points: np.ndarray, spare: _Buffer | None):
        if self.engine is None:
            return None
        if self.incremental:
            if spare is not None and spare.target is not None:
                # the spare buffer: nobody registers against it now
                return self.engine.update_tiles(spare.target,
                                                {e: tiles[e] for e in set(tiles) - spare.tiles},
                                                spare.tiles - set(tiles))
            return self.engine.build_tiled_target(tiles)
        return self.engine.build_target(points)

    def _raise_worker_error(self) -> None:
        if self._errors:
            exc = self._errors[0]
            if isinstance(exc, MapError):
                raise exc
            raise MapError(f"map provider: building a local map failed: {type(exc).__name__}: {exc}") \
                from exc

    def wait_idle(self, timeout_s: float = 10.0) -> bool:
        """Block until no build is queued or running (tests and benchmarks); True when idle."""
        deadline = time.monotonic() + timeout_s
        with self._lock:
            while self._queue or self._busy:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return False
                self._lock.wait(min(remaining, 0.05))
        return True

