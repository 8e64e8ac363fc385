"""The tasks of the map build plan (:mod:`blockloc.maps.build_plan`): pure functions of their
arguments that read scans, write into the build directory and return small numbers.

Every task opens the drives it reads itself (once per process, :func:`_opened`), writes
atomically (:class:`BuildTarget`: a temporary name, then a rename; an object store's put), and
returns a dict with what the client needs (centroids, bounds, counts, checksums) plus its own
wall time, bytes written and raw points read. A task run twice (Dask reruns a killed worker's
tasks) writes the same bytes again. No task holds more than one candidate block (or one block
and one candidate, for a merge) or one run or chunk of keyframes.
"""

from __future__ import annotations

import hashlib
import io
import logging
import os
import shutil
import threading
import time
import uuid
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from blockloc.datasets.base import SequenceView
from blockloc.fileio import load_array

log = logging.getLogger(__name__)

SCRATCH = ".work"
#: Opened drives a process keeps, the least recently read dropped first: a worker reads runs of
#: one drive, then the next (the executor keeps neighbouring runs on one worker), and each drive
#: kept holds its poses and scene data (~150 MB a simulated city drive); a task of a dropped
#: drive opens it again (seconds). A drive read with an estimated mounting and the drive it wraps
#: count as one.
_OPENED_MAX = 2


# ----------------------------------------------------------------------------- drives


@dataclass(frozen=True)
class Drive:
    """One mapping drive: how a worker opens its sequence, and which frames to map.

    name: for messages and the manifest. open: a picklable callable returning the Sequence (with
    ``mapping_poses()``); key: names what ``open`` returns (tasks of a worker share one opened
    sequence per key). Frames ``start .. stop-1`` (stop None: to the end).
    """

    name: str
    open: Callable[[], Any]
    key: str
    start: int = 0
    stop: int | None = None

    @classmethod
    def of(cls, seq, start: int = 0, stop: int | None = None, name: str | None = None) -> "Drive":
        """A drive of an opened sequence (pickled with the tasks when run on a cluster); name
        defaults to the sequence's."""
        return cls(name or seq.info.name, _Given(seq), f"given-{uuid.uuid4().hex}", int(start),
                   None if stop is None else int(stop))


class _Given:
    """An already opened sequence as a drive's opener."""

    def __init__(self, seq) -> None:
        self.seq = seq

    def __call__(self):
        return self.seq


@dataclass(frozen=True)
class DrivePlan:
    """A drive's keyframes (:class:`~blockloc.maps.mapping.KeyframePlan` fields) and map frame."""

    drive: Drive
    frames: np.ndarray  # (K,) int64
    T_map_lidar: np.ndarray  # (K, 4, 4)
    stamps: np.ndarray  # (K,) float64 s
    num_frames: int
    map_frame: str
    seconds: float = 0.0  # the planning task's wall time (opening the drive included)
    cpu_s: float = 0.0  # and its thread's CPU time

    @property
    def positions(self) -> np.ndarray:
        return self.T_map_lidar[:, :3, 3]

    def order_key(self) -> tuple:
        return (float(self.stamps[0]), self.drive.name, self.drive.start)


_OPENED: "OrderedDict[str, tuple]" = OrderedDict()
_OPENED_LOCK = threading.RLock()  # re-entered: a remounted drive opens its inner one


def _opened(drive: Drive) -> tuple:
    """(sequence, mapping trajectory, T_body_lidar) of a drive, opened once per process."""
    from blockloc.maps.mapping import mapping_poses_or_fail

    with _OPENED_LOCK:
        if drive.key in _OPENED:
            _touch(drive.key)
            return _OPENED[drive.key]
        seq = drive.open()
        item = (seq, mapping_poses_or_fail(seq), np.asarray(seq.info.T_body_lidar, np.float64))
        _OPENED[drive.key] = item
        _touch(drive.key)
        while len({_base(k) for k in _OPENED}) > _OPENED_MAX:
            oldest = _base(next(iter(_OPENED)))
            for k in [k for k in _OPENED if _base(k) == oldest]:
                del _OPENED[k]
        return item


def _base(key: str) -> str:
    """The drive a cache key reads: a remounted drive (``key|mounting-...``) reads its inner one's
    sequence, so the two count as one opened drive and are kept or dropped together."""
    return key.split("|", 1)[0]


