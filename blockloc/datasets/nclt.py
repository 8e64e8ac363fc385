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
(0, 0, +9.81). Velodyne points are in the velodyne frame; ``NCLT_T_BODY_LIDAR`` maps them into
the body frame.
"""

from __future__ import annotations

import logging
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np

from blockloc.errors import DatasetError
from blockloc.geometry import T_to_xyzrpy, Trajectory, xyzrpy_to_T

log = logging.getLogger(__name__)

# --- constants --------------------------------------------------------------------------------

#: Quantisation of NCLT's uint16 coordinates: metres = raw * SCALE + OFFSET.
NCLT_POINT_SCALE = 0.005
NCLT_POINT_OFFSET = -100.0
#: Magic number repeated 4 times at the start of every velodyne_hits.bin packet.
NCLT_HITS_MAGIC = 44444
NCLT_HITS_HEADER_BYTES = 24  # 4 x uint16 magic + uint32 num_hits + uint64 utime + 4 padding
NCLT_POINT_DTYPE = np.dtype([("x", "<u2"), ("y", "<u2"), ("z", "<u2"), ("intensity", "u1"),
                             ("laser_id", "u1")])
NCLT_HITS_HEADER_DTYPE = np.dtype([("magic", "<u2", (4,)), ("num_hits", "<u4"), ("utime", "<u8"),
                                   ("pad", "<u4")])

#: NCLT session dates in the order of the registry names nclt_1..nclt_5.
NCLT_SESSIONS = ("2012-01-15", "2012-01-22", "2012-02-02", "2012-04-29", "2012-05-11")


def _ssc_to_T(x, y, z, roll_deg, pitch_deg, yaw_deg) -> np.ndarray:
    """NCLT devkit "ssc" 6-vector (m, degrees) -> (4, 4), R = Rz(yaw) Ry(pitch) Rx(roll).

    This is the devkit's ``ssc_to_homo`` convention, identical to ``blockloc.geometry``'s.
    """
    return xyzrpy_to_T(x, y, z, *np.deg2rad([roll_deg, pitch_deg, yaw_deg]))


#: Velodyne HDL-32E in the body frame: the devkit's x_body_vel = [0.002, -0.004, -0.957, 0.807,
#: 0.166, -90.703] (x, y, z m; roll, pitch, yaw deg), as used by its project_vel_to_cam.py.
#: The lidar sits 0.957 m above the body origin (z down) and is yawed -90.7 deg.
NCLT_T_BODY_LIDAR = _ssc_to_T(0.002, -0.004, -0.957, 0.807, 0.166, -90.703)

#: Microstrain 3DM-GX3-45 (file ms25.csv) in the body frame. The NCLT paper (Carlevaris-Bianco
#: et al., IJRR 2016) and devkit give extrinsics only for the velodyne and the Ladybug camera;
#: the proprioceptive sensors (MS25 IMU, FOG, wheel odometry) are reported in the robot body
#: frame, whose origin is at the IMU. We therefore use identity. Not verified against a
#: calibration file (none is published); an error of a few cm in lever arm is negligible at
#: Segway speeds.
NCLT_T_BODY_IMU = np.eye(4)

#: Gravity in NCLT's map frame (z down), m/s^2.
NCLT_GRAVITY_MAP = (0.0, 0.0, 9.81)


# --- small atomic-file helpers ------------------------------------------------------------------

def _atomic_write_text(path: Path, text: str) -> None:
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as fh:
            fh.write(text)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


# --- ground truth csv -------------------------------------------------------------------------

def read_groundtruth_csv(path: str | Path) -> Trajectory:
    """Read an NCLT ``groundtruth_<date>.csv`` (or ``slam_poses_<date>.csv``).

    Rows: utime (microseconds), x, y, z (m), roll, pitch, yaw (rad), comma separated, no header
    (a header line starting with a letter or ``#`` is skipped). Returns T_map_body poses with
    stamps in seconds, sorted by time; rows holding NaN (NCLT's first rows often do) are dropped
    with one warning giving their count; duplicate stamps keep the first row.

    Raises DatasetError if the file is missing, or a line has fewer than 7 columns or a value
    that is not a number (naming the file and line).
    """
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"{path}: ground-truth file not found (expected NCLT csv: utime,x,y,z,roll,pitch,yaw)")
    rows = []
    with open(path, "r") as fh:
        for lineno, line in enumerate(fh, start=1):
            s = line.strip()
            if not s or s[0] == "#" or (lineno == 1 and s[0].isalpha()):
                continue
            parts = s.split(",")
            if len(parts) < 7:
                raise DatasetError(f"{path}:{lineno}: {len(parts)} columns, expected 7 "
                                   "(utime,x,y,z,roll,pitch,yaw)")
            try:
                rows.append([float(p) for p in parts[:7]])
            except ValueError:
                raise DatasetError(f"{path}:{lineno}: non-numeric value in {s[:80]!r}, "
                                   "expected utime,x,y,z,roll,pitch,yaw") from None
    data = np.asarray(rows, dtype=np.float64).reshape(-1, 7)
    bad = ~np.isfinite(data).all(axis=1)
    if bad.any():
        log.warning("%s: dropped %d of %d rows holding NaN/inf", path, int(bad.sum()), len(data))
        data = data[~bad]
    if len(data) == 0:
        raise DatasetError(f"{path}: no valid pose rows, expected utime,x,y,z,roll,pitch,yaw")
    order = np.argsort(data[:, 0], kind="stable")
    data = data[order]
    keep = np.concatenate([[True], np.diff(data[:, 0]) > 0])
    if not keep.all():
        log.warning("%s: dropped %d rows with duplicate utime", path, int((~keep).sum()))
        data = data[keep]
    poses = xyzrpy_to_T(*data[:, 1:].T)
    return Trajectory(data[:, 0] * 1e-6, poses)


def write_groundtruth_csv(path: str | Path, traj: Trajectory) -> None:
    """Write T_map_body poses as NCLT csv: utime (int us), x, y, z, roll, pitch, yaw (rad).

    Written to a temp file, then renamed. Stamps are rounded to whole microseconds.
    """
    path = Path(path)
    xyzrpy = T_to_xyzrpy(traj.poses)
    utime = np.round(traj.stamps * 1e6).astype(np.int64)
    lines = [f"{u:d}," + ",".join(f"{v:.9f}" for v in row) for u, row in zip(utime, xyzrpy)]
    _atomic_write_text(path, "\n".join(lines) + ("\n" if lines else ""))
