"""The map build plan: one list of pure tasks, run in this process or on a Dask cluster.

A build reads one or more mapping **drives** (sequences whose poses share one map frame) and
writes one block or grid store. The work is cut into tasks (:mod:`blockloc.maps.build_tasks`)
that are pure functions of their arguments; each writes its result into the build's directory
and returns only small numbers, so the same plan gives the same bytes whoever runs it: :class:`InlineExecutor` (this process, one
task after another: the serial build) or a Dask executor (:mod:`blockloc.maps.distributed`).

Steps (tasks in *italics*):

1. *plan_drive*: each drive's keyframes and their poses (no scan read). Drives are then put in a
   stable order: first keyframe stamp, then name, then first frame; the map does not depend on
   the order they were given in. With ``calibrate_mounting``, *mounting* estimates each drive's
   LiDAR mounting from registered keyframe pairs (:mod:`blockloc.maps.mounting`) and the drive
   is planned again with it.
2. Block maps (Algorithm 1, :mod:`blockloc.maps.block_maps`): the client cuts each drive's
   keyframes into candidate blocks from their positions (:class:`CandidateSegmenter`);
   *block_run* reads and deskews a run of ``KEYFRAMES_PER_RUN`` keyframes of a candidate and
   sums their points by voxel; *block_candidate* adds its runs' sums up in order (the same
   :class:`VoxelAccumulator` as the in-memory builder), writes the voxel centroids to the scratch
   area and returns their centroid and bounds. Runs are a fixed size, so a build has many small
   scan-reading tasks however many workers run them, and the same bytes. The client decides new / merge / skip / tail in order from
   centroids alone (:class:`BlockLedger`); a merge is a *block_merge* task (a new version of the
   block's points); when a merge's centroid is not back yet the ledger waits for it only if that
   block could be the nearest. *block_write* encodes each block's last version as its entry.
3. Grid maps: *grid_chunk* reads and deskews a run of ``chunk_keyframes`` keyframes, bins the
   points into tiles and sums them by voxel (:data:`~blockloc.maps.grid_tiles.VOXEL_SUM`);
   *grid_tile* merges a tile's sums from every chunk in plan order and writes the tile.
4. The client commits the manifest (atomically, :class:`~blockloc.maps.store.MapWriter`) when
   every entry's checksum is in. Any failure cancels the tasks and removes the build directory:
   no manifest, nothing half-written.

Scratch files live in ``<build dir>/.work/`` and are removed before the commit.
"""

from __future__ import annotations

import logging
import os
import threading
import uuid
from pathlib import Path
from typing import Any

import numpy as np

from blockloc.errors import MapError
from blockloc.maps.build_tasks import (SCRATCH, BuildTarget, Drive, DrivePlan,
                                       block_candidate_task, block_merge_task, block_run_task,
                                       block_write_task, dynamic_filter, forget_drives,
                                       grid_chunk_task, grid_tile_task, open_drive_task,
                                       plan_drive_task)

log = logging.getLogger(__name__)

#: Keyframes per grid chunk task: a fixed plan parameter (never derived from the number of
#: workers), so the sums, and the bytes, are the same on any cluster.
CHUNK_KEYFRAMES = 32
#: Tiles per grid tile task: one tile is milliseconds of work, about what Dask spends scheduling
#: a task; a fixed plan parameter (each tile is computed alone: it does not change the bytes).
TILES_PER_TASK = 16
#: Margin (m) added to the box a held block's centroid lies in (float32 rounding of the points).
_BOX_PAD_M = 0.01


# ----------------------------------------------------------------------------- executors


class _Done:
    """The result of a task run inline (the interface of a Dask future that the plan uses)."""

    def __init__(self, value: Any = None, error: BaseException | None = None) -> None:
        self._value, self._error = value, error

    def result(self) -> Any:
        if self._error is not None:
            raise self._error
        return self._value

    def done(self) -> bool:
        return True

    def add_done_callback(self, fn) -> None:
        fn(self)


class InlineExecutor:
    """Runs each task as it is submitted, in this process: the serial build."""

    description = "serial (this process)"
    dashboard_link = None

    def submit(self, fn, *args, key: str | None = None, priority: int = 0, locality: float | None = None) -> _Done:
        try:
            values = [a.result() if isinstance(a, _Done) else a for a in args]
            return _Done(fn(*values))
        except Exception as exc:  # kept for .result(), like a future
            return _Done(error=exc)

    def cancel(self, futures) -> None:
        pass