def _touch(key: str) -> None:
    """Mark ``key`` and the keys reading the same drive as the most recently read."""
    for k in [k for k in _OPENED if _base(k) == _base(key)]:
        _OPENED.move_to_end(k)


def drive_info(drive: Drive):
    """The ``SequenceInfo`` of ``drive``'s sequence, from this process's opened drives (opened
    here now when no task of this process has: a serial build's tasks then reuse it, and the
    warnings of opening it are given once)."""
    return _opened(drive)[0].info


def forget_drives(drives) -> None:
    """Drop the opened sequences of ``drives`` from this process's cache."""
    with _OPENED_LOCK:
        for d in drives:
            _OPENED.pop(d.key, None)


# ----------------------------------------------------------------------------- where tasks write


@dataclass(frozen=True)
class BuildTarget:
    """The build directory tasks write into: an absolute local path or a URL (fsspec).

    Names are relative (``000.pcd``, ``.work/candidate-3.npy``). Writes are atomic: a local file
    is written under :data:`SCRATCH` and renamed into place; an object store's put is atomic.
    """

    root: str

    @property
    def is_url(self) -> bool:
        from blockloc.maps.remote import is_url

        return is_url(self.root)

    def _fs(self):
        from fsspec.core import url_to_fs

        return url_to_fs(self.root)

    def write(self, name: str, data: bytes) -> None:
        if self.is_url:
            fs, root = self._fs()
            fs.pipe_file(f"{root}/{name}", data)
            return
        tmp = Path(self.root) / SCRATCH / f".{Path(name).name}.{uuid.uuid4().hex}.tmp"
        try:
            with open(tmp, "wb") as fh:  # never mkdir: a removed build directory stays removed
                fh.write(data)
            os.replace(tmp, Path(self.root) / name)
        finally:
            tmp.unlink(missing_ok=True)

    def read(self, name: str, start: int | None = None, end: int | None = None) -> bytes:
        if self.is_url:
            fs, root = self._fs()
            return fs.cat_file(f"{root}/{name}", start=start, end=end)
        with open(Path(self.root) / name, "rb") as fh:
            if start is None:
                return fh.read()
            fh.seek(start)
            return fh.read(end - start)

    def remove_scratch(self) -> None:
        if self.is_url:
            fs, root = self._fs()
            if fs.exists(f"{root}/{SCRATCH}"):
                fs.rm(f"{root}/{SCRATCH}", recursive=True)
        else:
            shutil.rmtree(Path(self.root) / SCRATCH, ignore_errors=True)


def _save_cloud(target: BuildTarget, name: str, points: np.ndarray, intensity) -> int:
    """Scratch cloud: (N, 3) float32, or (N, 4) with intensity as the last column; returns the
    bytes written."""
    arr = points if intensity is None else np.c_[points, intensity]
    buf = io.BytesIO()
    np.save(buf, np.ascontiguousarray(arr, np.float32), allow_pickle=False)
    target.write(name, buf.getvalue())
    return buf.getbuffer().nbytes


def _load_cloud(target: BuildTarget, name: str) -> tuple[np.ndarray, np.ndarray | None]:
    arr = load_array(io.BytesIO(target.read(name)))
    if arr.shape[1] == 4:
        return np.ascontiguousarray(arr[:, :3]), np.ascontiguousarray(arr[:, 3])
    return arr, None


def _write_entry(target: BuildTarget, file: str, points: np.ndarray, intensity) -> dict:
    """Encode one block/tile as PCD, write it, return its manifest numbers."""
    from blockloc.maps.pcd import encode_pcd
    from blockloc.maps.store import entry_stats

    data = encode_pcd(points, intensity)
    target.write(file, data)
    lo, hi, mean = entry_stats(points)
    return {"file": file, "bounds_min": lo, "bounds_max": hi, "centroid": mean,
            "num_points": int(len(points)), "bytes": len(data),
            "sha256": hashlib.sha256(data).hexdigest()}


# ----------------------------------------------------------------------------- the tasks


def _cpu_clock():
    """The CPU clock that charges a task what it costs: the whole process's when it runs one task
    at a time (a serial build, or a Dask worker with one thread, as the build starts them), so the
    threads a task starts (open3d's ray casts) count too; else only the task's own thread (other
    tasks run beside it in the process)."""
    try:
        from distributed import get_worker

        alone = get_worker().state.nthreads == 1
    except (ImportError, ValueError, AttributeError):  # not on a worker (ValueError): a serial build
        alone = True
    return time.process_time if alone else time.thread_time


