"""Shared helpers of the tracking benchmarks (tracking, scaling, campus): one backend stepped frame by
frame, a map-free odometry baseline, a psutil resource sampler, and a child-process entry point.

    python -m bench._track --seq SEQ --map MAP --backend block --json OUT [--max-frames N]

runs one backend in a fresh process (so peak RSS belongs to that backend alone) and writes its
metrics and per-frame arrays to OUT (.json) and OUT's .npz sibling.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from blockloc.resources import peak_rss_mb
from blockloc.fileio import atomic_path, atomic_write_text, to_jsonable

# per-frame columns every run records (saved to its .npz)
ROW_COLUMNS = ("index", "core_ms", "update_ms", "map_ms", "registration_ms", "switched", "status", "window",
               "active_points")
STATUS_CODES = {"ok": 0, "rejected": 1, "imu_only": 2, "lost": 3, "recovered": 4, "uninitialized": 5}
ODOM = "odom"  # the map-free baseline built from our parts: this tracker + a rolling map of its own scans
KISS = "kiss-icp"  # the map-free LiDAR-only baseline from PyPI (optional: pip install kiss-icp)


def kiss_available() -> bool:
    import importlib.util

    return importlib.util.find_spec("kiss_icp") is not None


class KissRun:
    """KISS-ICP (LiDAR only, constant-velocity prediction, its own deskew and voxel map) started at
    the first ground-truth pose; same interface as :class:`BackendRun`. KISS-ICP estimates the pose
    at mid-sweep, so poses are stamped at the sweep's mid time."""

    def __init__(self, seq, cfg, start: int = 0, stop: int | None = None) -> None:
        from kiss_icp.config import KISSConfig
        from kiss_icp.kiss_icp import KissICP

        self.backend = KISS
        kc = KISSConfig()
        kc.data.max_range = float(cfg.dataset.max_range_m)
        kc.data.min_range = float(cfg.dataset.min_range_m)
        kc.mapping.voxel_size = kc.data.max_range / 100.0  # KISS-ICP's own default rule
        kc.registration.max_num_threads = 2
        self.odom = KissICP(kc)
        self._map_points = 0
        self.info = seq.info
        gt = seq.ground_truth()
        st = np.asarray(seq.frame_stamps(), dtype=np.float64)
        self.T0 = gt.interpolate(st[start:start + 1] + 0.05)[0] @ self.info.T_body_lidar
        self.T_lidar_body = np.linalg.inv(self.info.T_body_lidar)
        self.stamps: list[float] = []
        self.poses: list[np.ndarray] = []
        self.rows: dict[str, list] = {c: [] for c in ROW_COLUMNS}

    def step(self, frame) -> None:
        t = (np.asarray(frame.time_offsets, np.float64) if frame.time_offsets is not None
             else np.zeros(len(frame.points)))
        span = float(t.max() - t.min()) if len(t) else 0.0
        t0 = time.perf_counter()
        self.odom.register_frame(np.asarray(frame.points, np.float64), (t - t.min()) / max(span, 1e-9))
        ms = (time.perf_counter() - t0) * 1e3
        r = self.rows
        if len(r["index"]) % 25 == 0:  # the voxel map's size (a copy of its points: not every scan)
            self._map_points = len(self.odom.local_map.point_cloud())
        for k, v in (("index", frame.index), ("core_ms", ms), ("update_ms", ms), ("map_ms", 0.0),
                     ("registration_ms", ms), ("switched", False), ("status", 0), ("window", 0),
                     ("active_points", self._map_points)):
            r[k].append(v)
        mid = float(frame.stamp) + (0.5 * (float(t.min()) + float(t.max())) if len(t) else 0.0)
        self.stamps.append(mid)
        self.poses.append(self.T0 @ self.odom.last_pose @ self.T_lidar_body)

    def arrays(self) -> dict[str, np.ndarray]:
        out = {k: np.asarray(v) for k, v in self.rows.items()}
        out["stamps"] = np.asarray(self.stamps, dtype=np.float64)
        out["poses"] = np.asarray(self.poses, dtype=np.float64).reshape(-1, 4, 4)
        out["counters"] = np.array(json.dumps({"failures": 0, "recoveries": 0, "switches": 0, "rejected": 0,
                                               "imu_only": 0}))
        out["map_stats"] = np.array(json.dumps({"active_points": int(out["active_points"][-1])}))
        return out

    def close(self) -> None:
        pass


