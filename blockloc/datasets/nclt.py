"""NCLT (University of Michigan North Campus Long-Term) sessions: constants, readers, writers.

File layout of one session directory (as the official downloads unpack, see ``registry.py``)::

    velodyne_sync/<utime>.bin   one motion-synchronised sweep, 8 bytes a point (see below)
    velodyne_hits.bin           optional: all raw hits in packets, used for per-point times
    ms25.csv                    IMU: utime, mag xyz (Gauss), accel xyz (m/s^2), gyro xyz (rad/s)
    groundtruth_<date>.csv      utime, x, y, z, roll, pitch, yaw (m, rad), T_map_body, z down
    slam_poses_<date>.csv       optional (simulator mapping sessions): same format as ground truth

Byte layouts (devkit ``read_vel_sync.py`` / ``read_vel_hits.py``, little endian):
- point: uint16 x, y, z (metres = raw * 0.005 - 100.0), uint8 intensity, uint8 laser id.
- hits packet: 4 x uint16 magic 44444, uint32 num_hits, uint64 utime (us), 4 bytes padding,
  then num_hits points of the layout above.

Frames: NCLT's body frame is x forward, y right, z down, so gravity in the map frame is
(0, 0, +9.81). The raw hits of ``velodyne_hits.bin`` are in the velodyne frame
(``NCLT_T_BODY_LIDAR`` maps them into the body frame), but the official ``velodyne_sync/*.bin``
scans are already in the body frame: the devkit's project_vel_to_cam.py projects them with the
camera's T_c_body alone, and public loaders (pyLiDAR-SLAM, KISS-ICP, pole-localization) pair
them with body poses directly. A real NCLT session therefore gets ``NCLT_T_BODY_SYNC``
(identity); sessions written by ``write_session`` (velodyne-frame points) record their
extrinsics in ``blockloc_session.json``.
"""

from __future__ import annotations

import logging
import os
import re
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable

import numpy as np

from blockloc.datasets.base import FramesByIndex, ImuData, LidarFrame, SequenceInfo, frame_index
from blockloc.datasets.nclt_hits import (  # noqa: F401  (re-exported: the hits layout and index are NCLT's)
    HITS_INDEX_CHUNK_WORDS,
    HITS_PACKET_US,
    NCLT_HITS_HEADER_BYTES,
    NCLT_HITS_HEADER_DTYPE,
    NCLT_HITS_MAGIC,
    HitsIndex,
    _hits_packets,
)
from blockloc.errors import DatasetError
from blockloc.fileio import atomic_write_text, replace_dir
from blockloc.trajectory_io import read_groundtruth_csv  # noqa: F401 - the loader's own format, re-exported
from blockloc.trajectory_io import text_lines as _text_lines
from blockloc.geometry import T_to_xyzrpy, Trajectory, xyzrpy_to_T

log = logging.getLogger(__name__)

# --- constants --------------------------------------------------------------------------------

#: Quantisation of NCLT's uint16 coordinates: metres = raw * SCALE + OFFSET.
NCLT_POINT_SCALE = 0.005
NCLT_POINT_OFFSET = -100.0
NCLT_POINT_DTYPE = np.dtype([("x", "<u2"), ("y", "<u2"), ("z", "<u2"), ("intensity", "u1"),
                             ("laser_id", "u1")])

_DATE_RE = re.compile(r"\d{4}-\d{2}-\d{2}")

#: NCLT session dates in the order of the registry names nclt_1..nclt_5.
NCLT_SESSIONS = ("2012-01-15", "2012-01-22", "2012-02-02", "2012-04-29", "2012-05-11")


def _ssc_to_T(x, y, z, roll_deg, pitch_deg, yaw_deg) -> np.ndarray:
    """NCLT devkit "ssc" 6-vector (m, degrees) -> (4, 4), R = Rz(yaw) Ry(pitch) Rx(roll).

    This is the devkit's ``ssc_to_homo`` convention, identical to ``blockloc.geometry``'s.
    """
    return xyzrpy_to_T(x, y, z, *np.deg2rad([roll_deg, pitch_deg, yaw_deg]))


#: Velodyne HDL-32E in the body frame: NCLT's x_body_vel = [0.002, -0.004, -0.957, 0.807,
#: 0.166, -90.703] (x, y, z m; roll, pitch, yaw deg). The lidar sits 0.957 m above the body
#: origin (z down) and is yawed -90.7 deg. This is the frame of the raw ``velodyne_hits.bin``
#: hits (and of the simulator's sweeps), not of the official ``velodyne_sync`` scans.
NCLT_T_BODY_LIDAR = _ssc_to_T(0.002, -0.004, -0.957, 0.807, 0.166, -90.703)