def _timed(fn):
    """A task that also reports its own wall time and its CPU time (``seconds``, ``cpu_s`` in its
    result; :func:`_cpu_clock`): the per-task costs of the benchmark's projection. CPU time is what
    a task costs on a core of its own, also on a shared machine where wall time is not."""
    import functools

    @functools.wraps(fn)
    def task(*args):
        clock = _cpu_clock()
        t0, c0 = time.perf_counter(), clock()
        out = fn(*args)
        if isinstance(out, dict):
            out["seconds"], out["cpu_s"] = time.perf_counter() - t0, clock() - c0
        return out

    return task


def open_drive_task(drive: Drive) -> None:
    """Task: open a drive in this process ahead of its first scan task (a simulated world and
    its scene or a bag index take seconds to build; every worker does it at once, while the
    drives are planned). A sequence with a ``prepare()`` method builds what its frames need."""
    seq, _, _ = _opened(drive)
    prepare = getattr(seq, "prepare", None)
    if callable(prepare):
        prepare()


def plan_drive_task(drive: Drive, keyframe_distance_m: float, keyframe_angle_deg: float) -> DrivePlan:
    """Task: the drive's keyframes and poses (reads stamps and poses, no scan)."""
    from blockloc.maps.mapping import plan_keyframes

    clock = _cpu_clock()
    t0, c0 = time.perf_counter(), clock()
    seq, _, _ = _opened(drive)
    plan = plan_keyframes(seq, keyframe_distance_m=keyframe_distance_m,
                          keyframe_angle_deg=keyframe_angle_deg, start=drive.start, stop=drive.stop)
    return DrivePlan(drive, plan.frames, plan.T_map_lidar, plan.stamps, plan.num_frames,
                     str(getattr(seq.info, "map_frame", "map")), time.perf_counter() - t0,
                     clock() - c0)


# ----------------------------------------------------------------------------- the LiDAR mounting

#: Keyframe pairs registered for a drive's mounting estimate (each pair reads up to two scans).
MOUNTING_PAIRS = 200


class _Remounted:
    """A drive's opener whose sequence reports ``T_body_lidar`` (the estimated mounting) instead
    of its own; the inner drive's opened sequence is reused (a simulated world is built once)."""

    def __init__(self, inner: Drive, T_body_lidar: np.ndarray) -> None:
        self.inner = inner
        self.T_body_lidar = np.asarray(T_body_lidar, np.float64)

    def __call__(self):
        from blockloc.datasets.base import RemountedSequence

        return RemountedSequence(_opened(self.inner)[0], self.T_body_lidar)


def remounted(drive: Drive, T_body_lidar: np.ndarray) -> Drive:
    """``drive`` read with the mounting ``T_body_lidar`` (4, 4)."""
    tag = hashlib.sha1(np.asarray(T_body_lidar, np.float64).tobytes()).hexdigest()[:10]
    return Drive(drive.name, _Remounted(drive, T_body_lidar), f"{drive.key}|mounting-{tag}",
                 drive.start, drive.stop)