class _Tasks:
    """Submits a build's tasks to an executor, counts them on one progress bar, and cancels all
    of them on failure."""

    def __init__(self, executor, progress) -> None:
        self.executor = executor
        self.build_id = uuid.uuid4().hex[:10]
        self.futures: list = []
        self.names: list[str] = []
        self.side: list = []  # tasks outside the plan (opening drives ahead): cancelled with it
        self._expected = 0
        self._lock = threading.Lock()
        self._done = 0
        self._final = False  # set by finished(): until then the plan may still grow
        # (done, total) callback; the bar drawing it is the command's (blockloc.commands.common)
        self._report = progress if callable(progress) else None

    def expect(self, n: int) -> None:
        """``n`` more tasks are about to be submitted (the total grows as the plan does)."""
        with self._lock:
            self._expected += n
            self._show()

    def submit(self, fn, *args, name: str, priority: int = 0, locality: float | None = None):
        """locality in [0, 1): where along the build's keyframes the task's data lies (tasks near
        each other read the same parts of a drive; an executor may keep them on one worker)."""
        if len(self.futures) >= self._expected:
            self.expect(1)
        extra = {} if locality is None else {"locality": locality}
        fut = self.executor.submit(fn, *args, key=f"{name}-{self.build_id}", priority=priority, **extra)
        self.futures.append(fut)
        self.names.append(name)
        fut.add_done_callback(self._tick)
        return fut

    def _tick(self, _fut) -> None:  # Dask calls it from its own thread
        with self._lock:
            self._done += 1
            try:
                self._show()
            except BaseException:
                # the callback stops a build by raising (a signal came): in the main thread that
                # ends the build; in Dask's thread the main thread's own signal handler does
                if threading.current_thread() is threading.main_thread():
                    raise

    def _show(self) -> None:
        total = max(self._expected, len(self.futures))
        if not self._final:
            # each stage plans the next one's tasks from its results (mounting, refinement, blocks),
            # so every task planned so far being done is not the end: the bar shows 100% once
            total = max(total, self._done + 1)
        if self._report is not None:
            self._report(self._done, total)

    def finished(self) -> None:
        """All done: the total is what ran (skips had no second task)."""
        with self._lock:
            self._expected = len(self.futures)
            self._final = True
            self._show()

    def cancel(self) -> None:
        self.executor.cancel(self.futures + self.side)

    def stats(self) -> dict:
        """Per task kind (candidate, merge, write, chunk, tile, plan): count, seconds (the tasks'
        own wall time, summed), cpu_s (their CPU time, summed, and ``cpu_each`` in submission
        order), bytes written, raw points read."""
        out: dict[str, dict] = {}
        for name, fut in zip(self.names, self.futures):
            r = fut.result()
            if isinstance(r, DrivePlan):
                r = {"seconds": r.seconds, "cpu_s": r.cpu_s}
            row = out.setdefault(name.split("-")[0], {"count": 0, "seconds": 0.0, "cpu_s": 0.0,
                                                      "bytes": 0, "raw_points": 0, "cpu_each": []})
            row["count"] += 1
            row["cpu_each"].append(r.get("cpu_s", 0.0))
            for k in ("seconds", "cpu_s", "bytes", "raw_points"):
                row[k] += r.get(k, 0)
        return out

    def skipped(self) -> list[dict]:
        """The keyframes the finished tasks could not read ({sequence, frame, error}), in order."""
        out = []
        for fut in self.futures:
            try:
                r = fut.result() if fut.done() else None
            except Exception:  # noqa: BLE001 - a failed task skipped nothing it could report
                continue
            if isinstance(r, dict):
                out += r.get("skipped") or []
        return sorted(out, key=lambda k: (k["sequence"], k["frame"]))

    def close(self) -> None:
        """Nothing to release (the command closes its bar)."""


# ----------------------------------------------------------------------------- the build


