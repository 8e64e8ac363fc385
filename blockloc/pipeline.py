"""``LocalizationPipeline(...).run()``: a sequence and a map in, a tracked trajectory and a report out.

The steps, in order (each a short private method):
  open the sequence -> open the map -> map provider + NDT + global init -> tracker ->
  initial pose -> track every frame (IMU fed up to each sweep's end) -> evaluate -> write results.

Results directory (``out``): ``poses.tum`` (time s, T_map_body), ``poses_kitti.txt`` (+ times),
``metrics.json``, ``diagnostics.csv`` (one row per frame), ``config.yaml``, ``trajectories.png``
and ``errors.png`` when ground truth exists; a ``latest`` symlink beside ``out`` points at it.
"""

from __future__ import annotations

import json
import logging
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional

import numpy as np

from blockloc.cache import cache_root
from blockloc.config import Config
from blockloc.errors import GlobalInitError, MapError, TrackingError
from blockloc.fileio import to_jsonable
from blockloc.geometry import Trajectory, inv_T, transform_points

log = logging.getLogger(__name__)

INIT_MODES = ("gt", "pose", "global")


def parse_init_pose(text: str) -> tuple[float, float, float | None]:
    """'x,y' or 'x,y,yaw' (m, m, rad, map frame) -> (x, y, yaw | None)."""
    try:
        vals = [float(v) for v in text.split(",")]
    except ValueError:
        vals = []
    if len(vals) not in (2, 3) or not all(np.isfinite(vals)):
        raise TrackingError(f"--init-pose {text!r}: expected x,y or x,y,yaw (metres, radians)")
    return vals[0], vals[1], (vals[2] if len(vals) == 3 else None)


def default_map_path(seq_name: str, backend: str, cfg: Config, data_root: str | None) -> Path:
    """Where the map for ``seq_name`` is expected when --map is not given.

    sim:<preset>/<session>[@seed]: a cached map built from the same world's ``map`` session.
    nclt_N: ``<data_root>/maps/nclt_<kind>`` (built from another session, as the paper does).
    """
    import re

    kind = "block" if backend == "block" else "grid"
    m = re.match(r"^sim:(?P<preset>[\w\-]+)/[\w\-]+(@(?P<seed>\d+))?$", seq_name)
    if m:
        return cache_root() / "maps" / f"sim_{m['preset']}_{m['seed'] or 1}_{kind}"
    if seq_name.startswith("nclt_"):
        from blockloc.datasets.registry import resolve_data_root

        return resolve_data_root(data_root, cfg.dataset) / "maps" / f"nclt_{kind}"
    p = Path(seq_name)
    if p.is_dir() and (p.parent / "map").is_dir():  # a generated sim dataset: <out>/loc beside <out>/map
        return p.parent / f"{kind}_map"
    raise MapError(f"no map for sequence {seq_name!r}: give --map MAP (build one with "
                   f"'blockloc map build --seq <mapping session> --kind {kind} --out MAP')")


def build_hint(seq_name: str, kind: str, out: Path) -> str:
    """The one-line command that builds the missing default map."""
    import re

    m = re.match(r"^sim:(?P<preset>[\w\-]+)/[\w\-]+(@(?P<seed>\d+))?$", seq_name)
    if m:
        src = f"sim:{m['preset']}/map@{m['seed'] or 1}"
    elif seq_name.startswith("nclt_"):
        src = "nclt_1" if seq_name != "nclt_1" else "nclt_3"
    else:
        src = str(Path(seq_name).parent / "map")
    return f"blockloc map build --seq {src} --kind {kind} --out {out}"


@dataclass
class TrackResult:
    """What ``run()`` returns: estimated trajectory (body in map), per-frame diagnostics, metrics."""

    trajectory: Trajectory
    diagnostics: list[dict]
    metrics: dict
    out_dir: Path | None
    estimates: list = field(default_factory=list, repr=False)