@_timed
def mounting_task(plan: DrivePlan, deskew: bool, max_pairs: int = MOUNTING_PAIRS,
                  auto: bool = False, translation_tolerance_m: float | None = None) -> dict:
    """Task: the drive's LiDAR mounting estimated from registered keyframe pairs
    (:mod:`blockloc.maps.mounting`). Reads the pairs' keyframes only. Returns ``T_body_lidar``
    (4, 4), ``estimate`` (its JSON summary), ``source`` (``"estimated"``) and the raw points read.

    auto: the default build's mode. A drive whose ``T_body_lidar`` is the identity has poses of
    the LiDAR itself (a scan folder without extrinsics, a SLAM's LiDAR trajectory; real NCLT's
    velodyne_sync scans are already in the body frame): nothing to estimate, ``source`` is
    ``"lidar poses"``. A drive the estimate fails on keeps its nominal mounting (``source``
    ``"nominal"``, ``reason`` why) instead of failing the build. Either way ``T_body_lidar`` and
    ``estimate`` are None. translation_tolerance_m: see :func:`~blockloc.maps.mounting.estimate_mounting`
    (None: its default).

    NDT registers the pairs, whatever engine tracking uses: on the campus map drive's first
    6000 frames (200 pairs) it recovered the simulated mounting to 0.035 deg and 4 mm, VGICP
    scan-to-scan to 0.07 deg and 14 mm.
    """
    from blockloc.errors import BlocklocError, MapError
    from blockloc.geometry import inv_T, transform_points
    from blockloc.maps.mounting import choose_pairs, estimate_mounting
    from blockloc.registration.engines import make_engine
    from blockloc.voxels import voxel_downsample

    _, _, X0 = _opened(plan.drive)
    if auto and np.allclose(X0, np.eye(4), rtol=0.0, atol=1e-12):
        return {"T_body_lidar": None, "estimate": None, "source": "lidar poses", "notes": [],
                "raw_points": 0, "bytes": 0}
    T_map_body = plan.T_map_lidar @ inv_T(X0)
    clouds, raw = {}, 0
    try:
        pairs = choose_pairs(T_map_body, max_pairs=max_pairs)
        needed = sorted(set(pairs.ravel().tolist()))
        for k, (pts_map, _) in zip(needed, _keyframe_clouds(plan.drive, plan.frames[needed].tolist(), deskew)):
            raw += len(pts_map)
            # back into the LiDAR frame at the scan stamp: deskewed points, as the pair sees them
            clouds[k] = voxel_downsample(transform_points(inv_T(plan.T_map_lidar[k]), pts_map), 0.2)[0]
        tol = {} if translation_tolerance_m is None else {"translation_tolerance_m": float(translation_tolerance_m)}
        est = estimate_mounting(clouds, T_map_body, pairs, X0, make_engine("ndt", num_threads=1), **tol)
    except BlocklocError as exc:  # too few pairs, a pair too sparse to register, ...
        if auto:
            return {"T_body_lidar": None, "estimate": None, "source": "nominal",
                    "reason": f"the estimate failed: {exc}", "notes": [], "raw_points": raw, "bytes": 0}
        if not isinstance(exc, MapError):
            raise
        raise MapError(f"{plan.drive.name}: {exc} (--calibrate-mounting needs keyframes 4-15 m "
                       "apart that see the same structure)") from None
    return {"T_body_lidar": est.T_body_lidar, "estimate": est.as_dict(), "source": "estimated",
            "notes": est.notes, "raw_points": raw, "bytes": 0}


# ----------------------------------------------------------------------------- the mapping poses refined

#: Keyframes a drive may have for its poses to be refined: every keyframe's scan is held in memory
#: at once (~0.1 MB each after the 0.2 m voxel filter); a longer drive is left as it came.
REFINE_MAX_KEYFRAMES = 4000


@_timed
def refine_task(plan: DrivePlan, deskew: bool, hold_mounting: bool, jackknife_blocks: int = 0) -> dict:
    """Task: the drive's keyframe poses refined against its own scans
    (:func:`blockloc.maps.pose_refine.refine_poses`, NDT scan to scan, then against local maps of
    neighbouring keyframes). Reads every keyframe.
    hold_mounting: keep the drive's ``T_body_lidar`` as it is (poses of the LiDAR itself, or a
    mounting not estimated); otherwise its rotation and forward translation are estimated with
    the poses. jackknife_blocks: passed on (the mounting x's block jackknife; the build: 0). Returns the
    keyframe stamps (K,), body poses before and after (K, 4, 4), ``T_body_lidar`` (4, 4),
    ``summary`` (JSON-ready; ``skipped`` says why nothing changed) and the raw points read."""
    from blockloc.geometry import inv_T, transform_points
    from blockloc.maps.pose_refine import refine_poses
    from blockloc.registration.engines import make_engine
    from blockloc.voxels import voxel_downsample

    _, _, X0 = _opened(plan.drive)
    T_map_body = plan.T_map_lidar @ inv_T(X0)
    base = {"stamps": plan.stamps, "before": T_map_body, "after": T_map_body, "T_body_lidar": X0,
            "raw_points": 0, "bytes": 0}
    K = len(plan.frames)
    if K > REFINE_MAX_KEYFRAMES:
        return {**base, "summary": {"skipped": f"{K} keyframes: more than the {REFINE_MAX_KEYFRAMES} "
                                               "a refinement holds in memory"}}
    clouds, raw = [], 0
    for k, (pts_map, _) in enumerate(_keyframe_clouds(plan.drive, plan.frames.tolist(), deskew)):
        raw += len(pts_map)
        # back into the LiDAR frame at the scan stamp: deskewed points, as the pairs see them
        clouds.append(voxel_downsample(transform_points(inv_T(plan.T_map_lidar[k]), pts_map), 0.2)[0])
    hold = {"mounting_sigma_rad": 1e-6, "mounting_sigma_m": 1e-4} if hold_mounting else {}
    r = refine_poses(T_map_body, plan.stamps, clouds, X0, make_engine("ndt", num_threads=1),
                     jackknife_blocks=jackknife_blocks, **hold)
    return {**base, "after": r.T_map_body, "T_body_lidar": r.T_body_lidar, "summary": r.as_dict(),
            "mounting_x_jackknife_m": r.mounting_x_jackknife_m, "raw_points": raw}