def build_map_from_drives(drives: list[Drive], kind: str, out: str | Path, *,
                          block_size_m: float = 100.0, tile_size_m: float = 20.0,
                          voxel_size_m: float = 0.2, keyframe_distance_m: float = 1.0,
                          keyframe_angle_deg: float = 15.0, deskew: bool = True,
                          calibrate_mounting: bool | str = False, executor=None, progress=False,
                          overwrite: bool = False,
                          chunk_keyframes: int = CHUNK_KEYFRAMES, params: dict | None = None,
                          stats: dict | None = None, mounting_translation_tolerance_m: float | None = None,
                          refine_poses: bool | str = False, remove_dynamic: bool = False):
    """Build a block or grid store at ``out`` from mapping drives sharing one map frame.

    drives: :class:`Drive` list (any order: the plan sorts them). kind: 'block' (S =
    ``block_size_m``) or 'grid' (tiles of ``tile_size_m``). voxel_size_m: voxel filter of blocks
    and tiles (<= 0: none). executor: None = :class:`InlineExecutor`, or a Dask executor
    (:func:`blockloc.maps.distributed.open_executor`): the same plan, the same bytes.
    calibrate_mounting: True: estimate each drive's LiDAR mounting from its scans first
    (:mod:`blockloc.maps.mounting`) and build with it instead of the sequence's ``T_body_lidar``
    (MapError when a drive's estimate fails); ``"auto"`` (the command's default): the same for
    drives whose poses are the body's, while drives with LiDAR poses (``T_body_lidar`` = I) and
    drives the estimate fails on (a warning) keep their own; False: every drive's own. The
    manifest keeps each estimate under ``mounting`` and each drive's ``mounting_source``
    (``{"source": "estimated" | "nominal" | "lidar poses", "reason"?}``).
    mounting_translation_tolerance_m: the estimated translation replaces the nominal one on the
    body axes the drive determines to this (None: ``TRANSLATION_TOLERANCE_M`` of
    :mod:`blockloc.maps.mounting`; 0: on every axis it observes).
    refine_poses: refine each drive's keyframe poses against its own scans after the mounting
    step (:mod:`blockloc.maps.pose_refine`; the mounting's rotation and forward translation are
    estimated with them where the mounting step estimated one) and build from them; the manifest keeps each drive's summary
    under ``pose_refinement``. A drive without revisits is left as it came (logged).
    ``"auto"`` (the command's default): only the drives whose mounting the build estimated
    (poses of the body, the estimate kept); the others are left as they came, marked so.
    remove_dynamic: leave moving objects (pedestrians, passing cars: voxels their own drive's
    later scans see through) out of the map (:mod:`blockloc.maps.dynamic_removal`, evidence over
    each task's keyframes and the drive's keyframes around them,
    :class:`~blockloc.maps.build_tasks.DynamicFilter`); the manifest's ``remove_dynamic`` keeps
    the settings and the points left out.
    progress: None/False or a callback ``(done, total)`` over tasks (commands draw the bar). stats: a dict
    to fill with per-task-kind counts, seconds, bytes and raw points (:meth:`_Tasks.stats`).
    Returns the opened :class:`~blockloc.maps.store.MapStore`.
    """

    if kind not in ("block", "grid"):
        raise MapError(f"map kind {kind!r}: expected block or grid")
    if not drives:
        raise MapError("no mapping drive to build a map from")
    if kind == "block" and not block_size_m > 0:
        raise MapError(f"block size {block_size_m!r} m: expected a positive number")
    if kind == "grid":
        from blockloc.maps.grid_tiles import check_tile_size

        tile_size_m = check_tile_size(tile_size_m)
    if int(chunk_keyframes) < 1:
        raise MapError(f"chunk_keyframes {chunk_keyframes!r}: expected an integer >= 1")
    executor = executor or InlineExecutor()
    dynamic = None
    if remove_dynamic:
        from blockloc.maps.dynamic_removal import DynamicParams

        dynamic = DynamicParams()
    writer = _open_writer(out, kind, overwrite)
    target = BuildTarget(writer.tmp if isinstance(writer.tmp, str) else str(Path(writer.tmp).resolve()))
    tasks = _Tasks(executor, progress)
    warm = getattr(executor, "on_each_worker", None)
    try:
        if warm is not None:  # not counted as tasks of the plan: they only fill a cache
            # each worker opens one drive, the one its share of the keyframes most likely starts
            # in (drives in the order given); a simulated world's scene, the slow part, is
            # shared by all its drives. Opening every drive everywhere kept ~150 MB a drive in
            # every worker (its poses, its trajectory's splines once read) that it never read.
            tasks.side = warm(open_drive_task, lambda i, n: (drives[i * len(drives) // max(n, 1)],),
                              key=f"open-{tasks.build_id}")
        tasks.expect(len(drives))
        plans = [f.result() for f in [tasks.submit(plan_drive_task, d, keyframe_distance_m,
                                                   keyframe_angle_deg, name=f"plan-{n}")
                                      for n, d in enumerate(drives)]]
        if calibrate_mounting not in (True, False, "auto"):
            raise MapError(f"calibrate_mounting {calibrate_mounting!r}: expected True, False or 'auto'")
        mounting = {}
        sources = {p.drive.name: {"source": "nominal", "reason": "not estimated"} for p in plans}
        if calibrate_mounting:
            plans, mounting, sources = _remount(tasks, plans, deskew, keyframe_distance_m,
                                                keyframe_angle_deg, auto=calibrate_mounting == "auto",
                                                translation_tolerance_m=mounting_translation_tolerance_m)
            drives = drives + [p.drive for p in plans]  # forgotten with the others at the end
        refined = {}
        if refine_poses not in (True, False, "auto"):
            raise MapError(f"refine_poses {refine_poses!r}: expected True, False or 'auto'")
        if refine_poses:
            plans, refined = _refine(tasks, plans, deskew, keyframe_distance_m, keyframe_angle_deg,
                                     mounting, sources, auto=refine_poses == "auto")
            drives = drives + [p.drive for p in plans]
        plans.sort(key=DrivePlan.order_key)
        frames = sorted({p.map_frame for p in plans})
        if len(frames) > 1:
            raise MapError(f"drives {', '.join(p.drive.name for p in plans)}: poses in different "
                           f"map frames ({', '.join(frames)}); expected one shared frame")
        common = {"sequence": " + ".join(p.drive.name for p in plans),
                  "keyframe_distance_m": keyframe_distance_m,
                  "keyframe_angle_deg": keyframe_angle_deg, "deskew": deskew}
        if len(plans) > 1:
            common["drives"] = [{"sequence": p.drive.name, "first_stamp": float(p.stamps[0]),
                                 "keyframes": len(p.frames)} for p in plans]
        if mounting:  # in the plan's order, as every other per-drive field (the same bytes)
            common["mounting"] = {p.drive.name: mounting[p.drive.name] for p in plans if p.drive.name in mounting}
        common["mounting_source"] = {p.drive.name: sources[p.drive.name] for p in plans}
        if refined:
            common["pose_refinement"] = {p.drive.name: refined[p.drive.name] for p in plans}
        common.update(params or {})
        try:
            if kind == "block":
                entries, p = _blocks(tasks, target, plans, block_size_m, voxel_size_m, deskew, dynamic)
            else:
                entries, p = _tiles(tasks, target, plans, tile_size_m, voxel_size_m, deskew,
                                    int(chunk_keyframes), dynamic)
                common["chunk_keyframes"] = int(chunk_keyframes)
        except MapError:  # e.g. no points left: because the scans could not be read, say so
            if tasks.skipped():
                check_skipped(tasks.skipped(), sum(len(p.frames) for p in plans))
            raise
        skipped = tasks.skipped()
        if skipped:
            common["skipped_keyframes"] = check_skipped(skipped, sum(len(p.frames) for p in plans))
        target.remove_scratch()
        for e in entries:
            writer.add_entry(e)
        writer.params = {**p, **common}
        writer.frame = frames[0]
        store = writer.commit()
    except BaseException:
        tasks.cancel()
        writer.abort()
        raise
    finally:
        tasks.finished()
        tasks.close()
        tasks.side = []  # releases them (a worker that died never ran its own)
        if isinstance(executor, InlineExecutor):
            forget_drives(drives)
    if stats is not None:
        stats.update(tasks=tasks.stats(), drives=len(plans),
                     keyframes=int(sum(len(p.frames) for p in plans)),
                     path_m=float(sum(np.linalg.norm(np.diff(p.positions, axis=0), axis=1).sum()
                                      for p in plans)))
    log.info("%s map %s: %d entries from %d drive(s), %d tasks (%s)", kind, out, len(store),
             len(plans), len(tasks.futures), getattr(executor, "description", executor))
    return store


#: The share of a drive's keyframes a build may skip (scans it cannot read) and still write a map.
MAX_SKIPPED_SHARE = 0.5


def check_skipped(skipped: list[dict], keyframes: int) -> list[dict]:
    """The skipped keyframes of a build (``skipped``: {sequence, frame, error}) of ``keyframes``
    planned: returned for the manifest when few enough remain skipped; MapError saying how many
    could not be read (and the first file's error) when more than :data:`MAX_SKIPPED_SHARE` or
    all of them were."""
    n = len(skipped)
    if n > MAX_SKIPPED_SHARE * keyframes or n >= keyframes:
        raise MapError(f"{n} of {keyframes} keyframes could not be read (first: {skipped[0]['error']}); "
                       f"a map needs at least {1 - MAX_SKIPPED_SHARE:.0%} of them; no map written")
    log.warning("map build: %d of %d keyframes skipped (scans that could not be read)", n, keyframes)
    return skipped


def _remount(tasks: _Tasks, plans: list[DrivePlan], deskew: bool, keyframe_distance_m: float,
             keyframe_angle_deg: float, auto: bool = False,
             translation_tolerance_m: float | None = None) -> tuple[list[DrivePlan], dict, dict]:
    """Each drive's mounting estimated (one task per drive), then each drive with an estimate
    planned again with it (keyframe poses are LiDAR poses). auto: see ``mounting_task``. Returns
    the new plans, ``{drive name: estimate}`` and ``{drive name: {"source": ..., "reason"?}}``."""
    from blockloc.maps.build_tasks import MOUNTING_PAIRS, mounting_task, remounted

    tasks.expect(len(plans))
    found = [f.result() for f in [tasks.submit(mounting_task, p, deskew, MOUNTING_PAIRS, auto,
                                               translation_tolerance_m, name=f"mounting-{n}")
                                  for n, p in enumerate(plans)]]
    sources = {}
    for p, m in zip(plans, found):
        sources[p.drive.name] = {k: m[k] for k in ("source", "reason") if k in m}
        e = m["estimate"]
        if e is None:
            log.log(logging.WARNING if m["source"] == "nominal" else logging.INFO,
                    "%s: LiDAR mounting kept as the sequence gives it (%s%s)", p.drive.name,
                    m["source"], f": {m['reason']}" if "reason" in m else "")
            continue
        log.info("%s: LiDAR mounting from %d of %d keyframe pairs: rotation %s deg, translation "
                 "%s m (body frame; 1-sigma %s deg, %s m)", p.drive.name, e["used"], e["pairs"],
                 e["rotation_deg"], e["translation_m"], e["sigma_deg"], e["sigma_m"])
        if e["translation_estimated"] != "xyz":
            log.info("%s: LiDAR mounting translation nominal on body axes %s: the drive determines x, "
                     "y, z to %s m (null: not observed), not %s m (the fit said %s m)", p.drive.name,
                     "".join(a for a in "xyz" if a not in e["translation_estimated"]),
                     e["translation_uncertainty_m"], e["translation_tolerance_m"], e["translation_solved_m"])
        for note in m["notes"]:
            log.warning("%s: %s", p.drive.name, note)
    todo = [(n, p, m) for n, (p, m) in enumerate(zip(plans, found)) if m["estimate"] is not None]
    tasks.expect(len(todo))
    new = {n: f.result() for n, f in [(n, tasks.submit(plan_drive_task, remounted(p.drive, m["T_body_lidar"]),
                                                       keyframe_distance_m, keyframe_angle_deg,
                                                       name=f"plan-mounted-{n}"))
                                      for n, p, m in todo]}
    return ([new.get(n, p) for n, p in enumerate(plans)],
            {p.drive.name: m["estimate"] for _, p, m in todo}, sources)


def _refine(tasks: _Tasks, plans: list[DrivePlan], deskew: bool, keyframe_distance_m: float,
            keyframe_angle_deg: float, mounting: dict, sources: dict,
            auto: bool = False) -> tuple[list[DrivePlan], dict]:
    """Each drive's keyframe poses refined (one task per drive), then each refined drive planned
    again with them. ``mounting`` ({drive name: estimate}) is updated in place where the
    refinement moved an estimated mounting's rotation. auto: only the drives whose mounting was
    estimated (the others' summary says why not). Returns the new plans and ``{drive name:
    refinement summary}``."""
    from blockloc.geometry import so3_log
    from blockloc.maps.build_tasks import refine_task, reposed

    # auto: the mapping drives with body poses whose mounting the build estimated; the
    # refinement's gain is mostly that mounting's forward translation (docs/bench/accuracy_seeds.md),
    # and a drive with LiDAR poses (a SLAM output such as the real walk's BALM poses) was no better
    def wanted(p: DrivePlan) -> bool:
        return not auto or sources[p.drive.name]["source"] == "estimated"

    chosen = [p for p in plans if wanted(p)]
    tasks.expect(len(chosen))
    futures = {p.drive.name: tasks.submit(refine_task, p, deskew, sources[p.drive.name]["source"] != "estimated",
                                          name=f"refine-{n}") for n, p in enumerate(chosen)}
    not_chosen = {"summary": {"skipped": "poses of the LiDAR or mounting not estimated (map.refine_poses auto: "
                                         "only drives whose mounting the build estimated; --refine-poses: every drive)"}}
    found = [futures[p.drive.name].result() if p.drive.name in futures else not_chosen for p in plans]
    summaries, todo = {}, []
    for n, (p, r) in enumerate(zip(plans, found)):
        summaries[p.drive.name] = r["summary"]
        if "skipped" in r["summary"]:
            # a warning only where every drive was asked for (--refine-poses); by default a drive
            # without revisits is common and map info says why
            (log.warning if not auto else log.info)("%s: mapping poses not refined, kept as they came (%s)",
                                                    p.drive.name, r["summary"]["skipped"])
            continue
        log.info("%s: mapping poses refined against the drive's scans: %d neighbour and %d revisit "
                 "pairs, moved by %.3f m median (at most %.3f m)", p.drive.name, r["summary"]["odometry_pairs"],
                 r["summary"]["loop_pairs"], r["summary"]["shift_median_m"], r["summary"]["shift_max_m"])
        todo.append((n, p, r))
        e = mounting.get(p.drive.name)
        if e is not None:  # rotation and forward translation estimated again with the poses
            X, X0 = r["T_body_lidar"], np.asarray(e["T_body_lidar_nominal"], np.float64)
            mounting[p.drive.name] = {**e, "T_body_lidar": np.round(X, 9).tolist(),
                                      "rotation_deg": np.round(np.rad2deg(so3_log(X[:3, :3] @ X0[:3, :3].T)), 4).tolist(),
                                      "translation_m": np.round(X[:3, 3] - X0[:3, 3], 4).tolist(),
                                      "refined_with_poses": True}
    tasks.expect(len(todo))
    new = {n: f.result() for n, f in [(n, tasks.submit(plan_drive_task, reposed(p.drive, r), keyframe_distance_m,
                                                       keyframe_angle_deg, name=f"plan-refined-{n}"))
                                      for n, p, r in todo]}
    return [new.get(n, p) for n, p in enumerate(plans)], summaries


def build_block_map_from_sequence(seq, *, out: str | Path, max_frames: int | None = None,
                                  **settings):
    """Block map from one mapping sequence and its ``mapping_poses()`` (its first ``max_frames``
    frames), written atomically to ``out``: :func:`build_map_from_drives` with one drive;
    ``settings``: its keyword arguments (block_size_m, keyframe_distance_m, keyframe_angle_deg,
    voxel_size_m, deskew, executor, progress, overwrite). Returns the opened store."""
    return build_map_from_drives([Drive.of(seq, stop=max_frames)], "block", out, **settings)


def build_grid_map_from_sequence(seq, *, out: str | Path, max_frames: int | None = None,
                                 **settings):
    """Grid store from one mapping sequence (tile_size_m and the rest of ``settings`` as for
    :func:`build_block_map_from_sequence`): each tile holds the voxel filter of its points."""
    return build_map_from_drives([Drive.of(seq, stop=max_frames)], "grid", out, **settings)


def _open_writer(out, kind: str, overwrite: bool):
    from blockloc.maps.remote import is_url
    from blockloc.maps.store import MapWriter

    if is_url(out):
        return UrlMapWriter(str(out), kind, overwrite=overwrite)
    w = MapWriter(out, kind, overwrite=overwrite)
    (w.tmp / SCRATCH).mkdir()
    return w


class UrlMapWriter:
    """A store written straight to a URL prefix (``s3://bucket/maps/city``, any writable fsspec
    URL), with the interface of :class:`~blockloc.maps.store.MapWriter` the plan uses.

    An object store has no rename, so the order of the writes is the commit: an ``.incomplete``
    marker first (:func:`~blockloc.maps.store.open_map` refuses a store holding one), then the
    entries (written by the tasks), then the kind's extra files and last the manifest, then the
    marker goes. ``overwrite`` deletes the old manifest first, so no reader mixes old and new
    files. :meth:`abort` deletes everything under the prefix (it held nothing or a replaced
    store).
    """

    def __init__(self, url: str, kind: str, *, frame: str = "map", overwrite: bool = False):
        from fsspec.core import url_to_fs

        from blockloc.maps.store import INCOMPLETE_MARKER, MANIFEST_NAME

        self.tmp = str(url).rstrip("/")
        self.kind, self.frame, self.params = kind, frame, {}
        self.entries: list = []
        self._fs, self._root = url_to_fs(self.tmp)
        names = [Path(n).name for n in self._fs.ls(self._root, detail=False)] \
            if self._fs.isdir(self._root) else []
        if names and MANIFEST_NAME not in names:
            raise MapError(f"{self.tmp}: holds files but no map store; not writing a map there")
        if MANIFEST_NAME in names:
            if not overwrite:
                raise MapError(f"{self.tmp}: already holds a map store (choose another --out, or "
                               "--overwrite to replace it)")
            self._fs.rm(f"{self._root}/{MANIFEST_NAME}")
        self._fs.pipe_file(f"{self._root}/{INCOMPLETE_MARKER}",
                           f"build started by pid {os.getpid()}\n".encode())

    def add_entry(self, entry):
        self.entries.append(entry)
        return entry

    def commit(self):
        """Extra files, then the manifest, then the marker goes; returns the opened store."""
        import tempfile

        from blockloc.maps.store import INCOMPLETE_MARKER, MANIFEST_NAME, MapWriter, open_map

        with tempfile.TemporaryDirectory(prefix="blockloc-manifest-") as tmp:
            staging = MapWriter(Path(tmp) / "m", self.kind, frame=self.frame, params=self.params)
            for e in self.entries:
                staging.add_entry(e)
            staging.commit()  # writes the extras and the manifest (the entries are remote)
            made = sorted(p.name for p in (Path(tmp) / "m").iterdir())
            for name in [n for n in made if n != MANIFEST_NAME] + [MANIFEST_NAME]:
                self._fs.pipe_file(f"{self._root}/{name}", (Path(tmp) / "m" / name).read_bytes())
        self._fs.rm(f"{self._root}/{INCOMPLETE_MARKER}")
        log.info("wrote %s map %s: %d entries", self.kind, self.tmp, len(self.entries))
        return open_map(self.tmp, cache_dir=False)

    def abort(self) -> None:
        try:
            if self._fs.exists(self._root):
                self._fs.rm(self._root, recursive=True)
        except OSError as exc:
            log.warning("%s: could not remove the failed build (%s)", self.tmp, exc)


def _entry(r: dict, entry_id: str, keyframes: np.ndarray | None = None):
    from blockloc.maps.store import MapEntry

    return MapEntry(entry_id, r["file"], np.asarray(r["bounds_min"], float),
                    np.asarray(r["bounds_max"], float), np.asarray(r["centroid"], float),
                    int(r["num_points"]), int(r["bytes"]), r["sha256"], keyframes)


def _blocks(tasks: _Tasks, target: BuildTarget, plans: list[DrivePlan], block_size_m: float,
            voxel_size_m: float, deskew: bool, dynamic=None):
    """Algorithm 1 over the drives' keyframes: candidate tasks, decisions here, merge and write
    tasks. dynamic: None, or the ``DynamicParams`` moving objects are left out with. Returns
    (entries, parameters)."""
    from blockloc.maps.block_maps import KEYFRAMES_PER_RUN, BlockLedger, CandidateSegmenter

    positions = np.concatenate([p.positions for p in plans])
    frames = np.concatenate([p.frames for p in plans])
    candidates = []  # (drive number, Candidate); keys index the concatenated keyframes
    base = 0
    for d, plan in enumerate(plans):
        seg = CandidateSegmenter(block_size_m)
        for k in range(len(plan.frames)):
            closed = seg.add(base + k, positions[base + k])
            if closed is not None:
                candidates.append((d, closed))
        tail = seg.finish()
        if tail is not None:
            candidates.append((d, tail))
        base += len(plan.frames)
    # every candidate: a task per run of its keyframes (read, deskew, voxel sums), one that adds
    # the runs' sums up, then a merge or a write (or nothing: a skip)
    runs = [[c.keys[i:i + KEYFRAMES_PER_RUN] for i in range(0, len(c.keys), KEYFRAMES_PER_RUN)]
            for _, c in candidates]
    tasks.expect(sum(len(r) for r in runs) + 2 * len(candidates))
    n_keys = max(1, base)
    starts = np.cumsum([0] + [len(p.frames) for p in plans])  # each drive's first key

    def moving(d: int, keys):
        return None if dynamic is None else dynamic_filter(plans[d], np.asarray(keys) - starts[d], dynamic)

    run_futures = [[tasks.submit(block_run_task, plans[d].drive, frames[keys].tolist(), voxel_size_m,
                                 deskew, target, f"{SCRATCH}/run-{n}-{i}.bin", moving(d, keys),
                                 name=f"run-{n}-{i}", locality=float(keys[0]) / n_keys)
                    for i, keys in enumerate(runs[n])]
                   for n, (d, _) in enumerate(candidates)]
    futures = [tasks.submit(block_candidate_task, target, voxel_size_m,
                            f"{SCRATCH}/candidate-{n}.npy", *run_futures[n], name=f"candidate-{n}",
                            priority=5)
               for n in range(len(candidates))]
    ledger = BlockLedger(block_size_m)
    versions: list[str] = []  # scratch name of each block's latest points
    writers: list = []  # the task that wrote it (a dependency of the next merge or the write)
    boxes: list[tuple[np.ndarray, np.ndarray]] = []  # bounds of each block's points
    merging: dict[int, Any] = {}  # block -> its latest merge task, centroid not known yet

    def resolve(blocks) -> None:
        for j in blocks:
            ledger.renew(j, merging.pop(j).result()["centroid"])

    drive = None
    for n, (d, cand) in enumerate(candidates):
        if d != drive:
            ledger.start_drive()
            drive = d
        r = futures[n].result()
        if r["name"] is None:
            log.debug("candidate %d (%s): no points, no block", n, plans[d].drive.name)
            continue
        ev = ledger.decide(cand.keys, r["centroid"], cand.short, resolve)
        j = ev.block
        if ev.action == "new":
            versions.append(r["name"])
            writers.append(futures[n])
            boxes.append((r["lo"], r["hi"]))
            log.info("block %03d: %d keyframes, %d points", j, len(cand.keys), r["num_points"])
        elif ev.action in ("merge", "tail"):
            lo, hi = np.minimum(boxes[j][0], r["lo"]), np.maximum(boxes[j][1], r["hi"])
            boxes[j] = (lo, hi)
            name = f"{SCRATCH}/block-{j}-{n}.npy"
            merging[j] = writers[j] = tasks.submit(
                block_merge_task, target, versions[j], r["name"], name, voxel_size_m, writers[j],
                futures[n], name=f"merge-{j}-{n}", priority=10)
            versions[j] = name
            ledger.hold(j, lo - _BOX_PAD_M, hi + _BOX_PAD_M)
    if not versions:
        raise MapError(f"{' + '.join(p.drive.name for p in plans)}: no points in any keyframe, "
                       "no block to write")
    resolve(list(merging))
    writes = [tasks.submit(block_write_task, target, versions[j], f"{j:03d}.pcd", writers[j],
                           name=f"write-{j:03d}", priority=5) for j in range(len(versions))]
    entries = []
    for j, f in enumerate(writes):
        keys = ledger.covered_keys(j)
        entries.append(_entry(f.result(), f"{j:03d}", positions[keys].reshape(-1, 3)))
    p = {"block_size_m": float(block_size_m), "voxel_size_m": float(voxel_size_m),
         "num_keyframes": int(len(positions)), "events": ledger.event_counts()}
    if dynamic is not None:
        p["remove_dynamic"] = _dynamic_record(dynamic, [f.result() for fs in run_futures for f in fs])
    return entries, p


def _dynamic_record(dynamic, results: list[dict]) -> dict:
    """The manifest's ``remove_dynamic``: the evidence settings and the points left out."""
    import dataclasses

    from blockloc.maps.build_tasks import DYNAMIC_CONTEXT_KEYFRAMES

    return {**dataclasses.asdict(dynamic), "context_keyframes": DYNAMIC_CONTEXT_KEYFRAMES,
            "moving_points": int(sum(r.get("moving_points", 0) for r in results)),
            "raw_points": int(sum(r.get("raw_points", 0) for r in results))}


def _tiles(tasks: _Tasks, target: BuildTarget, plans: list[DrivePlan], tile_size_m: float,
           voxel_size_m: float, deskew: bool, chunk: int, dynamic=None):
    """Grid tiles: chunk tasks (read, deskew, with ``dynamic`` (``DynamicParams``) moving objects
    left out, bin, sum by voxel), then one task per tile. Returns (entries, parameters)."""
    from blockloc.maps.grid_tiles import name_decimals, tile_name

    chunks = [(d, i, plan.frames[i:i + chunk].tolist()) for d, plan in enumerate(plans)
              for i in range(0, len(plan.frames), chunk)]
    tasks.expect(len(chunks))
    futures = [tasks.submit(grid_chunk_task, plans[d].drive, fr, tile_size_m, voxel_size_m, deskew,
                            target, f"{SCRATCH}/chunk-{n}.bin",
                            None if dynamic is None else dynamic_filter(plans[d], np.arange(i, i + len(fr)), dynamic),
                            name=f"chunk-{n}")
               for n, (d, i, fr) in enumerate(chunks)]
    parts: dict[tuple[int, int], list[tuple[str, int, int]]] = {}
    for f in futures:  # in plan order: a tile's parts are merged in the same order every time
        r = f.result()
        for ix, iy, r0, r1 in r["tiles"]:
            parts.setdefault((int(ix), int(iy)), []).append((r["name"], int(r0), int(r1)))
    if not parts:
        raise MapError(f"{' + '.join(p.drive.name for p in plans)}: no points in any keyframe, "
                       "no tile to write")
    dec = name_decimals(tile_size_m)
    cells = sorted(parts)
    names = [tile_name(ix, iy, tile_size_m, dec) for ix, iy in cells]
    batches = [list(zip(cells[i:i + TILES_PER_TASK], names[i:i + TILES_PER_TASK]))
               for i in range(0, len(cells), TILES_PER_TASK)]
    tasks.expect(len(batches))
    writes = [tasks.submit(grid_tile_task, target, [(c, parts[c], f"{nm}.pcd") for c, nm in batch],
                           tile_size_m, voxel_size_m, name=f"tiles-{n}") for n, batch in enumerate(batches)]
    entries = [_entry(r, nm) for f, batch in zip(writes, batches)
               for r, (_, nm) in zip(f.result()["entries"], batch)]
    log.info("tiled %d points into %d tiles of %.3g m", sum(e.num_points for e in entries),
             len(entries), tile_size_m)
    p = {"tile_size_m": tile_size_m, "origin": [0.0, 0.0], "name_decimals": dec,
         "voxel_size_m": float(voxel_size_m), "num_keyframes": int(sum(len(p.frames) for p in plans))}
    if dynamic is not None:
        p["remove_dynamic"] = _dynamic_record(dynamic, [f.result() for f in futures])
    return entries, p