# --------------------------------------------------------------------------- odometry baseline
@dataclass(frozen=True)
class RollingLocalMap:
    """What the tracker reads from a provider's update (the fields of ``blockloc.maps.provider.LocalMap``
    it uses): the NDT target and switch flags."""

    target: Any
    num_points: int
    switched: bool = False
    block_id: str | None = None
    region_id: str = "rolling"


class RollingMapProvider:
    """A map provider with no prior map: the local map is built from the tracker's own past scans.

    Scans (map frame, metres) are added after each accepted estimate as keyframes (every
    ``keyframe_m`` of travel); the NDT target is rebuilt from the keyframes within ``radius_m`` of the
    robot, voxel-downsampled to ``voxel_m``, whenever the robot moved ``rebuild_m`` since the last
    build (the first ``seed_scans`` scans are all kept and each rebuilds the target). With the same tracker, IMU and NDT as the map backends, this is LiDAR-inertial odometry:
    the difference to a map backend is what the prior map buys. Builds are synchronous (counted in
    the update's map time, not in deskew + registration + smoother).
    """

    def __init__(self, engine, *, radius_m: float = 60.0,
                 voxel_m: float = 0.2, keyframe_m: float = 1.0, rebuild_m: float = 1.0,
                 max_keyframes: int = 400, seed_scans: int = 10) -> None:
        self.engine = engine  # builds the rolling map's registration target
        self.radius_m = radius_m
        self.voxel_m = voxel_m
        self.keyframe_m = keyframe_m
        self.rebuild_m = rebuild_m
        self.max_keyframes = max_keyframes
        self.seed_scans = seed_scans  # the first scans are all kept (one sparse scan is no map)
        self.keyframes: list[tuple[np.ndarray, np.ndarray]] = []  # (position (3,), points (N, 3) float32)
        self._target = None
        self._num_points = 0
        self._built_at: np.ndarray | None = None
        self._dirty = False
        self.builds = 0
        self.build_ms = 0.0

    def add_scan(self, position_map: np.ndarray, points_map: np.ndarray) -> None:
        """Keep ``points_map`` (N, 3) as a keyframe if the robot at ``position_map`` moved far enough."""
        from blockloc.voxels import voxel_downsample

        p = np.asarray(position_map, np.float64).reshape(3)
        if (len(self.keyframes) >= self.seed_scans
                and np.linalg.norm(p - self.keyframes[-1][0]) < self.keyframe_m):
            return
        self.keyframes.append((p, voxel_downsample(np.asarray(points_map), self.voxel_m)[0].astype(np.float32)))
        if len(self.keyframes) > self.max_keyframes:
            self.keyframes.pop(0)
        self._dirty = True

    def update(self, position_map, velocity_map, stamp) -> RollingLocalMap:
        p = np.asarray(position_map, np.float64).reshape(3)
        if self._dirty and (self._built_at is None or len(self.keyframes) <= self.seed_scans
                            or np.linalg.norm(p - self._built_at) >= self.rebuild_m):
            self._rebuild(p)
        return RollingLocalMap(self._target, self._num_points)

    def _rebuild(self, p: np.ndarray) -> None:
        from blockloc.voxels import voxel_downsample

        t0 = time.perf_counter()
        near = [pts for c, pts in self.keyframes if np.linalg.norm(c[:2] - p[:2]) <= self.radius_m]
        if near:
            pts = voxel_downsample(np.concatenate(near), self.voxel_m)[0]
            self._target = self.engine.build_target(pts)
            self._num_points = len(pts)
        self._built_at = p.copy()
        self._dirty = False
        self.builds += 1
        self.build_ms += (time.perf_counter() - t0) * 1e3

    def stats(self) -> dict:
        kb = sum(k[1].nbytes for k in self.keyframes)
        return {"active_points": self._num_points, "resident_mb": kb / 2**20, "builds": self.builds,
                "build_ms": self.build_ms, "keyframes": len(self.keyframes)}

    def close(self) -> None:
        pass