class _Reposed:
    """A drive's opener whose sequence reports refined mapping poses (and the mounting estimated
    with them); the inner drive's opened sequence is reused."""

    def __init__(self, inner: Drive, key_stamps: np.ndarray, before: np.ndarray, after: np.ndarray,
                 T_body_lidar: np.ndarray) -> None:
        self.inner = inner
        self.key_stamps, self.before, self.after = key_stamps, before, after
        self.T_body_lidar = np.asarray(T_body_lidar, np.float64)

    def __call__(self):
        from blockloc.datasets.base import RemountedSequence

        return _ReposedSequence(RemountedSequence(_opened(self.inner)[0], self.T_body_lidar), self)


class _ReposedSequence(SequenceView):
    """A sequence whose ``mapping_poses()`` are moved as its keyframes were
    (:func:`blockloc.maps.pose_refine.corrected_poses`); everything else is the wrapped one's."""

    def __init__(self, seq, how: _Reposed) -> None:
        super().__init__(seq)
        self._how, self._poses = how, None

    def mapping_poses(self):
        from blockloc.geometry import Trajectory
        from blockloc.maps.pose_refine import corrected_poses

        if self._poses is None:
            traj = self.inner.mapping_poses()
            h = self._how
            self._poses = Trajectory(traj.stamps, corrected_poses(traj.stamps, traj.poses, h.key_stamps,
                                                                  h.before, h.after))
        return self._poses


def reposed(drive: Drive, found: dict) -> Drive:
    """``drive`` read with the poses and mounting :func:`refine_task` found (``found``)."""
    tag = hashlib.sha1(np.ascontiguousarray(found["after"]).tobytes()
                       + np.asarray(found["T_body_lidar"], np.float64).tobytes()).hexdigest()[:10]
    return Drive(drive.name, _Reposed(drive, found["stamps"], found["before"], found["after"],
                                      found["T_body_lidar"]), f"{drive.key}|poses-{tag}", drive.start, drive.stop)


def _keyframe_clouds(drive: Drive, frames: list[int], deskew: bool, skipped: list | None = None):
    """The keyframes' (points, intensity) in the map frame. A keyframe whose scan cannot be read
    (a truncated or corrupt file: DatasetError) is left out and, with ``skipped`` given,
    recorded there as {"sequence", "frame", "error"} (the build counts and names them; without
    ``skipped`` the error ends the task)."""
    from blockloc.errors import DatasetError
    from blockloc.maps.mapping import keyframe_points

    seq, traj, T_body_lidar = _opened(drive)
    for i in frames:
        try:
            yield keyframe_points(seq, i, traj, T_body_lidar, deskew)
        except DatasetError as exc:
            if skipped is None:
                raise
            log.warning("%s: keyframe %d skipped: %s", drive.name, i, exc)
            skipped.append({"sequence": drive.name, "frame": int(i), "error": str(exc)})


@dataclass(frozen=True)
class DynamicFilter:
    """Moving objects left out of a task's keyframes (``map build --remove-dynamic``): the voxel
    scan evidence of :mod:`blockloc.maps.dynamic_removal` over ``frames``, the task's own
    keyframes and up to :data:`DYNAMIC_CONTEXT_KEYFRAMES` of the drive's keyframes on each side
    of them (read only as evidence, so a pedestrian the run saw once is seen through by the scans
    around it). origins: (E, 3) float64, the LiDAR's position in the map frame (m) at each of
    ``frames`` (the drive plan's ``T_map_lidar``). params: a
    :class:`~blockloc.maps.dynamic_removal.DynamicParams`."""

    params: Any
    frames: tuple[int, ...]
    origins: np.ndarray