#: Frame of the official ``velodyne_sync/<utime>.bin`` scans: the body frame itself.
NCLT_T_BODY_SYNC = np.eye(4)

#: Microstrain 3DM-GX3-45 (file ms25.csv) in the body frame. The NCLT paper (Carlevaris-Bianco
#: et al., IJRR 2016) and devkit give extrinsics only for the velodyne and the Ladybug camera;
#: the proprioceptive sensors (MS25 IMU, FOG, wheel odometry) are reported in the robot body
#: frame, whose origin is at the IMU. We therefore use identity. Not verified against a
#: calibration file (none is published); an error of a few cm in lever arm is negligible at
#: Segway speeds.
NCLT_T_BODY_IMU = np.eye(4)

#: Gravity in NCLT's map frame (z down), m/s^2.
NCLT_GRAVITY_MAP = (0.0, 0.0, 9.81)


# --- text files -------------------------------------------------------------------------------

# --- ground truth csv -------------------------------------------------------------------------

def write_groundtruth_csv(path: str | Path, traj: Trajectory) -> None:
    """Write T_map_body poses as NCLT csv: utime (int us), x, y, z, roll, pitch, yaw (rad).

    Written to a temp file, then renamed. Stamps are rounded to whole microseconds.
    """
    path = Path(path)
    xyzrpy = T_to_xyzrpy(traj.poses)
    utime = np.round(traj.stamps * 1e6).astype(np.int64)
    lines = [f"{u:d}," + ",".join(f"{v:.9f}" for v in row) for u, row in zip(utime, xyzrpy)]
    atomic_write_text(path, "\n".join(lines) + ("\n" if lines else ""))


# --- point decoding ---------------------------------------------------------------------------