# --------------------------------------------------------------------------- one backend, stepped
class BackendRun:
    """One backend's :class:`~blockloc.app.session.Session`, stepped frame by frame from outside (so
    that several backends can share each scan), started at the ground-truth pose of frame
    ``start``. ``backend`` is a map policy (block | grid | srt | global) or ``odom`` (no prior
    map: :class:`RollingMapProvider` over the tracker's own scans)."""

    def __init__(self, seq, cfg, map_path: Path | None, backend: str, start: int = 0,
                 stop: int | None = None) -> None:
        from blockloc.app.assemble import build_session, engine_settings, make_tracker, open_store
        from blockloc.app.session import Session

        self.backend = backend
        if backend == ODOM:
            from blockloc.registration.engines import engine_from_settings

            rc = cfg.registration
            # 3 points per voxel: a map of a few sparse scans fills voxels more thinly than a prior map
            engine = engine_from_settings(engine_settings(rc), min_points_per_voxel=min(3, rc.min_points_per_voxel))
            provider = RollingMapProvider(engine)
            tracker = make_tracker(cfg, seq.info, map_provider=provider, registration=engine,
                                   use_imu=len(seq.imu()) > 0 and cfg.tracking.use_imu)
            self.session = Session(seq, tracker, provider)  # odometry has no map to relocalize in
        else:
            self.session = build_session(cfg, seq, open_store(map_path, cfg.map), backend=backend)
        self.session.initialize("gt", start)
        self.stamps: list[float] = []
        self.poses: list[np.ndarray] = []
        self.rows: dict[str, list] = {c: [] for c in ROW_COLUMNS}

    def step(self, frame) -> None:
        est = self.session.step(frame)
        d = est.diagnostics
        if self.backend == ODOM and est.T_map_body is not None:
            self._grow_rolling_map(frame, est, d.status)
        r = self.rows
        r["index"].append(frame.index)
        r["core_ms"].append(d.deskew_ms + d.registration_ms + d.smoother_ms)
        r["update_ms"].append(d.update_ms)
        r["map_ms"].append(d.map_ms)
        r["registration_ms"].append(d.registration_ms)
        r["switched"].append(bool(d.switched))
        r["status"].append(STATUS_CODES.get(d.status, 9))
        r["window"].append(d.window_size)
        r["active_points"].append(int(self.session.provider.stats().get("active_points", 0)))
        if est.T_map_body is not None:
            self.stamps.append(est.stamp)
            self.poses.append(np.asarray(est.T_map_body))

    def _grow_rolling_map(self, frame, est, status: str) -> None:
        """Accepted scans go into the rolling map at their estimated pose, deskewed as registration
        saw them; until the map has its seed scans, every scan goes in (at the initial pose plus the
        IMU's motion): a scan NDT rejected would otherwise be written in at a doubtful pose."""
        from blockloc.geometry import transform_points

        prov, tracker = self.session.provider, self.session.tracker
        T_map_lidar = np.asarray(est.T_map_body) @ self.session.info.T_body_lidar
        scan = tracker.last_scan_lidar
        if status == "ok" and scan is not None:
            prov.add_scan(T_map_lidar[:3, 3], transform_points(T_map_lidar, scan))
        elif len(prov.keyframes) < prov.seed_scans:
            pts = scan if scan is not None else frame.points
            prov.add_scan(T_map_lidar[:3, 3], transform_points(T_map_lidar, pts))

    def arrays(self) -> dict[str, np.ndarray]:
        out = {k: np.asarray(v) for k, v in self.rows.items()}
        out["stamps"] = np.asarray(self.stamps, dtype=np.float64)
        out["poses"] = np.asarray(self.poses, dtype=np.float64).reshape(-1, 4, 4)
        out["counters"] = np.array(json.dumps(self.session.tracker.counters))
        out["map_stats"] = np.array(json.dumps(to_jsonable(self.session.provider.stats())))
        return out

    def save(self, path: Path) -> None:
        with atomic_path(path, suffix=".npz") as tmp:
            np.savez(tmp, **self.arrays())

    def close(self) -> None:
        self.session.close()


def write_json(path: Path, obj) -> None:
    atomic_write_text(path, json.dumps(to_jsonable(obj), indent=1))


