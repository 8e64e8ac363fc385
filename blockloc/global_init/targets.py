"""Refinement targets assembled from per-entry voxel statistics kept between searches.

A refinement target is the registration target and the footprint (``refine.Footprint``) of the map
points in a box around a candidate (100 m: about 1.5M campus points). Built from the points, it
cost about 0.1 s CPU each, three times a no-hint search (the answer and the places the ambiguity
test refines), again for every search. :class:`TargetCache` keeps, per map entry (block or tile),
the engine's voxel statistics of its points (every level, with their Gaussians), the points sorted
by voxel column and its points counted per footprint cell, in a bounded LRU; a target over a box
is then assembled from them:

- the voxel columns wholly inside the box, aligned to the coarsest voxels ("core"), come from each
  entry's statistics as they are (a voxel two entries share gets the Gaussian of the summed
  statistics, as a target built from the points gives it);
- the points of the other columns meeting the box (a rim at most one coarse voxel wide) are read
  by index ranges of the column-sorted points, tested against the box as ``points_in_box`` tests
  them, and voxelized as one more tile.

An entry's statistics are built the first time a search needs an entry an earlier search asked for
(:meth:`TargetCache.ready`): a one-shot search builds its targets from the points as before.
Given a directory (``disk_dir``), an entry whose content has a sha256 is written there once built (by
a background thread) and read back by later processes instead of built again (campus: 4-8 ms to
read an entry against 25-100 ms to build it; a fresh process's second search paid 1-2 s for them).
The files are keyed by the engine's settings, the footprint's and the code that builds them; those
of other code not written to for a day are removed when new ones are written.

The target and the footprint are those of the same points as before (every voxel's statistics the
same sums, added in another order: equal to rounding), so verification judges the same thing.
Used where the engine can build a target from statistics (NDT), the map is a store, and the
levelled frame's xy axes are the map's (gravity along z: the simulator, NCLT); elsewhere the
caller builds the target from the points.
"""

from __future__ import annotations

import hashlib
import json
import logging
import queue
import shutil
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from blockloc.global_init.refine import Footprint, Refiner

log = logging.getLogger(__name__)

_BYTES_PER_POINT = 40  # an entry kept here, about (campus: 648 MB for 18.6M points, 35 bytes a point)
_STALE_S = 86400.0  # another code's statistics (or a temp file) not written to for a day are removed
_WRITE_QUEUE = 64  # entries waiting for the background writer; more are not written (built again later)
_EPS_M = 1e-6  # the core keeps this clear of the box's edges (a point's voxel is floor(x / res))


def axis_aligned(R_L_map: np.ndarray) -> bool:
    """Whether the levelled xy of a map point is its map xy, each axis kept or reversed."""
    R = np.asarray(R_L_map, float)
    return bool(np.all(R[:2, 2] == 0) and R[0, 1] == 0 and R[1, 0] == 0 and abs(R[0, 0]) == 1 and abs(R[1, 1]) == 1)


@dataclass
class _Entry:
    """One entry's points (N, 3) float32 sorted by finest voxel column, rows of ``span[1]`` columns
    from ``lo`` (``starts``: (span0 * span1 + 1,) offsets), its voxel statistics (``stats``), and its
    points counted per (voxel column, footprint cell): ``pair_col`` (P, 2), ``pair_cell`` (P, 2),
    ``pair_count`` (P,)."""

    points: np.ndarray
    lo: np.ndarray
    span: np.ndarray
    starts: np.ndarray
    stats: object  # the engine's tile statistics (None: no points)
    pair_col: np.ndarray  # (P, 2) int64 finest voxel column
    pair_cell: np.ndarray
    pair_count: np.ndarray

    @property
    def nbytes(self) -> int:
        return int(self.points.nbytes + self.starts.nbytes + (self.stats.nbytes if self.stats is not None else 0)
                   + self.pair_col.nbytes
                   + self.pair_cell.nbytes + self.pair_count.nbytes)

    def rim_points(self, a: np.ndarray, b: np.ndarray, c0: np.ndarray, c1: np.ndarray) -> np.ndarray:
        """Points (M, 3) float32 of the columns in [a, b] (inclusive, finest voxel indices) outside
        the core [c0, c1), gathered by index ranges."""
        A = np.maximum(a, self.lo)
        B = np.minimum(b, self.lo + self.span - 1)
        if np.any(B < A) or len(self.points) == 0:
            return np.zeros((0, 3), np.float32)
        rows = np.arange(A[0], B[0] + 1)
        in_core = (rows >= c0[0]) & (rows < c1[0])
        # (row, first column, last column) segments: a row outside the core whole, a core row on
        # both sides of the core
        seg = [np.stack([rows[~in_core], np.full((~in_core).sum(), A[1]), np.full((~in_core).sum(), B[1])], 1),
               np.stack([rows[in_core], np.full(in_core.sum(), A[1]), np.full(in_core.sum(), min(c0[1] - 1, B[1]))], 1),
               np.stack([rows[in_core], np.full(in_core.sum(), max(c1[1], A[1])), np.full(in_core.sum(), B[1])], 1)]
        seg = np.concatenate(seg)
        seg = seg[seg[:, 2] >= seg[:, 1]]
        base = (seg[:, 0] - self.lo[0]) * self.span[1] - self.lo[1]
        s = self.starts[base + seg[:, 1]]
        e = self.starts[base + seg[:, 2] + 1]
        n = e - s
        if n.sum() == 0:
            return np.zeros((0, 3), np.float32)
        idx = np.repeat(s - np.concatenate([[0], np.cumsum(n)[:-1]]), n) + np.arange(int(n.sum()))
        return self.points[idx]