def decode_points(raw: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Structured NCLT points (N,) of NCLT_POINT_DTYPE -> xyz (N, 3) float32 metres in the
    velodyne frame, intensity (N,) float32 0..255, laser id (N,) uint16."""
    # (raw - 20000) is exact in int32, so float32 keeps ~1e-6 m precision (raw * 0.005 - 100 in
    # float32 would lose up to 4e-6 m to cancellation near 100)
    zero = int(round(-NCLT_POINT_OFFSET / NCLT_POINT_SCALE))
    xyz = np.empty((len(raw), 3), dtype=np.float32)
    for k, name in enumerate("xyz"):
        np.multiply(raw[name].astype(np.int32) - zero, np.float32(NCLT_POINT_SCALE), out=xyz[:, k],
                    casting="unsafe")
    return xyz, raw["intensity"].astype(np.float32), raw["laser_id"].astype(np.uint16)


def encode_points(points: np.ndarray, intensity: np.ndarray | None, ring: np.ndarray | None
                  ) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) metres -> (structured (M,) NCLT_POINT_DTYPE, keep mask (N,) bool).

    Coordinates are rounded to the 5 mm grid; points that are not finite or outside the format's
    range [-100, 227.675] m are not kept. Intensity is rounded and clipped to 0..255 (NaN: 0);
    ring to 0..255.
    """
    words, keep = _encode_words(points, intensity, ring)
    return words.view(NCLT_POINT_DTYPE), keep


def _encode_words(points, intensity, ring) -> tuple[np.ndarray, np.ndarray]:
    """:func:`encode_points` as (M,) little-endian uint64 words (x | y << 16 | z << 32 |
    intensity << 48 | laser id << 56: the point layout's bytes), built in a few whole-array
    passes (a structured array filled field by field took 2.5x as long: ~3 ms a 56k-point scan)."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    q = np.rint((pts - NCLT_POINT_OFFSET) / NCLT_POINT_SCALE)
    inside = (q >= 0) & (q <= 65535)  # False for NaN, and +-inf is outside
    keep = inside[:, 0] & inside[:, 1] & inside[:, 2]
    every = bool(keep.all())
    pick = (lambda a: a) if every else (lambda a: a[keep])  # noqa: E731
    qi = pick(q).astype(np.uint64)
    words = qi[:, 0] | (qi[:, 1] << np.uint64(16)) | (qi[:, 2] << np.uint64(32))
    if intensity is not None:
        inten = np.clip(np.rint(pick(np.asarray(intensity, dtype=np.float64))), 0, 255)
        inten[np.isnan(inten)] = 0
        words |= inten.astype(np.uint64) << np.uint64(48)
    if ring is not None:
        words |= np.clip(pick(np.asarray(ring)), 0, 255).astype(np.uint64) << np.uint64(56)
    return words.astype("<u8", copy=False), keep


@dataclass
class EncodedFrame:
    """A frame in the bytes ``write_session`` writes: ``index``, ``stamp`` (s) and ``utime`` (us,
    its file name) of the frame, ``sync`` (the velodyne_sync file's bytes, or the path of a file
    holding them that the encoding process wrote on the session's filesystem: ``write_session``
    moves it in), ``hits`` (its velodyne_hits.bin packets, bytes-like; b"" when not asked),
    ``dropped`` (points not representable). Small to send between processes: 16 bytes a point,
    where a LidarFrame pickles to ~36; nothing of the sync bytes when they are a file."""

    index: int
    stamp: float
    utime: int
    sync: bytes | Path
    hits: bytes
    dropped: int


def encode_frame(frame: LidarFrame, hits: bool = True, encode_words=None) -> EncodedFrame:
    """``frame`` encoded as ``write_session`` writes it: points quantised (:func:`encode_points`)
    and sorted by time (stable), the hits packets (``hits``) of their times (per-point
    ``time_offsets``, else the stamp). encode_words: a function giving :func:`_encode_words`'s
    words and mask, its bits (the simulator's workers pass a one-pass kernel); None: that one."""
    utime = int(round(frame.stamp * 1e6))
    words, keep = (encode_words or _encode_words)(frame.points, frame.intensity, frame.ring)
    if frame.time_offsets is not None:
        off = np.asarray(frame.time_offsets, np.float64)
        t_us = utime + np.rint((off if keep.all() else off[keep]) * 1e6).astype(np.int64)
        if len(t_us) > 1 and not (t_us[1:] >= t_us[:-1]).all():  # sorted already: the same order
            order = np.argsort(t_us, kind="stable")
            words, t_us = words[order], t_us[order]
    else:
        t_us = np.full(len(words), utime, dtype=np.int64)
    return EncodedFrame(int(frame.index), frame.stamp, utime, words.tobytes(),
                        _hits_packets(words, t_us) if hits else b"", int(len(keep) - np.count_nonzero(keep)))


def azimuth_time_offsets(points: np.ndarray, *, period_s: float = 0.1,
                         azimuth_increases: bool = True) -> np.ndarray:
    """Per-point time offsets (N,) float32 s from azimuth, for a sweep without recorded times.

    Assumes one revolution per ``period_s``, that the first point is the first fired, and that the
    azimuth atan2(y, x) grows with time (``azimuth_increases``; True for NCLT's z-down velodyne
    frame, where the clockwise-from-above spin is positive about z; False for z-up frames).
    Offsets are relative to the first point, in [0, period_s).
    """
    if len(points) == 0:
        return np.zeros(0, dtype=np.float32)
    az = np.arctan2(points[:, 1], points[:, 0]).astype(np.float64)
    d = az - az[0] if azimuth_increases else az[0] - az
    frac = np.mod(d, 2.0 * np.pi) / (2.0 * np.pi)
    return (frac * period_s).astype(np.float32)


# --- IMU csv ----------------------------------------------------------------------------------

def read_ms25_csv(path: str | Path) -> ImuData:
    """Read NCLT ``ms25.csv``: utime (us), mag xyz, accel xyz (m/s^2), gyro xyz (rad/s).

    Returns ImuData in the MS25 frame with t in seconds. Rows holding NaN/inf are dropped;
    out-of-order rows are sorted and rows with a duplicate utime dropped (first kept); each such
    recovery logs one warning with the count. Fewer than 10 columns -> DatasetError naming the line.
    """
    path = Path(path)
    what = "utime, mag xyz, accel xyz, gyro xyz"
    try:
        data = np.loadtxt(path, delimiter=",", ndmin=2, dtype=np.float64)
    except (ValueError, UnicodeDecodeError):  # the line scan below says where and why
        data = None
    if data is None or (data.size and data.shape[1] < 10):
        for lineno, line in _text_lines(path, what):
            parts = line.strip().split(",")
            if not line.strip():
                continue
            if len(parts) < 10:
                raise DatasetError(f"{path}:{lineno}: {len(parts)} columns, expected 10 ({what})")
            try:
                [float(p) for p in parts]
            except ValueError:
                raise DatasetError(f"{path}:{lineno}: non-numeric value in {line.strip()[:80]!r}, "
                                   f"expected {what}") from None
        raise DatasetError(f"{path}: rows of unequal length, expected 10 columns each")
    data = data.reshape(-1, data.shape[1] if data.size else 10)
    return _imu_from_rows(path, data[:, 0], data[:, 4:7], data[:, 7:10])


def _imu_from_rows(path, utime, acc, gyro) -> ImuData:
    return clean_imu(path, np.asarray(utime, dtype=np.float64) * 1e-6, acc, gyro)


def clean_imu(source, t, acc, gyro) -> ImuData:
    """IMU rows (t (M,) s, acc (M, 3), gyro (M, 3)) -> ImuData with strictly increasing t.

    Rows holding NaN/inf are dropped, out-of-order rows sorted, rows with a duplicate stamp
    dropped (first kept); each recovery logs one warning naming ``source`` and the count.
    """
    path = source
    utime = np.asarray(t, dtype=np.float64)
    acc = np.asarray(acc, dtype=np.float64).reshape(-1, 3)
    gyro = np.asarray(gyro, dtype=np.float64).reshape(-1, 3)
    good = np.isfinite(utime) & np.isfinite(acc).all(axis=1) & np.isfinite(gyro).all(axis=1)
    if not good.all():
        log.warning("%s: dropped %d IMU rows holding NaN/inf", path, int((~good).sum()))
        utime, acc, gyro = utime[good], acc[good], gyro[good]
    if len(utime) and np.any(np.diff(utime) < 0):
        log.warning("%s: %d IMU rows out of time order; sorted", path,
                    int((np.diff(utime) < 0).sum()))
        order = np.argsort(utime, kind="stable")
        utime, acc, gyro = utime[order], acc[order], gyro[order]
    keep = np.concatenate([[True], np.diff(utime) > 0]) if len(utime) else np.zeros(0, bool)
    if not keep.all():
        log.warning("%s: dropped %d IMU rows with a duplicate stamp", path, int((~keep).sum()))
        utime, acc, gyro = utime[keep], acc[keep], gyro[keep]
    return ImuData(utime, np.ascontiguousarray(acc, dtype=np.float64),
                   np.ascontiguousarray(gyro, dtype=np.float64))


def write_ms25_csv(path: str | Path, imu: ImuData) -> None:
    """Write ImuData as NCLT ``ms25.csv`` (magnetometer columns 0). Temp file, then rename."""
    path = Path(path)
    utime = np.round(np.asarray(imu.t) * 1e6).astype(np.int64)
    rows = np.column_stack([np.zeros((len(utime), 3)), imu.acc, imu.gyro])
    lines = [f"{u:d}," + ",".join(f"{v:.9g}" for v in row) for u, row in zip(utime, rows)]
    atomic_write_text(path, "\n".join(lines) + ("\n" if lines else ""))


# --- the sequence -----------------------------------------------------------------------------

SIDECAR_NAME = "blockloc_session.json"


class NcltSequence(FramesByIndex):
    """A session directory in NCLT layout as a ``Sequence``.

    Frames: one per ``velodyne_sync/<utime>.bin``, loaded lazily. ``stamp`` = the file's utime in
    seconds. Points are in the lidar frame of ``info.T_body_lidar``, each as measured at its own firing time (raw, not
    deskewed); ``time_offsets`` = firing time - stamp, in seconds, from ``velodyne_hits.bin``
    (packet resolution, ~0.55 ms) when present and ``use_hits_times``; otherwise derived from the
    azimuth for a 10 Hz clockwise spin starting at the first point, i.e. offsets in [0, 0.1) s
    assuming the stamp is the start of the sweep (logged once). ``ring`` = the HDL-32E laser id
    (firing order, not elevation order). Points outside [min_range_m, max_range_m] are dropped.

    IMU: ``ms25.csv`` in the MS25 frame (NaN rows dropped, unsorted rows sorted, duplicate stamps
    dropped, each with a warning). Ground truth: ``groundtruth_<date>.csv`` (T_map_body, z down).
    ``mapping_poses()``: ``slam_poses_<date>.csv`` when present, else ground truth.

    Extrinsics: ``T_body_lidar`` = ``NCLT_T_BODY_SYNC`` (identity: official velodyne_sync scans are
    in the body frame), ``NCLT_T_BODY_IMU``, gravity +z, unless the directory holds
    ``blockloc_session.json`` (written by ``write_session``) giving ``T_body_lidar``, ``T_body_imu``
    and ``gravity_map``; a session of a ``blockloc sim`` dataset without it (``../sim.json``) gets
    ``NCLT_T_BODY_LIDAR``.

    Files are searched in ``session_dir``, then its parent and ``<parent>/ground_truth`` (ground
    truth), or ``<parent>/sensor_data/<date>`` (ms25.csv); explicit paths override the search.
    """

    def __init__(self, session_dir: str | Path, *, use_hits_times: bool = True,
                 min_range_m: float = 1.0, max_range_m: float = 100.0, date: str | None = None,
                 ms25_path: str | Path | None = None, groundtruth_path: str | Path | None = None,
                 name: str | None = None, want_imu: bool = True):
        self.session_dir = Path(session_dir)
        self.want_imu = bool(want_imu)  # False: the run ignores the IMU, a missing ms25.csv is no news
        self.min_range_m = float(min_range_m)
        self.max_range_m = float(max_range_m)
        sync_dir = self.session_dir / "velodyne_sync"
        if not sync_dir.is_dir():
            raise DatasetError(
                f"{sync_dir}: not found; put the NCLT velodyne_sync/<utime>.bin scans there "
                f"(download <date>_vel.tar.gz from the NCLT site and unpack it so that "
                f"{self.session_dir}/velodyne_sync exists)")
        self._sync_dir = sync_dir
        self.date = date or self._guess_date()
        self._utimes = self._list_sync(sync_dir)
        self._ms25_path = Path(ms25_path) if ms25_path else self._find_ms25()
        self._gt_path = (Path(groundtruth_path) if groundtruth_path
                         else self._find_csv(f"groundtruth_{self.date}.csv"))
        self._slam_path = self._find_csv(f"slam_poses_{self.date}.csv", only_session=True)
        hits = self.session_dir / "velodyne_hits.bin"
        self._hits_path = hits if (use_hits_times and hits.is_file()) else None
        self._hits: HitsIndex | None = None
        if self._hits_path is None:
            why = "disabled" if (not use_hits_times and hits.is_file()) else f"no {hits}"
            log.info("%s: per-point times from azimuth (10 Hz clockwise spin), %s",
                     self.session_dir, why)
        self._imu: ImuData | None = None
        self._gt: Trajectory | None | bool = False
        self._slam: Trajectory | None | bool = False
        # official NCLT: velodyne_sync scans are in the body frame (see the module docstring)
        T_bl, T_bi, g = NCLT_T_BODY_SYNC, NCLT_T_BODY_IMU, np.array(NCLT_GRAVITY_MAP)
        sidecar = self.session_dir / SIDECAR_NAME
        if sidecar.is_file():
            T_bl, T_bi, g = _read_sidecar(sidecar)
        elif self._hits_path is not None:
            # official hits are raw velodyne-frame returns, the sync scans body-frame points: their
            # bytes never coincide, so matching would only index a multi-GB file for nothing
            log.info("%s: official NCLT session: velodyne_hits.bin is in the velodyne frame and "
                     "velodyne_sync in the body frame, so per-point times come from the azimuth",
                     self.session_dir)
            self._hits_path = None
        self.info = SequenceInfo(name=name or f"nclt:{self.session_dir.name}",
                                 T_body_lidar=np.array(T_bl, dtype=np.float64),
                                 T_body_imu=np.array(T_bi, dtype=np.float64),
                                 gravity_map=np.asarray(g, dtype=np.float64),
                                 lidar_rate_hz=self._frame_rate_hz(), imu_rate_hz=self._peek_imu_rate())

    # discovery ---------------------------------------------------------------------------------
    def _frame_rate_hz(self) -> float:
        """Scans a second from the median stamp spacing (official velodyne_sync: ~5 Hz, the camera's
        rate; the sensor still spins at 10 Hz, which the azimuth times assume)."""
        if len(self._utimes) < 2:
            return 10.0
        return float(1e6 / np.median(np.diff(self._utimes)))

    def _guess_date(self) -> str:
        """The session's date: from its ``groundtruth_<date>.csv`` or ``slam_poses_<date>.csv``,
        else the directory's name when it is a date (NCLT's downloads unpack into ``<date>/``),
        else the date of the one ``groundtruth_<date>.csv`` where ground truth is searched,
        else the directory's name."""
        for prefix in ("groundtruth_", "slam_poses_"):
            found = sorted(self.session_dir.glob(f"{prefix}*.csv"))
            if found:
                return found[0].stem[len(prefix):]
        if _DATE_RE.fullmatch(self.session_dir.name):
            return self.session_dir.name
        found = self._ground_truth_candidates()
        if len(found) == 1:
            return found[0].stem[len("groundtruth_"):]
        return self.session_dir.name

    def _ground_truth_candidates(self) -> list[Path]:
        return sorted({p for d in self._ground_truth_dirs() for p in d.glob("groundtruth_*.csv")})

    def _ground_truth_dirs(self) -> list[Path]:
        """Where ``_find_csv`` looks for ``groundtruth_<date>.csv``, in order."""
        parent = self.session_dir.parent
        return [self.session_dir, parent, parent / "ground_truth", parent.parent / "ground_truth"]

    @staticmethod
    def _list_sync(sync_dir: Path) -> np.ndarray:
        utimes, skipped = [], 0
        with os.scandir(sync_dir) as it:
            for entry in it:
                stem, ext = os.path.splitext(entry.name)
                if ext == ".bin" and stem.isdigit():
                    utimes.append(int(stem))
                else:
                    skipped += 1
        if skipped:
            log.warning("%s: ignored %d files not named <utime>.bin", sync_dir, skipped)
        return np.unique(np.asarray(utimes, dtype=np.int64))

    def _find_ms25(self) -> Path | None:
        """The IMU file, or None (the session is tracked LiDAR-only; :meth:`imu` warns once,
        naming the file and the remedy for this kind of session)."""
        cands = [self.session_dir / "ms25.csv",
                 self.session_dir / "sensor_data" / "ms25.csv",
                 self.session_dir.parent / "sensor_data" / self.date / "ms25.csv"]
        for c in cands:
            if c.is_file():
                return c
        self._ms25_missing = cands[0]
        return None

    def _imu_remedy(self) -> str:
        """How to get this session's IMU file: re-simulate a `blockloc sim` session, download an NCLT one."""
        import json

        sim = self.session_dir.parent / "sim.json"
        if sim.is_file():
            try:
                meta = json.loads(sim.read_text())
                how = (f"blockloc sim --preset {meta['preset']} --seed {meta['seed']} "
                       f"--out {self.session_dir.parent}")
            except (OSError, ValueError, KeyError, TypeError):
                how = f"blockloc sim --out {self.session_dir.parent}"
            return f"a simulated session: re-run `{how}` to write it whole"
        if (self.session_dir / SIDECAR_NAME).is_file():
            return "a session blockloc wrote without its IMU; write it again with its IMU samples"
        return (f"for the IMU, download {self.date}_sen.tar.gz from the NCLT site and unpack it into "
                f"{self.session_dir.parent}")

    def _find_csv(self, fname: str, only_session: bool = False) -> Path | None:
        dirs = self._ground_truth_dirs()
        cands = [d / fname for d in (dirs[:1] if only_session else dirs)]
        for c in cands:
            if c.is_file():
                return c
        return None

    def _peek_imu_rate(self) -> float:
        if self._ms25_path is None:
            return 100.0  # the MS25's nominal rate (no samples to use it on)
        stamps = []
        for _, line in _text_lines(self._ms25_path, "utime, mag xyz, accel xyz, gyro xyz"):
            head = line.split(",", 1)[0].strip()
            try:
                stamps.append(float(head))
            except ValueError:
                continue
            if len(stamps) >= 200:
                break
        dt = np.diff(np.sort(np.asarray(stamps))) * 1e-6
        dt = dt[dt > 0]
        return float(round(1.0 / np.median(dt), 1)) if len(dt) else 100.0

    # protocol ----------------------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self._utimes)

    def frame_stamps(self) -> np.ndarray:
        """(F,) float64 seconds, the sync files' utimes."""
        return self._utimes * 1e-6

    def frame(self, index: int) -> LidarFrame:
        index = frame_index(index, len(self._utimes))
        utime = int(self._utimes[index])
        path = self._sync_dir / f"{utime}.bin"
        size = path.stat().st_size
        if size % 8 != 0:
            raise DatasetError(f"{path}: {size} bytes, expected a multiple of 8 (8-byte points); "
                               f"the file is truncated ({size // 8 * 8} or {(size // 8 + 1) * 8} expected)")
        words = np.fromfile(path, dtype="<u8")
        raw = words.view(NCLT_POINT_DTYPE)
        xyz, intensity, ring = decode_points(raw)
        offsets = self._time_offsets(words, xyz, utime)
        r2 = np.einsum("ij,ij->i", xyz, xyz)
        keep = np.isfinite(r2) & (r2 >= self.min_range_m ** 2) & (r2 <= self.max_range_m ** 2)
        frame = LidarFrame(index, utime * 1e-6, xyz, intensity, offsets, ring)
        if not keep.all():
            frame = frame.select(keep)
        if len(frame) == 0:
            log.warning("%s: empty scan (%d points before range filter)", path, len(raw))
        return frame

    def _time_offsets(self, words: np.ndarray, xyz: np.ndarray, utime: int) -> np.ndarray:
        if self._hits_path is not None:
            if self._hits is None:
                self._hits = HitsIndex(self._hits_path)
            t_us, found = self._hits.point_utimes(words, utime)
            offsets = ((t_us - utime) * 1e-6).astype(np.float32)
            if not found.all():
                log.debug("%d of %d points without a hit; azimuth times", int((~found).sum()), len(found))
                az = azimuth_time_offsets(xyz)
                offsets[~found] = az[~found]
            return offsets
        return azimuth_time_offsets(xyz)

    def imu(self) -> ImuData:
        """The ms25.csv samples, or an empty ImuData (len 0) when the session has no IMU file
        (one warning, naming it and the remedy: the run is LiDAR-only; an info line only when
        the session was opened with ``want_imu=False``: the user asked for LiDAR-only)."""
        if self._imu is None:
            if self._ms25_path is None:
                if self.want_imu:
                    log.warning("%s: not found; no IMU, tracking LiDAR-only (%s)", self._ms25_missing,
                                self._imu_remedy())
                else:
                    log.info("%s: not found; no IMU (LiDAR-only, as asked)", self._ms25_missing)
                self._imu = ImuData(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3)))
            else:
                self._imu = read_ms25_csv(self._ms25_path)
        return self._imu

    def ground_truth(self) -> Trajectory | None:
        if self._gt is False:
            if self._gt_path is None:
                # name the date as well as the pattern: a guessed date (the directory's name,
                # e.g. 'loc') is not a file name anyone should create
                others = self._ground_truth_candidates()
                # a date guessed from a directory called e.g. 'loc' is no file name to create
                date = self.date if _DATE_RE.fullmatch(self.date) else "<date>"
                log.warning("%s: no ground truth: no groundtruth_%s.csv in %s%s; --poses FILE gives a "
                            "reference trajectory", self.session_dir, date,
                            ", ".join(str(d) for d in self._ground_truth_dirs()),
                            f" (found {', '.join(p.name for p in others)}, of other dates)" if others else "")
                self._gt = None
            else:
                self._gt = read_groundtruth_csv(self._gt_path)
        return self._gt

    def mapping_poses(self) -> Trajectory | None:
        if self._slam is False:
            self._slam = read_groundtruth_csv(self._slam_path) if self._slam_path else None
        return self._slam if self._slam is not None else self.ground_truth()


