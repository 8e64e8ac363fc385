"""The recipes the commands, the benchmarks (and a live node) share: open a session on a sequence
in its map, run global initialization on one frame, build a map (and its place index), prepare
the demo's small world, write a run's report.

No printing, no progress bars, no signal handling here (the commands do those): a long recipe
takes a ``progress(done, total)`` callback, a ``say(message)`` callback, or ``should_stop()``.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import re
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from blockloc.app.assemble import build_engine, build_session, make_localizer, open_store, place_index_params
from blockloc.app.catalog import SequenceRef, map_kind_for_backend, map_params, open_sequence
from blockloc.app.session import RunResult, Session
from blockloc.config import Config, MapConfig, load_config
from blockloc.datasets.base import SequenceView
from blockloc.errors import BlocklocError, DatasetError, GlobalInitError, MapError, OutputWriteError
from blockloc.geometry import T_to_xyzrpy
from blockloc.global_init.place_index import PLACE_INDEX_NAME, write_place_index
from blockloc.global_init.relocalize import pose_error
from blockloc.jit import CompileClock
from blockloc.maps.build_plan import Drive, build_map_from_drives
from blockloc.maps.files import open_map_files
from blockloc.maps.mounting import with_map_mounting
from blockloc.maps.store import MapStore, open_map
from blockloc.maps.summary import map_points_xy
from blockloc.global_init.scan_prep import prepare_for_init
from blockloc.viz.layout import REPORT_NAME
from blockloc.viz.report import write_report

log = logging.getLogger("blockloc")

Progress = Callable[[int, int | None], None]


# ----------------------------------------------------------------------------- tracking
def resolve_map(ref: SequenceRef, map_path: str | None, backend: str, cfg: Config, data_root: str | None) -> str:
    """``--map``, else ``map.path`` of the config, else the sequence's default map (which must
    exist: MapError with the command that builds it)."""
    path = map_path or cfg.map.path or None
    if path is not None:
        return str(path)
    kind = map_kind_for_backend(backend)
    default = ref.default_map_path(kind, data_root=data_root, dataset_cfg=cfg.dataset,
                                   map_params=map_params(cfg.map, kind))
    if not open_map_files(default).exists("manifest.json"):
        raise MapError(f"map for {ref.text} not found at {default}; build it with: {ref.build_hint(kind, default)}")
    return str(default)


def open_session(seq: str, *, cfg: Config, map_path: str | None = None, backend: str | None = None,
                 data_root: str | None = None, observers=(), out_dir: Path | None = None,
                 keep_estimates: bool = False, lidar_topic: str | None = None,
                 imu_topic: str | None = None, poses=None) -> Session:
    """The Session for ``--seq`` in its map (what ``track`` and the benchmarks run)."""
    ref = SequenceRef.parse(seq)
    backend = backend or cfg.map.backend
    sequence = ref.open(data_root=data_root, dataset_cfg=cfg.dataset, lidar_topic=lidar_topic, imu_topic=imu_topic,
                        poses=poses, want_imu=cfg.tracking.use_imu)
    path = resolve_map(ref, map_path, backend, cfg, data_root)
    store = open_store(path, cfg.map)
    # `--seq` (and `--poses`) as `map changes --run` / `map update --run` can open it again (a path
    # made absolute: the run may be read from another directory); metrics.json's "sequence" is the
    # display name
    facts = {"map": path, "sequence_arg": str(ref.path.resolve()) if ref.path is not None else ref.text}
    if isinstance(poses, (str, os.PathLike)):
        facts["poses_arg"] = str(Path(poses).resolve())
    return build_session(cfg, sequence, store, backend=backend, observers=observers, out_dir=out_dir,
                         keep_estimates=keep_estimates, facts=facts)


def track(session: Session, *, mode: str, hint=None, max_frames: int | None = None,
          progress: Progress | None = None, should_stop: Callable[[], bool] | None = None) -> RunResult:
    """Run a session from its first frame (``max_frames`` of them, or all): initialize (``mode``
    gt | pose | global, ``hint`` (x, y, yaw or None) for pose), step, finish. A results file that
    cannot be written (disk full, the folder removed) ends the run with OutputWriteError naming
    the file, the cause and what was kept (:func:`stopped_note`)."""
    try:
        return session.run(0, max_frames, init=mode, pose_hint=hint, progress=progress, should_stop=should_stop)
    except OutputWriteError as exc:
        total = len(session.stamps) if max_frames is None else min(max_frames, len(session.stamps))
        out_dir = Path(session.out_dir) if session.out_dir is not None else None
        raise OutputWriteError(exc.path, exc.cause, stopped_note(session, total, out_dir)) from None


def stopped_note(session: Session, total: int, out_dir: Path | None) -> str:
    """What a run stopped by an output it could not write kept: frames done, whether its metrics
    were written, the temporary files left (named, to be removed or kept by the user)."""
    done = len(session.diagnostics)
    note = f"tracking stopped after {done} of {total} frames; every row written is whole"
    if out_dir is not None:
        written = session.output_error is None and (out_dir / "metrics.json").is_file()
        note += "; metrics.json " + ("written" if written else "not written")
        left = sorted(p.name for p in out_dir.glob("*.partial")) if out_dir.is_dir() else []
        if left:
            note += f"; left: {', '.join(left)}"
    return note


def write_run_report(session: Session, res: RunResult, out_dir: Path, quiet: bool = False) -> Path | None:
    """``report.html`` in the results folder: metrics, plots, config and an interactive top view.
    quiet: the run already failed (its error is on its way): a report that cannot be written is
    logged in one line (None returned) instead of replacing that error."""
    try:
        return _write_run_report(session, res, out_dir)
    except (OSError, BlocklocError) as exc:
        if not quiet:
            raise
        log.error("report not written: %s", exc)
        return None


def _write_run_report(session: Session, res: RunResult, out_dir: Path) -> Path:
    images = {caption: out_dir / name for caption, name in (("trajectories", "trajectories.png"),
                                                             ("errors over time", "errors.png"),
                                                             ("error breakdown", "error_breakdown.png"))
              if (out_dir / name).is_file()}
    return write_report(out_dir / REPORT_NAME, metrics=res.metrics, estimate=res.trajectory,
                        ground_truth=session.ground_truth, diagnostics=res.diagnostics, config=session.config,
                        map_xy=map_points_xy(session.store) if session.store is not None else None,
                        map_entries=session.run_info().map_entries, images=images,
                        title=f"{res.metrics.get('sequence')}")


class _FrameTap(SequenceView):
    """A sequence that remembers the last frame it handed out (``last``): the frame the session is
    stepping, for an observer that needs its raw points (the observers' events carry none)."""

    def __init__(self, seq) -> None:
        super().__init__(seq)
        self.last = None

    def frames(self, start: int = 0, stop: int | None = None):
        for frame in self.inner.frames(start, stop):
            self.last = frame
            yield frame


class LiveChanges:
    """``track --detect-changes``: a run observer feeding the change detector
    (:class:`~blockloc.maps.changes.pipeline.ChangeDetector`) every frame as the session emits it:
    the frame's pose and status (trusted by the rule ``map changes`` reads a run folder with,
    :class:`~blockloc.maps.changes.runs.TrustedFrames`) and its raw scan, taken from the
    sequence as the session steps it (nothing read twice). A used frame waits one trusted frame
    for the pose after it (deskewing). Statuses and poses are final when emitted (``poses.tum``
    and ``diagnostics.csv`` write them as they come), so no other lag is needed.

    ``attach(session)`` before the run (it wraps ``session.seq``); :meth:`result` at any time
    after (the frames fed so far); ``error``: what stopped it (logged in one line; the frames after
    it are not fed, tracking goes on), or None."""

    def __init__(self, stride: int = 1, settle_frames: int = 10) -> None:
        self.stride, self.settle_frames = int(stride), int(settle_frames)
        self.detector = None
        self.error: BaseException | None = None
        self.frames_tracked = 0
        self._tap: _FrameTap | None = None

    def attach(self, session: Session) -> None:
        self.begin(session)
        self._tap = _FrameTap(session.seq)
        session.seq = self._tap

    def begin(self, session: Session, warm: bool = True) -> None:
        """The detector for ``session``'s map and sensor, without wrapping its sequence: for a
        caller that steps the session itself (the live node) and feeds :meth:`add` the frames.
        warm: load the detector's compiled kernels now (:meth:`ChangeDetector.warm_up`), in this
        thread; else the caller does it (the node, on the detector's own thread)."""
        from blockloc.maps.changes.pipeline import ChangeDetector

        info = session.seq.info
        self.detector = ChangeDetector(session.store, info.T_body_lidar, info.gravity_map, stride=self.stride)
        self.restart_trust()
        if warm:
            self.detector.warm_up()

    def restart_trust(self) -> None:
        """Trust starts over: the next ``settle_frames`` ok frames are not trusted
        (:class:`~blockloc.maps.changes.runs.TrustedFrames`). Call it in the thread and order of
        :meth:`trusted`."""
        from blockloc.maps.changes.runs import TrustedFrames

        self._trusted = TrustedFrames(self.settle_frames)

    def restart(self, trust: bool = True) -> None:
        """The source restarted (a live stream's stamps jumped back): trust starts over (``trust``:
        here; the node does it in its own thread, :meth:`restart_trust`) and the detector lets go
        of the poses before it (:meth:`ChangeDetector.restart`: a scan waiting for the pose after
        it is never deskewed with a pose of the restarted stream). A failure stops detection."""
        if trust:
            self.restart_trust()
        if self.detector is None or self.error is not None:
            return
        try:
            self.detector.restart()
        except Exception as exc:  # noqa: BLE001 - tracking goes on; the command reports it at the end
            self.error = exc
            log.error("change detection stopped at a source restart: %s (tracking goes on)", exc)

    def start(self, info) -> None:
        pass

    def frame(self, event) -> None:
        if self.detector is None or self.error is not None:
            return
        trusted = self.trusted(event.status, event.T_map_body)
        self.add(event.index, event.stamp, event.T_map_body, trusted, self._tap.last if self._tap is not None else None)

    def trusted(self, status: str, T_map_body) -> bool:
        """The run folder's rule (:class:`~blockloc.maps.changes.runs.TrustedFrames`) on the
        next emitted frame's status, in order: call it once per frame, before :meth:`add`."""
        return self._trusted(status) and T_map_body is not None

    def add(self, index: int, stamp: float, T_map_body, trusted: bool, frame) -> None:
        """One emitted frame, in order: its pose (map frame, (4, 4) or None), whether it is
        trusted (:meth:`trusted`) and its raw scan (the ``LidarFrame`` the session stepped; only
        read when trusted; None for a trusted frame the stride skips is allowed, the detector
        refuses it for a used one). A failure stops detection (``error``), never the caller."""
        if self.detector is None or self.error is not None:
            return
        self.frames_tracked += 1
        try:
            if trusted and frame is not None and int(frame.index) != int(index):
                raise RuntimeError(f"frame {index}: its scan is not the one the session stepped")
            self.detector.add(stamp, T_map_body, trusted, frame if trusted else None)
        except Exception as exc:  # noqa: BLE001 - tracking goes on; the command reports it at the end
            self.error = exc
            log.error("change detection stopped on frame %d: %s (tracking goes on)", index, exc)

    def finish(self, metrics: dict) -> None:
        pass

    def result(self, interrupted: bool = False):
        """(ChangeResult, cost): what the frames fed so far show (``interrupted``: noted in its
        params), and the detector's cost: wall and CPU time (the detector's thread) per frame
        tracked and per scan processed (p50 / p99 / max, ms), the classification at the end, the
        blocks loaded (``join_*``: the frames blocks joined on; ``per_scan_no_join``: the others), and
        the 1-min load average."""
        det = self.detector
        t0, c0 = time.perf_counter(), time.thread_time()
        notes = {"live": True, "lag_frames": 1}
        if interrupted:
            notes["interrupted"] = True
            notes["note"] = "the run was interrupted: changes from the frames tracked before it"
        res = det.result(**notes)
        final_wall, final_cpu = time.perf_counter() - t0, time.thread_time() - c0
        costs = np.asarray(det.costs, float).reshape(-1, 4)
        wall, cpu = costs[:, 0], costs[:, 1]
        used, joins = costs[:, 2] > 0, costs[:, 3] > 0

        def stats(v):
            if not len(v):
                return {"p50": 0.0, "p99": 0.0, "max": 0.0}
            return {"p50": round(1e3 * float(np.median(v)), 2), "p99": round(1e3 * float(np.percentile(v, 99)), 2),
                    "max": round(1e3 * float(v.max()), 2)}

        tracked = max(self.frames_tracked, 1)
        scans = max(res.scans_used + res.scans_rejected, 1)
        total_wall, total_cpu = float(wall.sum()) + final_wall, float(cpu.sum()) + final_cpu
        cost = {"wall_s": round(total_wall, 3), "cpu_s": round(total_cpu, 3), "frames_tracked": self.frames_tracked,
                "wall_ms_per_scan_used": round(1e3 * total_wall / scans, 1),
                "cpu_ms_per_scan_used": round(1e3 * total_cpu / scans, 1),
                "wall_ms_per_frame_tracked": round(1e3 * total_wall / tracked, 1),
                "cpu_ms_per_frame_tracked": round(1e3 * total_cpu / tracked, 1),
                "per_frame_cpu_ms": stats(cpu), "per_frame_wall_ms": stats(wall),
                "per_scan_cpu_ms": stats(cpu[used]), "per_scan_wall_ms": stats(wall[used]),
                # the steady state, and the frames on which blocks joined (loaded, voxelized)
                "per_scan_no_join_cpu_ms": stats(cpu[used & ~joins]),
                "join_frames": int(joins.sum()), "join_cpu_ms": stats(cpu[joins]),
                "final_wall_s": round(final_wall, 3), "final_cpu_s": round(final_cpu, 3),
                # imports and compiled kernels loaded before the first frame (ChangeDetector.warm_up)
                "startup_wall_s": round(det.startup[0], 3) if det.startup else None,
                "startup_cpu_s": round(det.startup[1], 3) if det.startup else None,
                "blocks_loaded": len(res.block_keys), "blocks_in_map": len(det.store.ids),
                "cpu_clock": "thread_time (the detector's own thread)",
                "load_1min": round(os.getloadavg()[0], 1)}
        return res, cost


def write_live_changes(live: LiveChanges, session: Session, out_dir: Path, interrupted: bool = False,
                       during: str = "track --detect-changes", cost: dict | None = None) -> dict:
    """``track --detect-changes``: what :class:`LiveChanges` accumulated, written as
    ``out_dir/changes.json`` (atomically) and drawn into its ``run.mcap`` and ``report.html``.
    Returns the changes document with its ``cost``."""
    from blockloc.app.lifelong import write_changes

    res, measured = live.result(interrupted=interrupted)
    return write_changes(res, session.store, Path(out_dir) / "changes.json", out_dir,
                         map=str(session.facts.get("map")), run=str(out_dir), sequence=str(session.info.name),
                         during=during, cost={**measured, **(cost or {})})


# ----------------------------------------------------------------------------- global init
def search_seconds(localizer_s: float, wall_s: float, compile_s: float) -> float:
    """Seconds the search took without compiling: the localizer's own clock, or the call's wall time less
    the compile, whichever is smaller.

    The compile can fall outside the part the localizer times itself, so it comes off the call's wall
    time, never off ``localizer_s`` (that gave CI a negative time: 0.4 s timed, 0.9 s compiled before).
    """
    return max(0.0, min(localizer_s, wall_s - compile_s))


def run_init(seq_name: str, frame_index: int, map_path: str, *, cfg: Config, hint: tuple | None = None,
             window_m: float | None = None, yaw_window_deg: float | None = None, data_root: str | None = None,
             poses=None) -> tuple:
    """Global initialization of frame ``frame_index`` of a sequence in a map store, the scan
    prepared as tracking prepares it. hint: (x, y, yaw or None), map frame, m and rad, or None
    (the whole map). Returns (InitResult, summary dict for printing/JSON); with ground truth the
    summary holds the pose error. Raises BlocklocError on bad input."""
    gi = cfg.global_init
    window_m = gi.window_m if window_m is None else window_m
    yaw_window_deg = gi.yaw_window_deg if yaw_window_deg is None else yaw_window_deg
    x, y, hint_yaw = hint if hint is not None else (None, None, None)
    if not (window_m > 0 and math.isfinite(window_m)):
        raise GlobalInitError(f"--window {window_m}: expected a positive size in metres")
    if not (0 < yaw_window_deg <= 360):
        raise GlobalInitError(f"--yaw-window {yaw_window_deg}: expected an angle in (0, 360] degrees")
    seq = open_sequence(seq_name, data_root=data_root, dataset_cfg=cfg.dataset, poses=poses)
    if not 0 <= frame_index < len(seq):
        raise GlobalInitError(f"--frame {frame_index}: expected 0..{len(seq) - 1} ({seq.info.name} has "
                              f"{len(seq)} frames)")
    t_open = time.perf_counter()
    store = open_store(map_path, cfg.map)
    seq = with_map_mounting(seq, store, cfg.map.use_map_mounting)  # as track does (issue 41)
    engine = build_engine(cfg.registration, resolution_m=gi.ndt_resolution_m)
    loc = make_localizer(store, seq.info.gravity_map, cfg, engine=engine)
    open_s = time.perf_counter() - t_open
    scan = prepare_for_init(seq.frame(frame_index), seq.imu(), seq.info)
    t0, c0 = time.perf_counter(), time.process_time()
    with CompileClock() as jit:
        res = loc.localize(scan.points_body, scan.gravity_body, None if x is None else (x, y), hint_yaw,
                           window_m, yaw_window_deg if hint_yaw is not None else 360.0)
    t1, c1 = time.perf_counter(), time.process_time()
    summ = init_summary(res, scan.stamp)
    # search and refinement: not process start, map opening, loading the place index, nor compiling
    # the kernels on the first run after an install (compile_s)
    summ["time_s"] = round(search_seconds(float(res.time_s), t1 - t0, jit.seconds), 3)
    summ["compile_s"] = round(jit.seconds, 3)
    summ["cold"] = cold_start(open_s, t1 - t0, res.stats, jit.seconds)
    summ["cold"]["first_call_cpu_s"] = round(c1 - c0, 3)  # CPU time of every thread (compiling included)
    gt = seq.ground_truth()
    if gt is not None and gt.stamps[0] <= scan.stamp <= gt.stamps[-1]:
        Tg = gt.interpolate(np.array([scan.stamp]))[0]
        gx, gy, _, _, _, gyaw = (float(v) for v in T_to_xyzrpy(Tg))
        summ["gt"] = {"x": gx, "y": gy, "yaw": gyaw}
        if res.T_map_body is not None:
            err_m, err_deg = pose_error(np.asarray(res.T_map_body), Tg)
            summ["error_m"], summ["error_deg"] = round(err_m, 4), round(err_deg, 4)
    return res, summ


def cold_start(open_s: float, first_call_s: float, stats: dict, compile_s: float = 0.0) -> dict:
    """The cold start of a fresh process, seconds: ``total_s`` from opening the map store to the
    answer of the first search (``map_open_s`` the store and the localizer, ``index_load_s`` the
    place index, the rest the search, which reads the blocks' pyramids and points from disk or the
    on-disk cache), without numba's one-off compilation (``compile_s``, first run after an install).
    Wall clock: on a loaded machine ``first_call_cpu_s`` (set by the caller) says more."""
    return {"total_s": round(max(0.0, open_s + first_call_s - compile_s), 3), "map_open_s": round(open_s, 3),
            "index_load_s": round(float(stats.get("index_load_s", 0.0)), 3),
            # (index_load_s is without its compile, which compile_s holds: never below 0 when they overlap)
            "search_s": round(max(0.0, first_call_s - compile_s - float(stats.get("index_load_s", 0.0))), 3)}


def init_summary(res, stamp: float | None = None) -> dict:
    """JSON-ready dict: x, y, z (m), roll, pitch, yaw (rad) of T_map_body, score, fitness, ..."""
    out: dict = {"verified": bool(res.verified), "ambiguous": bool(res.ambiguous),
                 "score": round(float(res.score), 4), "fitness": round(float(res.fitness), 4),
                 "time_s": round(float(res.time_s), 3), "num_candidates": len(res.candidates)}
    if stamp is not None:
        out["stamp"] = float(stamp)
    out["pose"] = None  # x, y, z (m), roll, pitch, yaw (rad); also flat, below
    if res.T_map_body is not None:
        x, y, z, roll, pitch, yaw = (float(v) for v in T_to_xyzrpy(res.T_map_body))
        out.update(x=x, y=y, z=z, roll=roll, pitch=pitch, yaw=yaw)
        out["pose"] = {"x": x, "y": y, "z": z, "roll": roll, "pitch": pitch, "yaw": yaw}
    out["candidates"] = [
        dict(zip(("x", "y", "z", "roll", "pitch", "yaw"), (round(float(v), 4) for v in T_to_xyzrpy(c.T_map_body))),
             score=round(c.score, 4), fitness=round(c.fitness, 4), verified=c.verified)
        for c in res.candidates]
    out["stats"] = {k: (round(v, 4) if isinstance(v, float) else v) for k, v in res.stats.items()}
    return out


# ----------------------------------------------------------------------------- maps
def build_map(seq, kind: str, out: str | Path, map_cfg: MapConfig, *, overwrite: bool = False,
              progress: Progress | None = None, max_frames: int | None = None, executor=None,
              calibrate_mounting: bool | None = None, refine_poses: bool | None = None,
              remove_dynamic: bool | None = None) -> MapStore:
    """Build a block or grid store from a mapping sequence with the ``MapConfig`` settings.
    progress: a ``(done, total)`` callback or None. executor: None (serial) or a Dask executor
    (:func:`blockloc.maps.distributed.open_executor`). calibrate_mounting: as
    :func:`build_map_from_specs`."""
    return build_map_from_specs([Drive.of(seq, stop=max_frames)], kind, out, map_cfg,
                                overwrite=overwrite, progress=progress, executor=executor,
                                calibrate_mounting=calibrate_mounting, refine_poses=refine_poses,
                                remove_dynamic=remove_dynamic)


def build_map_from_specs(drives, kind: str, out: str | Path, map_cfg: MapConfig, *, overwrite: bool = False,
                         progress: Progress | None = None, executor=None,
                         calibrate_mounting: bool | None = None, refine_poses: bool | None = None,
                         remove_dynamic: bool | None = None) -> MapStore:
    """:func:`blockloc.maps.build_plan.build_map_from_drives` with the ``MapConfig`` settings.
    calibrate_mounting: None: ``map.calibrate_mounting`` (true: ``"auto"``, body-pose drives
    only, a failed estimate keeps the nominal mounting); True (``--calibrate-mounting``): every
    drive, a failed estimate is an error; False (``--nominal-mounting``): none. refine_poses: None:
    ``map.refine_poses`` (true: ``"auto"``, the drives whose mounting the build estimated); True /
    False (``--refine-poses``: every drive / ``--no-refine-poses``: none).
    remove_dynamic: None: ``map.remove_dynamic``; True / False (``--remove-dynamic`` /
    ``--keep-dynamic``)."""
    if calibrate_mounting is None:
        calibrate_mounting = "auto" if map_cfg.calibrate_mounting else False
    return build_map_from_drives(
        drives, kind, out, block_size_m=map_cfg.block_size_m, tile_size_m=map_cfg.tile_size_m,
        voxel_size_m=map_cfg.voxel_size_m, keyframe_distance_m=map_cfg.keyframe_distance_m,
        keyframe_angle_deg=map_cfg.keyframe_angle_deg,
        calibrate_mounting=calibrate_mounting, executor=executor, progress=progress,
        overwrite=overwrite, mounting_translation_tolerance_m=map_cfg.mounting_translation_tolerance_m,
        refine_poses=("auto" if map_cfg.refine_poses else False) if refine_poses is None else bool(refine_poses),
        remove_dynamic=bool(map_cfg.remove_dynamic if remove_dynamic is None else remove_dynamic))


@dataclass(frozen=True)
class SequenceSpec:
    """A ``--seq`` value (and its ``--poses``) as a picklable opener: what each Dask worker calls
    to open the drive itself (only this small object travels with the tasks).

    text: sequence name or absolute path; poses: absolute trajectory path or None (the
    sequence's own mapping poses); data_root, dataset_cfg: as for ``SequenceRef.open``.
    """

    text: str
    data_root: str | None = None
    dataset_cfg: Any = None
    poses: str | None = None

    def __call__(self):
        return SequenceRef.parse(self.text).open(data_root=self.data_root,
                                                 dataset_cfg=self.dataset_cfg, poses=self.poses)


#: ``--seq NAME[START:STOP]``: frames START..STOP-1 of a sequence as one drive.
DRIVE_SLICE = re.compile(r"^(?P<seq>.+)\[(?P<start>\d*):(?P<stop>\d*)\]$")


def drive_sequence_name(text: str) -> str:
    """The sequence a ``NAME[START:STOP]`` drive names (``NAME``)."""
    return DRIVE_SLICE.sub(r"\g<seq>", text)


def mapping_sequence(params: dict) -> str | None:
    """The sequence a map store was built from, as ``open_sequence`` takes it: its manifest's first
    drive (``drives``, else ``sequence``, which joins several with " + "), without a
    ``[START:STOP]`` slice; None when the manifest names none."""
    drives = params.get("drives")
    if isinstance(drives, list) and drives and isinstance(drives[0], dict) and drives[0].get("sequence"):
        text = str(drives[0]["sequence"])
    elif params.get("sequence"):
        text = str(params["sequence"]).split(" + ")[0]
    else:
        return None
    return drive_sequence_name(text)


def parse_drive(text: str, poses: str | None = None, *, data_root: str | None = None,
                dataset_cfg: Any = None, max_frames: int | None = None) -> Drive:
    """A ``--seq`` value -> :class:`~blockloc.maps.build_plan.Drive`. ``NAME[START:STOP]`` maps
    frames START..STOP-1 only; paths become absolute (workers may run elsewhere); ``max_frames``
    caps the drive to its first N frames. DatasetError (one line) when the name names nothing."""
    m = DRIVE_SLICE.match(text)
    name = m["seq"] if m else text
    start = int(m["start"] or 0) if m else 0
    stop = int(m["stop"]) if m and m["stop"] else None
    if stop is not None and stop <= start:
        raise DatasetError(f"--seq {text!r}: empty frame range (expected NAME[START:STOP], "
                           "START < STOP)")
    if max_frames is not None:
        stop = start + max_frames if stop is None else min(stop, start + max_frames)
    ref = SequenceRef.parse(name)
    if ref.path is not None:
        name = str(Path(name).expanduser().resolve())
    if poses:
        if not Path(poses).expanduser().exists():
            raise DatasetError(f"--poses {poses}: no such trajectory file")
        poses = str(Path(poses).expanduser().resolve())
    spec = SequenceSpec(name, None if data_root is None else str(data_root), dataset_cfg, poses)
    key = f"{name}|{poses}|{data_root}"
    return Drive(text, spec, key, start, stop)


def add_place_index(path: str | Path, gravity_map, cfg: Config) -> MapStore:
    """Build the place index (no-hint relocalization) of the local store at ``path`` with the
    ``global_init`` settings of ``cfg`` and add it to the store; returns the reopened store."""
    t0 = time.perf_counter()
    store, index = write_place_index(path, gravity_map, place_index_params(cfg.global_init))
    log.info("place index: %d places, %d bytes in %.1f s", len(index), store.extras[PLACE_INDEX_NAME].bytes,
             time.perf_counter() - t0)
    return store


# ----------------------------------------------------------------------------- the demo's world
DEMO_PRESET = "small"
DEMO_SEED = 1
HINT_NOISE_M = 4.0  # the demo's hint is this far (each axis, uniform) from the truth; yaw is not given


@dataclass
class SmallWorld:
    """The demo's world: its mapping and localization sessions (``--seq`` names, simulated on the
    fly) and the block map built from the first (a cache entry keyed by the code that made it)."""

    mapping: str
    loc: str
    block_map: Path

    @classmethod
    def default(cls, preset: str = DEMO_PRESET, seed: int = DEMO_SEED, map_cfg: MapConfig | None = None) -> "SmallWorld":
        """The block map is the default map of ``sim:<preset>/loc@<seed>`` for the block settings
        of ``map_cfg`` (default: the sim preset's)."""
        if map_cfg is None:
            map_cfg = load_config(preset="sim").map
        loc = f"sim:{preset}/loc@{seed}"
        ref = SequenceRef.parse(loc)
        return cls(ref.mapping_source(), loc, ref.default_map_path("block", map_params=map_params(map_cfg, "block")))


def ensure_block_map(world: SmallWorld, cfg: Config, say: Callable[[str], None] = log.info,
                     progress: Progress | None = None) -> Path:
    """The block map of the mapping session (built once, reused). Processes that ask for it at the
    same time (two demos, parallel test workers) build it once: the others wait for the first."""
    with _build_lock(world.block_map, say):
        try:
            store = open_map(world.block_map)
            say(f"block map: cached at {world.block_map} ({len(store)} blocks)")
            return world.block_map
        except MapError:
            pass
        return _build_block_map(world, cfg, say, progress)


@contextlib.contextmanager
def _build_lock(path: Path, say: Callable[[str], None]):
    """An exclusive lock on ``<path>.lock`` (flock: released by the kernel when a holder dies)."""
    import fcntl

    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fh = open(path.with_name(path.name + ".lock"), "a")
    except OSError:  # a read-only cache: nothing can be built there, so nothing to wait for
        yield
        return
    with fh:
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            say(f"block map: another process is building {path}; waiting for it ...")
            fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


def _build_block_map(world: SmallWorld, cfg: Config, say: Callable[[str], None],
                     progress: Progress | None) -> Path:
    say(f"block map: simulating the keyframes of {world.mapping} and stitching blocks of "
        f"{cfg.map.block_size_m:g} m" + (" (LiDAR mounting estimated first)" if cfg.map.calibrate_mounting else "")
        + " ...")
    t0 = time.perf_counter()
    seq = open_sequence(world.mapping, dataset_cfg=cfg.dataset)
    # as `blockloc map build` does by default (map.calibrate_mounting), so the demo shows the defaults
    build_map(seq, "block", world.block_map, cfg.map, overwrite=True, progress=progress)
    store = add_place_index(world.block_map, seq.info.gravity_map, cfg)  # `map build` stores one too
    say(f"block map: {len(store)} blocks and a place index in {time.perf_counter() - t0:.0f} s")
    return world.block_map


def prepare_small_world(cfg: Config | None = None, say: Callable[[str], None] = log.info,
                        progress: Progress | None = None) -> tuple[SmallWorld, Config]:
    """The `small` world and its (cached) block map: (SmallWorld, Config used, default the sim preset)."""
    cfg = cfg or load_config(preset="sim")
    world = SmallWorld.default(map_cfg=cfg.map)
    ensure_block_map(world, cfg, say=say, progress=progress)
    return world, cfg


def noisy_hint(seq, seed: int = DEMO_SEED, noise_m: float = HINT_NOISE_M) -> tuple[float, float, None]:
    """A position hint near the first ground-truth pose (as a user clicking on a map would give)."""
    gt = seq.ground_truth()
    p = gt.interpolate(np.array([seq.frame_stamps()[0]]))[0][:3, 3]
    rng = np.random.default_rng(seed)
    dx, dy = rng.uniform(-noise_m, noise_m, 2)
    return float(p[0] + dx), float(p[1] + dy), None


def demo_session(cfg: Config | None = None, *, world: SmallWorld | None = None, out: Path | None = None,
                 observers=(), say: Callable[[str], None] = log.info, keep_estimates: bool = False,
                 progress: Progress | None = None) -> tuple[Session, tuple]:
    """(Session on the small world's localization session in its block map, the hint). world:
    one :func:`prepare_small_world` returned (with its ``cfg``), else prepared here."""
    if world is None or cfg is None:
        world, cfg = prepare_small_world(cfg, say=say, progress=progress)
    seq = open_sequence(world.loc, dataset_cfg=cfg.dataset)
    session = build_session(cfg, seq, open_map(world.block_map), backend="block", observers=observers,
                            out_dir=out, keep_estimates=keep_estimates, facts={"map": str(world.block_map)})
    return session, noisy_hint(seq)