class TargetCache:
    """Refinement targets (``Refiner``) over boxes of a :class:`~blockloc.global_init.maps.StoreMap`,
    from per-entry statistics kept in an LRU of at most ``max_bytes`` (module docstring).

    engine: a registration engine with ``tile_stats`` and ``target_from_tile_stats`` (NDT);
    R_L_map (3, 3): the levelled frame (:func:`axis_aligned`); footprint_cell_m (0: no footprint),
    footprint_min_share: as :class:`~blockloc.global_init.refine.Refiner` takes them; disk_dir: where
    entries' statistics are kept between processes (None: not kept; the engine must also have
    ``tile_stats_from_arrays``).
    """

    def __init__(self, engine, R_L_map: np.ndarray, footprint_cell_m: float, footprint_min_share: float,
                 max_bytes: int, disk_dir: str | Path | None = None):
        self.engine = engine
        self.R = np.asarray(R_L_map, float).reshape(3, 3)
        self.R2 = np.ascontiguousarray(self.R[:2])
        self.cell_m = float(footprint_cell_m)
        self.min_share = float(footprint_min_share)
        self.max_bytes = int(max_bytes)
        opts = engine.target_options
        self.res = float(opts["resolution"])
        self.step = 1 << int(opts["coarse_levels"])  # the core's columns: whole coarsest voxels
        self._entries: OrderedDict[str, _Entry] = OrderedDict()
        self.hits = self.misses = 0
        self._search = 0  # searches begun (begin_search)
        self._first_seen: dict[str, int] = {}  # entry key -> the search that first asked for it
        self._lock = threading.Lock()  # the entries' LRU
        self.loaded = 0  # entries read from disk_dir
        self.disk_dir = None
        if disk_dir is not None and hasattr(engine, "tile_stats_from_arrays"):
            from blockloc.cache import fingerprint

            # what the files depend on: the engine's voxels, the footprint's cells, the levelled
            # frame, and the code that computes them
            settings = json.dumps([sorted(opts.items()), self.cell_m, np.round(self.R, 9).tolist()])
            self._settings_key = hashlib.sha256(settings.encode()).hexdigest()[:10]
            # (the whole registration package: the voxel statistics are its kernels' too)
            code = fingerprint("blockloc.registration", "blockloc.global_init.targets",
                               "blockloc.global_init._kernels")
            self.disk_dir = Path(disk_dir) / f"targets-{self._settings_key}-{code}"
            self._swept = False
            self._write_failed = False
            # entries built during a search are written by a background thread: ~10 MB each, which
            # a robot's slow storage must not add to the search
            self._pending: queue.Queue = queue.Queue(maxsize=_WRITE_QUEUE)
            self._writer: threading.Thread | None = None

    @staticmethod
    def usable(engine, map_source, R_L_map) -> bool:
        """Whether targets over ``map_source`` with ``engine`` can be assembled here."""
        return (hasattr(engine, "target_from_tile_stats") and hasattr(engine, "target_options")
                and hasattr(map_source, "entry_points") and axis_aligned(R_L_map))

    @property
    def nbytes(self) -> int:
        return sum(e.nbytes for e in self._entries.values())

    def __len__(self) -> int:
        """Entries kept."""
        return len(self._entries)

    def begin_search(self) -> None:
        """A new search (one ``localize``) begins: entries an earlier search asked for may now be kept."""
        self._search += 1

    def ready(self, map_source, lo_L: np.ndarray, hi_L: np.ndarray) -> bool:
        """Whether the box's target is assembled here: every entry it meets is kept, or was asked for
        by an earlier search (then it is built now) and is small enough to keep (a quarter of the
        budget at ~40 bytes a point; a map stored as one big entry is refined from its points).
        Otherwise the caller builds the target from the points, as a one-shot search (``blockloc
        init``) always does: building an entry's statistics costs more than one target from its
        points, and pays only in a process that searches again (the node, a session, the bench)."""
        ok = True
        for i in map_source.entries_in(lo_L, hi_L):
            key = map_source.entry_key(i)
            if key in self._entries:
                continue
            first = self._first_seen.setdefault(key, self._search)
            if first == self._search or self._too_big(map_source, i):
                ok = False
        return ok

    def _too_big(self, map_source, i: int) -> bool:
        """Whether entry i is over a quarter of the budget (~40 bytes a point): it is refined from its
        points instead (:meth:`ready`), so its statistics are neither kept nor written."""
        return len(map_source.entry_points(i)) * _BYTES_PER_POINT > self.max_bytes / 4

    def _entry(self, map_source, i: int) -> _Entry:
        with self._lock:  # targets are assembled side by side (``GlobalLocalizer._refine``)
            return self._entry_locked(map_source, i)

    def _entry_locked(self, map_source, i: int) -> _Entry:
        key = map_source.entry_key(i)
        e = self._entries.get(key)
        if e is not None:
            self._entries.move_to_end(key)
            self.hits += 1
            return e
        self.misses += 1
        e = self._load_or_build(map_source, i)
        self._entries[key] = e
        total = self.nbytes
        while total > self.max_bytes and len(self._entries) > 1:
            total -= self._entries.popitem(last=False)[1].nbytes
        return e

    def _disk_path(self, map_source, i: int) -> Path | None:
        sha = map_source.entry_sha256(i) if hasattr(map_source, "entry_sha256") else None
        return None if self.disk_dir is None or not sha else self.disk_dir / f"{sha}.npz"

    def _load_or_build(self, map_source, i: int) -> _Entry:
        """Entry i read from ``disk_dir``, else built from its points (and written there in the
        background)."""
        path = self._disk_path(map_source, i)
        if path is not None:
            try:
                if path.is_file():
                    entry = self._read(path)
                    self.loaded += 1
                    return entry
            except (OSError, ValueError, KeyError, TypeError, IndexError) as exc:  # rebuilt, rewritten
                log.warning("ignoring unreadable cache %s (%s)", path, exc)
        entry = self._build(np.asarray(map_source.entry_points(i)))
        if path is not None:
            self._write_later(path, entry)
        return entry

    def prepare(self, map_source, i: int) -> bool:
        """Entry i's statistics built and written to ``disk_dir`` unless already there (not kept
        in memory); False where nothing is kept: no ``disk_dir``, no sha256, a failed write, or an
        entry too big to be assembled from (:meth:`ready`: refined from its points)."""
        path = self._disk_path(map_source, i)
        if path is None or self._too_big(map_source, i):
            return False
        try:
            if path.is_file():
                return True
        except OSError:
            return False
        self._write(path, self._build(np.asarray(map_source.entry_points(i))))
        return path.is_file()

    def flush(self) -> None:
        """Wait until the entries queued for writing are written (or given up)."""
        if self.disk_dir is not None:
            self._pending.join()

    def _write_later(self, path: Path, entry: _Entry) -> None:
        if self._writer is None:
            self._writer = threading.Thread(target=self._write_loop, name="blockloc-target-cache", daemon=True)
            self._writer.start()
        try:
            self._pending.put_nowait((path, entry))
        except queue.Full:
            pass  # a later process builds it again

    def _write_loop(self) -> None:
        while True:
            path, entry = self._pending.get()
            try:
                self._write(path, entry)
            except Exception as exc:  # noqa: BLE001 - the cache only saves time; the search goes on
                log.warning("cannot write global-init cache %s (%s)", path, exc)
            finally:
                self._pending.task_done()

    def _write(self, path: Path, entry: _Entry) -> None:
        from blockloc.fileio import atomic_path

        arrays = dict(points=entry.points, lo=entry.lo, span=entry.span, starts=entry.starts,
                      pair_col=entry.pair_col, pair_cell=entry.pair_cell, pair_count=entry.pair_count,
                      has_stats=np.array(entry.stats is not None))
        if entry.stats is not None:
            arrays.update({f"stats_{k}": v for k, v in entry.stats.to_arrays().items()})
        try:
            with atomic_path(path) as tmp, open(tmp, "wb") as f:
                np.savez(f, **arrays)  # uncompressed: read back at disk speed
        except OSError as exc:  # a read-only cache only costs time; said once, not per entry
            if not self._write_failed:
                log.warning("cannot write global-init cache %s (%s); entries will be built again", path, exc)
            self._write_failed = True
            return
        if not self._swept:
            self._swept = True
            self._sweep(path.parent)

    def _sweep(self, mine: Path) -> None:
        """Remove what no process reads again: the statistics of other code with the same settings
        (an older blockloc, an edited checkout) not written to for a day, and temp files of writes a
        process did not finish (killed) as old. A day: two installs sharing the cache (a robot's and
        a developer's) do not remove each other's files while both are in use."""
        cutoff = time.time() - _STALE_S
        for other in mine.parent.glob(f"targets-{self._settings_key}-*"):
            try:
                if other != mine and other.is_dir() and other.stat().st_mtime < cutoff:
                    shutil.rmtree(other, ignore_errors=True)
            except OSError:
                pass
        for tmp in mine.glob(".*.tmp"):
            try:
                if tmp.stat().st_mtime < cutoff:
                    tmp.unlink()
            except OSError:
                pass

    def _read(self, path: Path) -> _Entry:
        """An entry as :meth:`_write` wrote it; ValueError (or KeyError) for anything else."""
        from blockloc.fileio import load_arrays

        arrays = load_arrays(path)
        stats = (self.engine.tile_stats_from_arrays({k[6:]: v for k, v in arrays.items() if k.startswith("stats_")})
                 if bool(arrays["has_stats"]) else None)
        entry = _Entry(arrays["points"], arrays["lo"], arrays["span"], arrays["starts"], stats, arrays["pair_col"],
                       arrays["pair_cell"], arrays["pair_count"])
        num = len(entry.points)
        ints = (entry.lo, entry.span, entry.starts, entry.pair_col, entry.pair_cell, entry.pair_count)
        ok = (entry.points.ndim == 2 and entry.points.shape[1:] == (3,) and entry.points.dtype == np.float32
              and all(a.dtype.kind == "i" for a in ints) and entry.lo.shape == (2,) and entry.span.shape == (2,)
              and np.all(entry.span >= 1) and entry.starts.shape == (int(np.prod(entry.span)) + 1,)
              and int(entry.starts[0]) == 0 and int(entry.starts[-1]) == num and np.all(np.diff(entry.starts) >= 0)
              and (stats is None) == (num == 0) and (stats is None or stats.num_points == num)
              and entry.pair_col.shape == entry.pair_cell.shape == (len(entry.pair_count), 2)
              and int(entry.pair_count.sum()) == (num if self.cell_m > 0 else 0))
        if not ok:
            raise ValueError(f"{num} points, columns {entry.span.tolist()}, {len(entry.starts)} offsets, "
                             f"{len(entry.pair_count)} footprint pairs: not one entry of these settings")
        return entry

    def _build(self, pts32: np.ndarray) -> _Entry:
        from blockloc.global_init import _kernels as K

        pts32 = np.asarray(pts32, np.float32).reshape(-1, 3)
        p = pts32.astype(np.float64)
        col = np.floor(p[:, :2] * (1.0 / self.res)).astype(np.int64)  # the voxel's x, y (voxel_stats)
        if len(p) == 0:
            z2 = np.zeros((0, 2), np.int64)
            return _Entry(pts32, np.zeros(2, np.int64), np.ones(2, np.int64), np.zeros(2, np.int64), None, z2, z2,
                          np.zeros(0, np.int64))
        lo = col.min(axis=0)
        span = col.max(axis=0) - lo + 1
        code = (col[:, 0] - lo[0]) * span[1] + (col[:, 1] - lo[1])
        order = np.argsort(code, kind="stable")
        starts = np.searchsorted(code[order], np.arange(int(span[0] * span[1]) + 1))
        stats = self.engine.tile_stats(p[order])
        if self.cell_m > 0:
            cells = K.levelled_cells(p, self.R2, self.cell_m)
            c_lo = cells.min(axis=0)
            c_span = cells.max(axis=0) - c_lo + 1
            pair = (code * c_span[0] + (cells[:, 0] - c_lo[0])) * c_span[1] + (cells[:, 1] - c_lo[1])
            u, cnt = np.unique(pair, return_counts=True)
            cell = np.stack([(u // c_span[1]) % c_span[0] + c_lo[0], u % c_span[1] + c_lo[1]], 1)
            ucode = u // (c_span[0] * c_span[1])
            pcol = np.stack([ucode // span[1] + lo[0], ucode % span[1] + lo[1]], 1)
        else:
            pcol, cell, cnt = np.zeros((0, 2), np.int64), np.zeros((0, 2), np.int64), np.zeros(0, np.int64)
        return _Entry(pts32[order], lo, span, starts, stats, pcol, cell, cnt.astype(np.int64))

    def refiner(self, map_source, lo_L: np.ndarray, hi_L: np.ndarray, min_points: int = 100) -> Refiner | None:
        """The refiner of the map points whose levelled xy lies in [lo_L, hi_L] (as
        ``map_source.points_in_box`` returns them), or None with fewer than ``min_points``."""
        from blockloc.global_init import _kernels as K

        lo_L = np.asarray(lo_L, float).reshape(2)
        hi_L = np.asarray(hi_L, float).reshape(2)
        # the box in the map frame (the levelled axes are the map's, maybe reversed)
        sign = np.array([self.R[0, 0], self.R[1, 1]])
        m0 = np.minimum(sign * lo_L, sign * hi_L)
        m1 = np.maximum(sign * lo_L, sign * hi_L)
        inv = 1.0 / self.res
        a = np.floor(m0 * inv).astype(np.int64)  # every column meeting the box
        b = np.floor(m1 * inv).astype(np.int64)
        g = self.res * self.step
        c0 = (np.ceil((m0 + _EPS_M) / g) * self.step).astype(np.int64)  # whole columns inside, aligned
        c1 = (np.floor((m1 - _EPS_M) / g) * self.step).astype(np.int64)
        if np.any(c1 <= c0):
            c0 = c1 = np.zeros(2, np.int64)  # no core: every point is tested
        tiles, rims, n_core = {}, [], 0
        core_pairs = []
        for i in map_source.entries_in(lo_L, hi_L):
            e = self._entry(map_source, i)
            if e.stats is not None and np.all(c1 > c0):
                part = e.stats.select_columns(c0, c1)
                if part.num_points:
                    tiles[("core", i)] = part
                    n_core += part.num_points
                if len(e.pair_count):
                    k = ((e.pair_col[:, 0] >= c0[0]) & (e.pair_col[:, 0] < c1[0])
                         & (e.pair_col[:, 1] >= c0[1]) & (e.pair_col[:, 1] < c1[1]))
                    core_pairs.append((e.pair_cell[k], e.pair_count[k]))
            rims.append(e.rim_points(a, b, c0, c1))
        rim = np.concatenate(rims) if rims else np.zeros((0, 3), np.float32)
        rim = rim[K.in_levelled_box(rim, self.R2, lo_L[0], lo_L[1], hi_L[0], hi_L[1])].astype(np.float64)
        if n_core + len(rim) < min_points:
            return None
        if len(rim):
            tiles[("rim",)] = self.engine.tile_stats(rim)
        target = self.engine.target_from_tile_stats(tiles)
        footprint = None
        if self.cell_m > 0:
            f_lo = np.floor(lo_L / self.cell_m).astype(np.int64) - 1
            f_n = np.floor(hi_L / self.cell_m).astype(np.int64) + 2 - f_lo
            counts = (K.cell_counts(rim, self.R2, self.cell_m, f_lo[0], f_lo[1], int(f_n[0]), int(f_n[1]))
                      .astype(np.int64) if len(rim) else np.zeros((int(f_n[0]), int(f_n[1])), np.int64))
            for cell, cnt in core_pairs:
                np.add.at(counts, (cell[:, 0] - f_lo[0], cell[:, 1] - f_lo[1]), cnt)
            footprint = Footprint.from_counts(self.R, self.cell_m, self.min_share, f_lo, counts)
        return Refiner.from_target(self.engine, target, footprint)