#: Keyframes of the drive read on each side of a task's own as evidence only (a fixed plan
#: parameter: the bytes do not depend on the workers). At the default 1 m keyframe spacing the
#: evidence spans the task's keyframes plus 2 x 8 m of the drive.
DYNAMIC_CONTEXT_KEYFRAMES = 8


def dynamic_filter(plan: DrivePlan, keys: np.ndarray, params) -> DynamicFilter:
    """The :class:`DynamicFilter` of a task over ``keys`` (sorted indices into ``plan``'s
    keyframes): those keyframes and up to :data:`DYNAMIC_CONTEXT_KEYFRAMES` on each side."""
    keys = np.asarray(keys, np.int64)
    lo = max(0, int(keys.min()) - DYNAMIC_CONTEXT_KEYFRAMES)
    hi = min(len(plan.frames), int(keys.max()) + 1 + DYNAMIC_CONTEXT_KEYFRAMES)
    sel = np.union1d(keys, np.arange(lo, hi))
    return DynamicFilter(params, tuple(int(f) for f in plan.frames[sel]),
                         np.ascontiguousarray(plan.T_map_lidar[sel, :3, 3], np.float64))


def _task_clouds(drive: Drive, frames: list[int], deskew: bool, skipped: list,
                 dynamic: DynamicFilter | None) -> tuple[list, int]:
    """The task's keyframe clouds (as :func:`_keyframe_clouds`) and the number of points left out
    as moving (0 without ``dynamic``). A context keyframe that cannot be read only weakens the
    evidence (it is not counted as skipped: the task that owns it counts it)."""
    if dynamic is None:
        return list(_keyframe_clouds(drive, frames, deskew, skipped)), 0
    from blockloc.geometry import up_from_gravity
    from blockloc.maps.dynamic_removal import static_masks

    own = set(int(f) for f in frames)
    seq = _opened(drive)[0]
    up = up_from_gravity(getattr(seq.info, "gravity_map", (0.0, 0.0, -9.81)))
    evidence, read = [], {}  # read: own frame -> (index in evidence, intensity)
    for f, origin in zip(dynamic.frames, dynamic.origins):
        got = list(_keyframe_clouds(drive, [f], deskew, skipped if f in own else []))
        if got:
            if f in own:
                read[f] = (len(evidence), got[0][1])
            evidence.append((origin, got[0][0]))
    order = [f for f in frames if f in read]  # dynamic_filter puts every own frame in the evidence
    masks = static_masks(evidence, [read[f][0] for f in order], dynamic.params, up)
    out, removed = [], 0
    for f, keep in zip(order, masks):
        i, inten = read[f]
        removed += int(len(keep) - keep.sum())
        out.append((evidence[i][1][keep], None if inten is None else np.asarray(inten)[keep]))
    return out, removed


@_timed
def block_run_task(drive: Drive, frames: list[int], voxel_size_m: float, deskew: bool,
                   target: BuildTarget, name: str, dynamic: DynamicFilter | None = None) -> dict:
    """Task: a run of a candidate block's keyframes read, deskewed and summed by voxel
    (:func:`~blockloc.maps.block_maps.keyframe_run_sums`), the records saved as ``name``; with
    ``dynamic``, moving objects left out first. Returns the record count, whether every keyframe
    had intensity, the raw point count and the points left out as moving."""
    from blockloc.maps.block_maps import keyframe_run_sums

    skipped: list = []
    clouds, moving = _task_clouds(drive, frames, deskew, skipped, dynamic)
    rec, has_intensity = keyframe_run_sums(clouds, voxel_size_m)
    data = rec.tobytes()
    target.write(name, data)
    return {"name": name, "records": int(len(rec)), "has_intensity": has_intensity,
            "raw_points": int(sum(len(p) for p, _ in clouds) + moving), "moving_points": moving,
            "bytes": len(data), "skipped": skipped}


