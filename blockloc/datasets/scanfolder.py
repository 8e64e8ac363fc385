"""A folder of point clouds (as SLAM systems export them) with a trajectory, as a Sequence.

Layout (DIR is the folder given, or the parent of a ``scans/`` folder given; the clouds sit in
DIR or ``DIR/scans/``)::

    DIR/scans/*.pcd | *.bin | *.ply   one scan a file, in name order (numeric names by value)
    DIR/poses.tum                     T_map_body, TUM ``t x y z qx qy qz qw``        (optional)
    DIR/poses.txt + DIR/times.txt     T_map_body, KITTI 3x4 rows + one stamp a line  (optional)
    DIR/times.txt                     one stamp (s) per scan, in scan order          (optional)
    DIR/imu.csv                       ``t,ax,ay,az,gx,gy,gz``: s, m/s^2, rad/s, imu frame (optional)
    DIR/extrinsics.yaml               T_body_lidar, T_body_imu (4x4), gravity_map (3,), map_frame
                                      (optional; identity extrinsics: body = lidar)

The trajectory is ``poses=`` (a path, Trajectory or TrajectoryFile), else ``DIR/poses.tum``, else
``DIR/poses.txt`` (sniffed: KITTI, with ``DIR/times.txt`` as its stamps, or TUM). Its frame is
the map frame (``info.map_frame``: ``map_frame`` of extrinsics.yaml, else "map"). The poses are
both ``ground_truth()`` and ``mapping_poses()``.

Scan stamps, first that applies: ``DIR/times.txt`` (as many lines as scans); numeric file names
that are times (``1630500000.123.pcd`` seconds; integer names of 9+ digits by magnitude:
>= 1e8 s, >= 1e11 ms, >= 1e14 us, >= 1e17 ns; smaller integers such as ``000123`` are
indices); the pose stamps when the counts match; the clouds' own absolute per-point times (each
scan stamped at its earliest point); else, with no trajectory, ``index / rate_hz`` (warned).

Pose i belongs to scan i when the counts match (restamped to the scan's stamp); otherwise the
poses are interpolated at the scans' stamps, and scans the trajectory does not cover are named in
a warning and listed by ``uncovered_frames()`` (map building skips them; see ``with_poses``).

No ``imu.csv``: ``imu()`` returns an empty ImuData (``len(seq.imu()) == 0``, the sign of a
LiDAR-only sequence) and ``info.imu_rate_hz`` is 0.
"""

from __future__ import annotations

import logging
import os
import re
from collections import Counter
from pathlib import Path

import numpy as np

from blockloc.datasets.base import FramesByIndex, ImuData, LidarFrame, SequenceInfo, frame_index
from blockloc.datasets.pointclouds import CLOUD_SUFFIXES, cloud_time_range, read_point_cloud
from blockloc.datasets.with_poses import (TrajectoryInfo, info_with_frame, load_trajectory,
                                          match_trajectory, stamp_range, warn_uncovered)
from blockloc.errors import DatasetError
from blockloc.geometry import Trajectory
from blockloc.trajectory_io import parse_rows

log = logging.getLogger(__name__)

_NUMERIC_RE = re.compile(r"^(\d+)(?:[._](\d+))?$")
_EXTRINSIC_KEYS = ("T_body_lidar", "T_body_imu", "gravity_map", "map_frame")


# ----------------------------------------------------------------------------- the folder


def _cloud_files(folder: Path) -> list[Path]:
    if not folder.is_dir():
        return []
    return [Path(e.path) for e in os.scandir(folder)
            if e.is_file() and not e.name.startswith(".")
            and os.path.splitext(e.name)[1].lower() in CLOUD_SUFFIXES]


_SIDE_FILES = ("poses.tum", "poses.txt", "times.txt", "imu.csv", "extrinsics.yaml")