# --------------------------------------------------------------------------- summaries
def summarize(z, gt=None) -> dict:
    """Metrics of one backend from its arrays (``BackendRun.arrays()`` or a loaded .npz): accuracy
    against ``gt`` (a Trajectory or None), per-scan times (core = deskew + registration + smoother),
    health counters and the local map size."""
    from blockloc.geometry import Trajectory

    counters = json.loads(str(z["counters"]))
    core, upd, sw = z["core_ms"], z["update_ms"], z["switched"].astype(bool)
    tracked = z["status"] != STATUS_CODES["uninitialized"]
    q = lambda a, p: float(np.percentile(a, p)) if len(a) else None  # noqa: E731
    m = {"frames": int(len(core)), **{k: counters[k] for k in ("failures", "recoveries", "switches",
                                                                 "rejected", "imu_only")},
         "core_ms_median": q(core[tracked], 50), "core_ms_mean": float(np.mean(core[tracked])),
         "core_ms_p99": q(core[tracked], 99),
         "update_ms_median": q(upd[tracked], 50), "update_ms_mean": float(np.mean(upd[tracked])),
         "update_ms_p99": q(upd[tracked], 99),
         "registration_ms_median": q(z["registration_ms"][tracked], 50),
         "map_ms_median": q(z["map_ms"][tracked], 50),
         "switch_frames": int(sw.sum()), "switch_core_ms_p99": q(core[sw], 99),
         "switch_update_ms_p99": q(upd[sw], 99),
         "active_points_median": q(z["active_points"], 50), "active_points_max": int(z["active_points"].max()),
         "map_stats": json.loads(str(z["map_stats"]))}
    est = Trajectory(z["stamps"], z["poses"])
    m["_stamps"], m["_positions"] = est.stamps, est.positions
    if gt is not None and len(est) > 1:
        from blockloc.evaluation.report import evaluate_trajectories

        ev = evaluate_trajectories(gt, est, align=False, max_time_diff_s=0.02, rpe_deltas_m=(10.0,),
                                   interpolate=True)
        m.update({k: ev.get(k) for k in ("ate_trans_rmse_m", "ate_trans_max_m", "ate_full_rmse",
                                         "ate_rot_rmse_deg", "path_length_m", "matched", "rpe_10m_trans_mean_pct")})
    return m


def trajectory_rmse(a: dict, b: dict) -> float | None:
    """RMSE [m] between two summaries' positions at their common stamps (None if none match)."""
    sa, sb = np.round(a["_stamps"], 6), np.round(b["_stamps"], 6)
    common, ia, ib = np.intersect1d(sa, sb, return_indices=True)
    if not len(common):
        return None
    d = np.linalg.norm(a["_positions"][ia] - b["_positions"][ib], axis=1)
    return float(np.sqrt(np.mean(d ** 2)))


# --------------------------------------------------------------------------- resources
class ResourceSampler:
    """Samples this process's CPU utilization and RSS with psutil every ``period_s`` in a thread (as
    the grid-puzzle paper did). cpu_percent: 100 = one core busy (2 cores: up to 200)."""

    def __init__(self, period_s: float = 0.2) -> None:
        import psutil

        self.proc = psutil.Process()
        self.period_s = period_s
        self.cpu: list[float] = []
        self.rss_mb: list[float] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def __enter__(self) -> "ResourceSampler":
        self.proc.cpu_percent(None)
        self._t0 = time.perf_counter()
        self._cpu0 = sum(self.proc.cpu_times()[:2])
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()
        self.wall_s = time.perf_counter() - self._t0
        self.cpu_s = sum(self.proc.cpu_times()[:2]) - self._cpu0

    def _run(self) -> None:
        while not self._stop.wait(self.period_s):
            self.cpu.append(self.proc.cpu_percent(None))
            self.rss_mb.append(self.proc.memory_info().rss / 2**20)

    def summary(self) -> dict:
        return {"cpu_percent_mean": float(np.mean(self.cpu)) if self.cpu else None,
                "cpu_percent_median": float(np.median(self.cpu)) if self.cpu else None,
                "cpu_percent_overall": 100.0 * self.cpu_s / self.wall_s if self.wall_s else None,
                "rss_mb_mean": float(np.mean(self.rss_mb)) if self.rss_mb else None,
                "rss_mb_max": float(np.max(self.rss_mb)) if self.rss_mb else None,
                "samples": len(self.cpu), "wall_s": self.wall_s}


#: Engine names a benchmark's ``backend@engine`` may give beyond ``registration.method``'s: the
#: registration settings each stands for.
ENGINE_VARIANTS = {"vgicp1": {"method": "vgicp", "voxel_grids": 1}}  # small_gicp's single voxel grid