class LocalizationPipeline:
    """Track one sequence in one map.

    seq: a sequence name (``sim:small/loc``, ``nclt_2``, a path) or an opened Sequence.
    map_path: map store (None: the default for the sequence, see :func:`default_map_path`).
    backend: block | grid | srt | global. init: 'gt' (first ground-truth pose), 'pose' (global
    init around ``init_pose`` = (x, y, yaw|None)), 'global' (relocalize over the whole map).
    out: results directory or None (nothing written). progress: callable(done, total) or None.
    max_frames: stop after this many frames (None: all). keep_estimates: keep Estimate objects.
    """

    def __init__(self, seq, *, cfg: Config | None = None, map_path: str | Path | None = None,
                 backend: str | None = None, init: str = "gt", init_pose=None, out: str | Path | None = None,
                 data_root: str | None = None, progress: Callable[[int, int], None] | None = None,
                 max_frames: int | None = None, start_frame: int = 0, keep_estimates: bool = False,
                 frame_filter: Callable | None = None) -> None:
        self.cfg = cfg or Config()
        self.seq_arg = seq
        self.map_path = map_path
        self.backend = backend or self.cfg.map.backend
        if init not in INIT_MODES:
            raise TrackingError(f"init {init!r}: expected one of {', '.join(INIT_MODES)}")
        if init == "pose" and init_pose is None:
            raise TrackingError("init 'pose' needs an x,y[,yaw] hint")
        self.init = init
        self.init_pose = init_pose
        self.out = Path(out) if out is not None else None
        self.data_root = data_root
        self.progress = progress
        self.max_frames = max_frames
        self.start_frame = start_frame
        self.keep_estimates = keep_estimates
        self.frame_filter = frame_filter
        self.timings: dict[str, float] = {}

    # ----------------------------------------------------------------- the steps
    def run(self) -> TrackResult:
        t0 = time.perf_counter()
        self._open_sequence()
        self._open_map()
        self._make_components()
        try:
            self._make_tracker()
            self._initialize()
            self._track()
        finally:
            self.provider.close()
        self.timings["total_s"] = time.perf_counter() - t0
        metrics = self._evaluate()
        out_dir = self._write_results(metrics)
        return TrackResult(self.trajectory, self.diags, metrics, out_dir,
                           self.estimates if self.keep_estimates else [])

    def _open_sequence(self) -> None:
        from blockloc.datasets import open_sequence

        if isinstance(self.seq_arg, (str, Path)):
            self.seq_name = str(self.seq_arg)
            self.seq = open_sequence(self.seq_arg, data_root=self.data_root, dataset_cfg=self.cfg.dataset)
        else:
            self.seq = self.seq_arg
            self.seq_name = self.seq.info.name
        self.info = self.seq.info
        self.gt = self.seq.ground_truth()
        if self.init == "gt" and self.gt is None:
            raise TrackingError(f"{self.seq_name}: --init gt needs ground truth; use --init-pose x,y,yaw "
                                "or no init option (global localization)")

    def _open_map(self) -> None:
        from blockloc.maps.store import open_map_from_config

        path = self.map_path or self.cfg.map.path or None
        if path is None:
            path = default_map_path(self.seq_name, self.backend, self.cfg, self.data_root)
            if not Path(path).exists():
                kind = "block" if self.backend == "block" else "grid"
                raise MapError(f"map for {self.seq_name} not found at {path}; build it with: "
                               f"{build_hint(self.seq_name, kind, Path(path))}")
        self.map_path = path
        self.store = open_map_from_config(path, self.cfg.map)

    def _make_components(self) -> None:
        from blockloc.global_init.relocalize import GlobalLocalizer, InitParams
        from blockloc.maps.provider import MapProvider, ndt_target_builders
        from blockloc.registration.ndt import NdtRegistration

        rc = self.cfg.registration
        build, build_tiles = ndt_target_builders(rc.resolution_m, rc.min_points_per_voxel)
        self.provider = MapProvider.from_config(self.store, self.cfg.map, target_builder=build,
                                                tiles_target_builder=build_tiles, backend=self.backend)
        self.registration = NdtRegistration.from_config(rc)
        self.localizer = GlobalLocalizer.for_store(self.store, self.info.gravity_map,
                                                   InitParams.from_config(self.cfg.global_init, rc))

    def relocalize(self, points_lidar: np.ndarray, hint: Optional[np.ndarray], gravity_body: np.ndarray,
                   stamp: float) -> Optional[np.ndarray]:
        """Global init of one scan (lidar frame); around ``hint`` (T_map_body) or over the whole map."""
        gi = self.cfg.global_init
        pts_body = transform_points(self.info.T_body_lidar, points_lidar)
        try:
            if hint is None:
                res = self.localizer.localize(pts_body, gravity_body, None, None, gi.window_m, 360.0)
            else:
                yaw = float(np.arctan2(hint[1, 0], hint[0, 0]))
                res = self.localizer.localize(pts_body, gravity_body, (float(hint[0, 3]), float(hint[1, 3])),
                                              yaw, gi.window_m, gi.yaw_window_deg)
        except GlobalInitError as exc:  # e.g. a scan too sparse to project: this attempt failed, tracking goes on
            log.info("global init at t=%.2f: %s", stamp, exc)
            self.reloc_log.append({"stamp": stamp, "verified": False, "fitness": 0.0, "time_s": 0.0,
                                   "hint": hint is not None, "error": str(exc)})
            return None
        self.reloc_log.append({"stamp": stamp, "verified": bool(res.verified), "fitness": float(res.fitness),
                               "time_s": float(res.time_s), "hint": hint is not None})
        if not res.verified or res.T_map_body is None:
            log.info("global init at t=%.2f: no verified match (best fitness %.2f)", stamp, res.fitness)
            return None
        return np.asarray(res.T_map_body)

    def _make_tracker(self) -> None:
        from blockloc.tracking.tracker import Tracker

        self.reloc_log: list[dict] = []
        self.tracker = Tracker.from_config(self.cfg, self.info, map_provider=self.provider,
                                           registration=self.registration, relocalize=self.relocalize)
        self.imu = self.seq.imu()
        self.stamps = np.asarray(self.seq.frame_stamps(), dtype=np.float64)
        stop = len(self.stamps) if self.max_frames is None else min(len(self.stamps),
                                                                    self.start_frame + self.max_frames)
        self.frame_range = (self.start_frame, stop)

    def _initialize(self) -> None:
        """Initial pose: ground truth, global init around a hint, or nothing (first frame relocalizes)."""
        first = self.frame_range[0]
        stamp = float(self.stamps[first])
        self.init_info: dict = {"mode": self.init}
        if self.init == "gt":
            T0 = self.gt.interpolate(np.array([stamp]))[0]
            h = 0.05
            p = self.gt.interpolate(np.array([stamp - h, stamp + h]))[:, :3, 3]
            self.tracker.initialize(T0, stamp, velocity_map=(p[1] - p[0]) / (2 * h))
        elif self.init == "pose":
            x, y, yaw = self.init_pose
            frame = self.seq.frame(first)
            gi = self.cfg.global_init
            from blockloc.global_init.command import gravity_at

            t0 = time.perf_counter()
            res = self.localizer.localize(transform_points(self.info.T_body_lidar, frame.points),
                                          gravity_at(self.seq, stamp), (x, y), yaw, gi.window_m,
                                          gi.yaw_window_deg if yaw is not None else 360.0)
            self.init_info.update(time_s=time.perf_counter() - t0, verified=bool(res.verified),
                                  fitness=float(res.fitness), score=float(res.score), ambiguous=bool(res.ambiguous))
            if res.T_map_body is None or not res.verified:
                raise TrackingError(f"global init around ({x:.1f}, {y:.1f}) found no verified pose "
                                    f"(best fitness {res.fitness:.2f}); try another --init-pose or --window")
            self.tracker.initialize(np.asarray(res.T_map_body), stamp)
            if self.gt is not None:
                Tg = self.gt.interpolate(np.array([stamp]))[0]
                self.init_info["error_m"] = float(np.linalg.norm(Tg[:3, 3] - res.T_map_body[:3, 3]))
        # 'global': the tracker relocalizes over the whole map on the first frame

    def _track(self) -> None:
        imu, tr = self.imu, self.tracker
        j = int(np.searchsorted(imu.t, self.stamps[self.frame_range[0]] - 1.0))
        self.estimates, poses, stamps, self.diags = [], [], [], []
        total = self.frame_range[1] - self.frame_range[0]
        t0 = time.perf_counter()
        for n, frame in enumerate(self.seq.frames(*self.frame_range)):
            if self.frame_filter is not None:
                frame = self.frame_filter(frame)
                if frame is None:
                    continue
            t_end = frame.stamp + (float(np.max(frame.time_offsets)) if frame.time_offsets is not None
                                   and len(frame.time_offsets) else 0.0)
            while j < len(imu.t) and imu.t[j] <= t_end:
                tr.insert_imu(imu.t[j], imu.acc[j], imu.gyro[j])
                j += 1
            est = tr.insert_frame(frame)
            d = est.as_dict()
            d.update(index=frame.index, stamp=frame.stamp)
            self.diags.append(d)
            if est.T_map_body is not None:
                poses.append(est.T_map_body)
                stamps.append(est.stamp)
            if self.keep_estimates:
                self.estimates.append(est)
            if self.progress is not None:
                self.progress(n + 1, total)
        self.timings["track_s"] = time.perf_counter() - t0
        self.trajectory = Trajectory(np.asarray(stamps), np.asarray(poses).reshape(-1, 4, 4))

    def _evaluate(self) -> dict:
        import psutil

        d = self.diags
        upd = np.array([x["update_ms"] for x in d if x["status"] != "uninitialized"])
        sw = np.array([x["update_ms"] for x in d if x["switched"]])
        c = self.tracker.counters
        m: dict = {
            "sequence": self.seq_name, "map": str(self.map_path), "backend": self.backend,
            "init": self.init_info, "frames": len(d), "estimated": len(self.trajectory),
            "failures": c["failures"], "recoveries": c["recoveries"], "switches": c["switches"],
            "rejected": c["rejected"], "imu_only": c["imu_only"],
            "update_ms_median": _q(upd, 50), "update_ms_mean": float(upd.mean()) if len(upd) else None,
            "update_ms_p99": _q(upd, 99), "update_ms_max": float(upd.max()) if len(upd) else None,
            "switch_update_ms_p99": _q(sw, 99),
            "deskew_ms_median": _q(np.array([x["deskew_ms"] for x in d]), 50),
            "registration_ms_median": _q(np.array([x["registration_ms"] for x in d]), 50),
            "smoother_ms_median": _q(np.array([x["smoother_ms"] for x in d]), 50),
            "fitness_median": _q(np.array([x["fitness"] for x in d]), 50),
            "window_size_min": int(min((x["window_size"] for x in d), default=0)),
            "window_size_max": int(max((x["window_size"] for x in d), default=0)),
            "peak_rss_mb": _peak_rss_mb(psutil),
            "track_s": self.timings.get("track_s"), "total_s": self.timings.get("total_s"),
            "relocalizations": self.reloc_log, "map_stats": to_jsonable(self.provider.stats()),
        }
        if self.gt is not None and len(self.trajectory) > 1:
            from blockloc.evaluation.report import evaluate_trajectories

            ev = self.cfg.evaluation
            plot_dir = self.out if (self.out is not None and ev.plots) else None
            if plot_dir is not None:
                plot_dir.mkdir(parents=True, exist_ok=True)
            res = evaluate_trajectories(self.gt, self.trajectory, align=ev.align,
                                        max_time_diff_s=ev.max_time_diff_s, rpe_deltas_m=ev.rpe_deltas_m,
                                        plot_dir=plot_dir, interpolate=True)
            m.update(res)
        return to_jsonable(m)

    def _write_results(self, metrics: dict) -> Path | None:
        if self.out is None:
            return None
        from blockloc.config import save_config
        from blockloc.evaluation.trajectory_io import write_kitti, write_tum

        out = self.out
        out.mkdir(parents=True, exist_ok=True)
        if len(self.trajectory):
            write_tum(out / "poses.tum", self.trajectory)
            write_kitti(out / "poses_kitti.txt", self.trajectory)
        _atomic_text(out / "metrics.json", json.dumps(metrics, indent=2))
        save_config(self.cfg, out / "config.yaml")
        _write_csv(out / "diagnostics.csv", self.diags)
        latest = out.parent / "latest"
        try:
            if latest.is_symlink() or not latest.exists():
                tmp = out.parent / ".latest.tmp"
                if tmp.is_symlink():
                    tmp.unlink()
                tmp.symlink_to(out.name)
                tmp.replace(latest)
        except OSError as exc:  # e.g. a file system without symlinks
            log.info("no 'latest' link: %s", exc)
        return out


# --------------------------------------------------------------------------- helpers
def _q(a: np.ndarray, q: float):
    a = a[np.isfinite(a)] if len(a) else a
    return float(np.percentile(a, q)) if len(a) else None


def _peak_rss_mb(psutil) -> float:
    # VmHWM first: it restarts at exec, whereas Linux's ru_maxrss carries a parent's peak into a
    # child started by fork + exec (a tracking run launched by a large process reported its parent's peak).
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return float(line.split()[1]) / 1024.0
    except (OSError, ValueError, IndexError):
        pass
    try:
        import resource

        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KiB
    except Exception:
        return psutil.Process().memory_info().rss / 2**20


def _atomic_text(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    tmp.replace(path)


def _write_csv(path: Path, rows: list[dict]) -> None:
    import csv
    import io

    if not rows:
        _atomic_text(path, "")
        return
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(rows[0].keys()))
    w.writeheader()
    for r in rows:
        w.writerow(r)
    _atomic_text(path, buf.getvalue())