def _layout(path: Path) -> tuple[Path, Path, list[Path]]:
    """(root holding poses/imu/extrinsics, folder of the scans, scan files). Given DIR/scans
    itself (and no side file in it), the root is DIR."""
    sub = _cloud_files(path / "scans")
    if sub:
        return path, path / "scans", sub
    root = path
    if path.name == "scans" and not any((path / f).is_file() for f in _SIDE_FILES):
        root = path.parent
    return root, path, _cloud_files(path)


def is_scan_folder(path: str | Path) -> bool:
    """True when ``path`` is a directory holding point clouds (.pcd, .bin, .ply) itself or in
    ``scans/``, and is not an NCLT session (``velodyne_sync/``) or a ROS2 bag (metadata.yaml)."""
    path = Path(path)
    if not path.is_dir() or (path / "velodyne_sync").is_dir() or (path / "metadata.yaml").is_file():
        return False
    return bool(_layout(path)[2])


def _sort_scans(files: list[Path]) -> list[Path]:
    """Scans of the most common suffix (others ignored, warned), numeric names by value, else
    by name."""
    counts = Counter(f.suffix.lower() for f in files)
    suffix = counts.most_common(1)[0][0]
    if len(counts) > 1:
        log.warning("%s: using the %d %s files; ignoring %s", files[0].parent, counts[suffix],
                    suffix, ", ".join(f"{n} {s}" for s, n in counts.items() if s != suffix))
    files = [f for f in files if f.suffix.lower() == suffix]
    if all(_NUMERIC_RE.match(f.stem) for f in files):
        from decimal import Decimal

        def key(f: Path):
            m = _NUMERIC_RE.match(f.stem)
            return Decimal(f"{m[1]}.{m[2] or 0}"), f.name
        return sorted(files, key=key)
    return sorted(files, key=lambda f: f.name)


def stamps_from_names(files: list[Path]) -> np.ndarray | None:
    """Stamps (F,) s from numeric file names, or None when the names are not times (see the
    module docstring)."""
    out = []
    for f in files:
        m = _NUMERIC_RE.match(f.stem)
        if m is None:
            return None
        whole, frac = m[1], m[2]
        if frac is not None:
            out.append(int(whole) + float(f"0.{frac}"))
            continue
        v = int(whole)
        if v < 10 ** 8:
            return None  # an index, not a time
        scale = 1.0 if v < 10 ** 11 else 1e-3 if v < 10 ** 14 else 1e-6 if v < 10 ** 17 else 1e-9
        out.append(v * scale)
    return np.asarray(out, np.float64)


def read_times_file(path: Path, expected: int, scans: Path) -> np.ndarray:
    """One stamp (s) per line; DatasetError unless there are ``expected`` of them."""
    stamps, _ = parse_rows(path, path.read_text(), 1, "time in seconds")
    if len(stamps) != expected:
        raise DatasetError(f"{path}: {len(stamps)} stamps ({stamp_range(stamps[:, 0])}), expected "
                           f"one per scan of {scans} ({expected} scans)")
    return stamps[:, 0]


def read_imu_csv(path: str | Path) -> ImuData:
    """``t,ax,ay,az,gx,gy,gz`` rows (s, m/s^2, rad/s; a header line is skipped) -> ImuData.

    Rows with NaN are dropped, out-of-order rows sorted (each warned, ``nclt.clean_imu``).
    """
    from blockloc.datasets.nclt import clean_imu

    path = Path(path)
    rows = []
    with open(path) as fh:
        for lineno, line in enumerate(fh, start=1):
            s = line.strip()
            if not s or s.startswith("#"):
                continue
            parts = [p for p in re.split(r"[,\s]+", s) if p]
            if lineno == 1 and parts and parts[0][:1].isalpha():
                continue  # header
            if len(parts) < 7:
                raise DatasetError(f"{path}:{lineno}: {len(parts)} columns, expected 7 "
                                   "(t,ax,ay,az,gx,gy,gz)")
            try:
                rows.append([float(p) for p in parts[:7]])
            except ValueError:
                raise DatasetError(f"{path}:{lineno}: non-numeric value in {s[:60]!r}, expected "
                                   "t,ax,ay,az,gx,gy,gz") from None
    data = np.asarray(rows, np.float64).reshape(-1, 7)
    return clean_imu(str(path), data[:, 0], data[:, 1:4], data[:, 4:7])