def engine_settings(engine: str) -> dict:
    """The ``registration`` settings of a benchmark engine name (``ndt``, ``vgicp``, ``vgicp1``)."""
    return dict(ENGINE_VARIANTS.get(engine, {"method": engine}))


# --------------------------------------------------------------------------- child process
def run_child(seq_name: str, map_path: str | None, backend: str, out_json: Path, *, cfg_preset: str = "sim",
              block_size_m: float | None = None, max_frames: int | None = None, method: str | None = None) -> dict:
    """Run one backend over ``seq_name`` in this process; write metrics (+ arrays as .npz).
    method: registration engine (``registration.method`` or :data:`ENGINE_VARIANTS`; None: the preset's)."""
    from blockloc.config import load_config
    from blockloc.app.catalog import open_sequence

    overrides: dict = {"evaluation": {"plots": False}}
    if block_size_m:
        overrides["map"] = {"block_size_m": block_size_m}
    if method:
        overrides["registration"] = engine_settings(method)
    cfg = load_config(cfg_preset, overrides=overrides)
    seq = open_sequence(seq_name, dataset_cfg=cfg.dataset)
    stop = len(seq) if max_frames is None else min(len(seq), max_frames)
    rss0 = peak_rss_mb()
    t0 = time.perf_counter()
    from blockloc.maps.remote import is_url

    where = None if not map_path else (map_path if is_url(map_path) else Path(map_path))  # a URL stays one
    run = (KissRun(seq, cfg, 0, stop) if backend == KISS else BackendRun(seq, cfg, where, backend, 0, stop))
    setup_s = time.perf_counter() - t0
    with ResourceSampler() as sampler:
        t0 = time.perf_counter()
        for frame in seq.frames(0, stop):
            run.step(frame)
        track_s = time.perf_counter() - t0
    run.close()
    arrays = run.arrays()
    with atomic_path(out_json.with_suffix(".npz"), suffix=".npz") as tmp:
        np.savez(tmp, **arrays)
    res = {"backend": backend, "sequence": seq_name, "map": map_path, "setup_s": setup_s, "track_s": track_s,
           "peak_rss_mb": peak_rss_mb(), "rss_before_setup_mb": rss0, "resources": sampler.summary(),
           "load_avg": os.getloadavg()[0]}
    write_json(out_json, res)
    return res


def run_in_child(seq_name: str, map_path, backend: str, out_json: Path, **kw) -> dict:
    """``run_child`` in a fresh Python process; returns its metrics dict plus the loaded arrays."""
    import subprocess

    cmd = [sys.executable, "-m", "bench._track", "--seq", str(seq_name), "--backend", backend,
           "--json", str(out_json)]
    if map_path:
        cmd += ["--map", str(map_path)]
    for k, v in kw.items():
        if v is not None:
            cmd += [f"--{k.replace('_', '-')}", str(v)]
    root = Path(__file__).resolve().parent.parent
    subprocess.run(cmd, cwd=root, check=True)
    res = json.loads(out_json.read_text())
    res["arrays"] = dict(np.load(out_json.with_suffix(".npz")))
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench._track")
    ap.add_argument("--seq", required=True)
    ap.add_argument("--map", default=None)
    ap.add_argument("--backend", required=True)
    ap.add_argument("--json", required=True)
    ap.add_argument("--cfg-preset", default="sim")
    ap.add_argument("--block-size-m", type=float, default=None)
    ap.add_argument("--max-frames", type=int, default=None)
    ap.add_argument("--method", default=None, help="registration engine (default: the preset's)")
    a = ap.parse_args(argv)
    import logging

    logging.basicConfig(level=logging.WARNING)
    run_child(a.seq, a.map, a.backend, Path(a.json), cfg_preset=a.cfg_preset, block_size_m=a.block_size_m,
              max_frames=a.max_frames, method=a.method)
    return 0


if __name__ == "__main__":
    sys.exit(main())


def progress_lines(label: str):
    """A ``(done, total)`` callback printing ``label: done/total`` to stderr at every tenth of
    the total (benchmark runs are usually piped into a log)."""
    last = [None]

    def report(done: int, total: int | None = None) -> None:
        step = int(10 * done / total) if total else None
        if step != last[0] or (total and done == total):
            last[0] = step
            print(f"{label}: {done}/{total or '?'}", file=sys.stderr, flush=True)

    return report