def _read_sidecar(path: Path):
    import json

    try:
        d = json.loads(path.read_text())
        T_bl = np.asarray(d["T_body_lidar"], dtype=np.float64).reshape(4, 4)
        T_bi = np.asarray(d["T_body_imu"], dtype=np.float64).reshape(4, 4)
        g = np.asarray(d["gravity_map"], dtype=np.float64).reshape(3)
    except (ValueError, KeyError, TypeError) as exc:
        raise DatasetError(f"{path}: malformed ({exc}); expected JSON with T_body_lidar (4x4), "
                           "T_body_imu (4x4), gravity_map (3)") from None
    return T_bl, T_bi, g


# --- writer -----------------------------------------------------------------------------------

def write_session(out_dir: str | Path, *, date: str, frames: Iterable[LidarFrame], imu: ImuData,
                  ground_truth: Trajectory, slam_poses: Trajectory | None = None,
                  write_hits: bool = True, T_body_lidar: np.ndarray | None = None,
                  T_body_imu: np.ndarray | None = None,
                  gravity_map: np.ndarray | tuple | None = None) -> Path:
    """Write a session in NCLT layout to ``out_dir``; returns ``out_dir``.

    frames: iterable of LidarFrame in the velodyne frame (stamps in s, ``time_offsets`` in s
      relative to the stamp, ``ring`` = laser id, ``intensity`` 0..255), consumed one at a time;
      or of :class:`EncodedFrame` (:func:`encode_frame`, e.g. encoded in the processes that made
      the frames), written as they are (a sync file they wrote already is moved in).
      Points are quantised to 5 mm and written in time order; non-finite or unrepresentable
      points are dropped (one warning with the total count).
    imu: samples in the MS25 frame -> ``ms25.csv``. ground_truth, slam_poses: T_map_body ->
      ``groundtruth_<date>.csv`` / ``slam_poses_<date>.csv``.
    write_hits: also write ``velodyne_hits.bin`` (packets of HITS_PACKET_US) for per-point times.
    T_body_lidar, T_body_imu, gravity_map: recorded in ``blockloc_session.json`` (always written;
      missing ones default to NCLT's velodyne-frame ``NCLT_T_BODY_LIDAR``, ``NCLT_T_BODY_IMU``,
      ``NCLT_GRAVITY_MAP``), which the loader uses instead of the official layout's defaults.

    Atomic: everything goes into ``<out_dir>.tmp-*`` beside it, renamed to ``out_dir`` at the end
    (an existing ``out_dir`` is replaced).
    """
    out_dir = Path(out_dir)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f"{out_dir.name}.tmp-", dir=out_dir.parent))
    try:
        sync_dir = tmp / "velodyne_sync"
        sync_dir.mkdir()
        dropped = 0
        n_frames = 0
        last_utime = None
        hits_fh = open(tmp / "velodyne_hits.bin", "wb") if write_hits else None
        try:
            for frame in frames:
                enc = frame if isinstance(frame, EncodedFrame) else encode_frame(frame, write_hits)
                utime = enc.utime
                if last_utime is not None and utime <= last_utime:
                    raise DatasetError(f"frame {enc.index}: stamp {enc.stamp!r} s is not after "
                                       f"the previous frame's ({last_utime * 1e-6!r} s)")
                last_utime = utime
                dropped += enc.dropped
                if isinstance(enc.sync, (str, os.PathLike)):  # written already: moved in
                    os.replace(enc.sync, sync_dir / f"{utime}.bin")
                else:
                    with open(sync_dir / f"{utime}.bin", "wb") as fh:
                        fh.write(enc.sync)
                if hits_fh is not None:
                    hits_fh.write(enc.hits)
                n_frames += 1
        finally:
            if hits_fh is not None:
                hits_fh.close()
        if dropped:
            log.warning("write_session %s: dropped %d non-finite or out-of-range points",
                        out_dir, dropped)
        write_ms25_csv(tmp / "ms25.csv", imu)
        write_groundtruth_csv(tmp / f"groundtruth_{date}.csv", ground_truth)
        if slam_poses is not None:
            write_groundtruth_csv(tmp / f"slam_poses_{date}.csv", slam_poses)
        # always written: these points are in the velodyne frame, unlike official velodyne_sync scans
        import json

        d = {"T_body_lidar": np.asarray(NCLT_T_BODY_LIDAR if T_body_lidar is None else T_body_lidar,
                                        dtype=float).tolist(),
             "T_body_imu": np.asarray(NCLT_T_BODY_IMU if T_body_imu is None else T_body_imu,
                                      dtype=float).tolist(),
             "gravity_map": np.asarray(NCLT_GRAVITY_MAP if gravity_map is None else gravity_map,
                                       dtype=float).tolist()}
        atomic_write_text(tmp / SIDECAR_NAME, json.dumps(d, indent=1))
        replace_dir(tmp, out_dir, "session")
        log.info("wrote %d frames to %s", n_frames, out_dir)
        return out_dir
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


# ----------------------------------------------------------------------------- as a --seq path
PRESET = "nclt"  # the config preset of an NCLT session (a ``blockloc sim`` one: "sim")


def detect(path: Path) -> bool:
    """True for an NCLT-layout session directory (it has ``velodyne_sync/``)."""
    return path.is_dir() and (path / "velodyne_sync").is_dir()


def open_path(path: Path, options: dict) -> "NcltSequence":
    """The session at ``path``; options: min_range_m, max_range_m, use_hits_times, want_imu
    (False: the run ignores the IMU, a missing ms25.csv is not warned about)."""
    return NcltSequence(path, use_hits_times=bool(options.get("use_hits_times", True)),
                        min_range_m=options.get("min_range_m", 1.0), max_range_m=options.get("max_range_m", 100.0),
                        want_imu=bool(options.get("want_imu", True)))