def read_extrinsics(path: str | Path) -> dict:
    """extrinsics.yaml -> dict with T_body_lidar, T_body_imu ((4, 4) each; a 4x4 nested list or
    16 numbers row-major), gravity_map (3,) and map_frame (str), each only when present."""
    import yaml

    path = Path(path)
    try:
        doc = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as exc:
        raise DatasetError(f"{path}: not valid YAML ({str(exc).splitlines()[0]})") from None
    if not isinstance(doc, dict):
        raise DatasetError(f"{path}: expected a mapping with keys {', '.join(_EXTRINSIC_KEYS)}")
    unknown = sorted(set(doc) - set(_EXTRINSIC_KEYS))
    if unknown:
        raise DatasetError(f"{path}: unknown key(s) {', '.join(unknown)}, expected "
                           f"{', '.join(_EXTRINSIC_KEYS)}")
    out = {}
    for key in ("T_body_lidar", "T_body_imu"):
        if key in doc:
            try:
                T = np.asarray(doc[key], np.float64).reshape(4, 4)
            except (ValueError, TypeError):
                raise DatasetError(f"{path}: {key} must be a 4x4 matrix (nested list or 16 "
                                   "numbers, row-major)") from None
            R = T[:3, :3]
            if (not np.isfinite(T).all() or np.abs(R.T @ R - np.eye(3)).max() > 1e-3
                    or abs(np.linalg.det(R) - 1.0) > 1e-3 or np.abs(T[3] - [0, 0, 0, 1]).max() > 1e-9):
                raise DatasetError(f"{path}: {key} is not a rigid transform (rotation block must be "
                                   "orthonormal with det +1, last row 0 0 0 1)")
            out[key] = T
    if "gravity_map" in doc:
        try:
            g = np.asarray(doc["gravity_map"], np.float64).reshape(3)
        except (ValueError, TypeError):
            raise DatasetError(f"{path}: gravity_map must be 3 numbers (m/s^2)") from None
        if not (np.isfinite(g).all() and 5.0 < np.linalg.norm(g) < 15.0):
            raise DatasetError(f"{path}: gravity_map {g.tolist()} must be a finite vector of "
                               "about 9.81 m/s^2")
        out["gravity_map"] = g
    if "map_frame" in doc:
        out["map_frame"] = str(doc["map_frame"])
    return out


# ----------------------------------------------------------------------------- the sequence