@_timed
def block_candidate_task(target: BuildTarget, voxel_size_m: float, name: str, *runs: dict) -> dict:
    """Task: a candidate block's points from its runs' voxel sums (``runs``: the results of its
    :func:`block_run_task` tasks, in keyframe order, added in that order as the in-memory
    :class:`~blockloc.maps.block_maps.VoxelAccumulator` does), saved as ``name``; returns
    centroid (3,), bounds lo/hi (3,) and the point count (``name`` None when the keyframes hold
    no point)."""
    from blockloc.maps.block_maps import VoxelAccumulator, block_centroid
    from blockloc.maps.grid_tiles import VOXEL_SUM

    acc = VoxelAccumulator(voxel_size_m)
    for r in runs:
        acc.add_run(np.frombuffer(target.read(r["name"]), VOXEL_SUM), r["has_intensity"])
    pts, inten = acc.result()
    if len(pts) == 0:
        return {"name": None, "bytes": 0}
    return {"name": name, "centroid": block_centroid(pts), "lo": pts.min(axis=0).astype(np.float64),
            "hi": pts.max(axis=0).astype(np.float64), "num_points": len(pts),
            "bytes": _save_cloud(target, name, pts, inten)}


@_timed
def block_merge_task(target: BuildTarget, block_name: str, candidate_name: str, out_name: str,
                     voxel_size_m: float, *after) -> dict:
    """Task: block version ``block_name`` merged with a candidate, saved as ``out_name``;
    returns the new centroid (3,) and point count. ``after``: the tasks that wrote the inputs."""
    from blockloc.maps.block_maps import block_centroid, merge_block_points

    pts, inten = _load_cloud(target, block_name)
    more, more_inten = _load_cloud(target, candidate_name)
    pts, inten = merge_block_points(pts, inten, more, more_inten, voxel_size_m)
    return {"name": out_name, "centroid": block_centroid(pts), "num_points": len(pts),
            "bytes": _save_cloud(target, out_name, pts, inten)}


@_timed
def block_write_task(target: BuildTarget, version_name: str, file: str, *after) -> dict:
    """Task: a block's last version written as its entry ``file``; returns its manifest numbers."""
    pts, inten = _load_cloud(target, version_name)
    return _write_entry(target, file, pts, inten)


@_timed
def grid_chunk_task(drive: Drive, frames: list[int], tile_size_m: float, voxel_size_m: float,
                    deskew: bool, target: BuildTarget, name: str, dynamic: DynamicFilter | None = None) -> dict:
    """Task: a run of keyframes read, deskewed (with ``dynamic``: moving objects left out),
    binned into tiles and summed by voxel; the records of every tile saved one after another as
    ``name``. Returns ``tiles``: [(ix, iy, first record, end record)], the raw point count and the
    points left out as moving."""
    from blockloc.maps.grid_tiles import tile_voxel_sums

    pts, inten, skipped = [], [], []
    clouds, moving = _task_clouds(drive, frames, deskew, skipped, dynamic)
    for p, i in clouds:
        pts.append(p)
        inten.append(np.zeros(len(p), np.float32) if i is None else np.asarray(i, np.float32))
    pts = np.concatenate(pts) if pts else np.zeros((0, 3))
    inten = np.concatenate(inten) if inten else np.zeros(0, np.float32)
    finite = np.isfinite(pts).all(axis=1)
    tiles, parts, row = [], [], 0
    for (ix, iy), rec in tile_voxel_sums(pts[finite], inten[finite], tile_size_m, voxel_size_m):
        tiles.append((ix, iy, row, row + len(rec)))
        parts.append(rec)
        row += len(rec)
    data = b"".join(r.tobytes() for r in parts)
    target.write(name, data)
    return {"name": name, "tiles": tiles, "raw_points": int(len(pts)) + moving, "moving_points": moving,
            "bytes": len(data), "skipped": skipped}


@_timed
def grid_tile_task(target: BuildTarget, tiles: list[tuple[tuple[int, int], list, str]],
                   tile_size_m: float, voxel_size_m: float) -> dict:
    """Task: tiles, one after another: each tile's voxel sums from every chunk (``(cell, parts,
    file)``, parts: (chunk file, first record, end record) in plan order) merged and written as
    entry ``file``. Returns ``entries``: their manifest numbers, in the given order."""
    from blockloc.maps.grid_tiles import VOXEL_SUM, merge_voxel_sums, voxel_sum_points

    size = VOXEL_SUM.itemsize
    entries = []
    for cell, parts, file in tiles:
        recs = [np.frombuffer(target.read(name, r0 * size, r1 * size), VOXEL_SUM)
                for name, r0, r1 in parts]
        pts, inten = voxel_sum_points(merge_voxel_sums(recs, voxel_size_m), cell, tile_size_m)
        entries.append(_write_entry(target, file, pts, inten))
    return {"entries": entries, "bytes": sum(e["bytes"] for e in entries)}