class ScanFolderSequence(FramesByIndex):
    """A folder of point clouds with a trajectory (see the module docstring).

    path: DIR (holding the clouds or ``scans/``). poses: a trajectory (path, Trajectory or
    TrajectoryFile) overriding DIR/poses.*. frame_name: the trajectory's frame (default:
    extrinsics.yaml ``map_frame``, else "map"). min_range_m, max_range_m: range filter (m).
    rate_hz: the scan rate assumed when no stamp is known at all. max_gap_s: see ``with_poses``.
    """

    def __init__(self, path: str | Path, *, poses=None, frame_name: str | None = None,
                 min_range_m: float = 0.0, max_range_m: float = np.inf, name: str | None = None,
                 rate_hz: float = 10.0, max_gap_s: float | None = None):
        self.path = Path(path)
        if not self.path.is_dir():
            raise DatasetError(f"{self.path}: not a directory, expected a folder of point clouds "
                               f"({', '.join(CLOUD_SUFFIXES)}) or one with scans/")
        self.root, self.scans_dir, files = _layout(self.path)
        if not files:
            raise DatasetError(f"{self.path}: no point clouds ({', '.join(CLOUD_SUFFIXES)}) in it "
                               "or in scans/")
        self.files = _sort_scans(files)
        self.min_range_m, self.max_range_m = float(min_range_m), float(max_range_m)
        self._options = dict(frame_name=frame_name, min_range_m=min_range_m,
                             max_range_m=max_range_m, name=name, rate_hz=rate_hz, max_gap_s=max_gap_s)
        extr_path = self.root / "extrinsics.yaml"
        extr = read_extrinsics(extr_path) if extr_path.is_file() else {}
        self._imu_path = self.root / "imu.csv" if (self.root / "imu.csv").is_file() else None
        self._imu: ImuData | None = None

        stamps, self.stamp_source = self._scan_stamps()
        traj, timed, label = self._trajectory(poses)
        self.trajectory_source = label
        self._match = None
        if traj is not None:
            if stamps is None and not (len(traj) == len(self.files) and timed):
                stamps, self.stamp_source = self._cloud_stamps(), "cloud times"
                if stamps is None and not timed and len(traj) == len(self.files):
                    stamps, self.stamp_source = self._index_stamps(rate_hz), "index"
            self._match = match_trajectory(stamps, traj, timed=timed, num_frames=len(self.files),
                                           pair_equal_counts=True,
                                           traj_name=label, seq_name=str(self.scans_dir),
                                           max_gap_s=max_gap_s)
            if stamps is None:
                stamps, self.stamp_source = self._match.trajectory.stamps.copy(), "poses"
            warn_uncovered(self._match.uncovered, [f.name for f in self.files], label,
                           self._match.trajectory)
        if stamps is None:
            stamps, self.stamp_source = self._cloud_stamps(), "cloud times"
        if stamps is None:
            stamps, self.stamp_source = self._index_stamps(rate_hz), "index"
        if np.any(np.diff(stamps) <= 0):
            k = int(np.flatnonzero(np.diff(stamps) <= 0)[0])
            raise DatasetError(f"{self.scans_dir}: scan stamps ({self.stamp_source}) not strictly "
                               f"increasing: {self.files[k].name} at {stamps[k]:.6f} s, "
                               f"{self.files[k + 1].name} at {stamps[k + 1]:.6f} s")
        self._stamps = np.asarray(stamps, np.float64)
        info = SequenceInfo(
            name=name or f"scans:{self.root.name}",
            T_body_lidar=extr.get("T_body_lidar", np.eye(4)),
            T_body_imu=extr.get("T_body_imu", np.eye(4)),
            gravity_map=extr.get("gravity_map", np.array([0.0, 0.0, -9.81])),
            lidar_rate_hz=_rate(self._stamps, rate_hz),
            imu_rate_hz=100.0 if self._imu_path else 0.0)
        self.info: TrajectoryInfo = info_with_frame(info, frame_name or extr.get("map_frame", "map"),
                                                    label)
        if self._imu_path:
            self.info.imu_rate_hz = _rate(self.imu().t, 100.0)
        log.info("%s: %d scans (%s, stamps from %s), trajectory %s, %s", self.scans_dir,
                 len(self.files), self.files[0].suffix, self.stamp_source, label or "none",
                 f"IMU {self._imu_path.name}" if self._imu_path else "no IMU")

    # setup ---------------------------------------------------------------------------------------
    def _scan_stamps(self) -> tuple[np.ndarray | None, str | None]:
        times = self.root / "times.txt"
        if times.is_file():
            return read_times_file(times, len(self.files), self.scans_dir), str(times)
        named = stamps_from_names(self.files)
        if named is not None:
            return named, "file names"
        return None, None

    def _index_stamps(self, rate_hz: float) -> np.ndarray:
        log.warning("%s: no scan stamps (no times.txt, file names are not times, no absolute "
                    "per-point times, no timed trajectory): assuming %.1f Hz from 0 s",
                    self.scans_dir, rate_hz)
        return np.arange(len(self.files)) / float(rate_hz)

    def _trajectory(self, poses):
        """(Trajectory | None, timed, label) from ``poses`` or the folder's poses file."""
        if poses is None:
            for cand in (self.root / "poses.tum", self.root / "poses.txt"):
                if cand.is_file():
                    poses = cand
                    break
        if poses is None:
            return None, True, None
        return load_trajectory(poses)

    def _cloud_stamps(self) -> np.ndarray | None:
        """Each scan's earliest absolute per-point time, or None if a scan has none (reads all)."""
        first = cloud_time_range(self.files[0])
        if first is None:
            return None
        out = [first[0]]
        for f in self.files[1:]:
            r = cloud_time_range(f)
            if r is None:
                raise DatasetError(f"{f}: no absolute per-point times, expected them as in "
                                   f"{self.files[0].name} (stamps come from the clouds' times; "
                                   "or give times.txt)")
            out.append(r[0])
        return np.asarray(out, np.float64)

    def with_poses(self, poses, *, frame_name: str | None = None, max_gap_s: float | None = None
                   ) -> "ScanFolderSequence":
        """The same folder with another trajectory (path, Trajectory or TrajectoryFile)."""
        opts = dict(self._options)
        opts["frame_name"] = frame_name or opts["frame_name"]
        opts["max_gap_s"] = max_gap_s if max_gap_s is not None else opts["max_gap_s"]
        return ScanFolderSequence(self.path, poses=poses, **opts)

    # protocol ----------------------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self.files)

    def frame_stamps(self) -> np.ndarray:
        return self._stamps.copy()

    def frame(self, index: int) -> LidarFrame:
        index = frame_index(index, len(self))
        stamp = float(self._stamps[index])
        cloud = read_point_cloud(self.files[index], stamp=stamp, min_range_m=self.min_range_m,
                                 max_range_m=self.max_range_m)
        if len(cloud) == 0:
            log.warning("%s: no valid points", self.files[index])
        return LidarFrame(index, stamp, cloud.points, cloud.intensity, cloud.time_offsets,
                          cloud.ring, cloud.num_dropped)

    def imu(self) -> ImuData:
        """The samples of DIR/imu.csv, or an empty ImuData (len 0) when the folder has none."""
        if self._imu is None:
            self._imu = (read_imu_csv(self._imu_path) if self._imu_path else
                         ImuData(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3))))
        return self._imu

    def ground_truth(self) -> Trajectory | None:
        return None if self._match is None else self._match.trajectory

    def mapping_poses(self) -> Trajectory | None:
        return self.ground_truth()

    def uncovered_frames(self) -> np.ndarray:
        """(K,) int64 indices of scans the trajectory does not cover (skip them for mapping)."""
        return np.zeros(0, np.int64) if self._match is None else self._match.uncovered.copy()

    def close(self) -> None:
        """Nothing to release (files are opened per frame)."""


def _rate(stamps: np.ndarray, default: float) -> float:
    dt = np.diff(np.asarray(stamps, np.float64))
    dt = dt[dt > 0]
    return float(round(1.0 / np.median(dt), 2)) if len(dt) else float(default)


# ----------------------------------------------------------------------------- as a --seq path
PRESET = None  # any sensor
TAKES_POSES = True  # a trajectory replaces the folder's own poses file


def detect(path: Path) -> bool:
    return is_scan_folder(path)


def open_path(path: Path, options: dict) -> ScanFolderSequence:
    """The folder at ``path``; options: min_range_m, max_range_m, poses, poses_frame (its own
    trajectory file is overridden by ``poses``: one reading of the folder either way)."""
    return ScanFolderSequence(path, poses=options.get("poses"), frame_name=options.get("poses_frame"),
                              min_range_m=options.get("min_range_m", 0.0),
                              max_range_m=options.get("max_range_m", np.inf))
