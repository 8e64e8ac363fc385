"""Trajectory files: TUM, KITTI and NCLT ground truth, read into ``blockloc.geometry.Trajectory``.

Formats
-------
- **TUM** (``.tum``, or ``.txt`` with 8 columns): one pose a line, ``t x y z qx qy qz qw``;
  t in seconds, position in metres, unit quaternion (Hamilton, scalar last) of ``R_map_body``.
  Lines starting with ``#`` and blank lines are skipped; commas are accepted as separators.
- **KITTI** (``.kitti``, or ``.txt`` with 12 columns): one pose a line, the top 3x4 of ``T_map_body``
  row-major. The format has no time column: stamps are read from a times file beside it,
  ``<stem>.times.txt`` first, then KITTI's own ``times.txt`` (one stamp in seconds a line, as many
  lines as poses). Without one, the stamps are the row indices 0, 1, 2, ... and the trajectory is
  marked *untimed*: evaluation then pairs it with the other trajectory by index (equal lengths
  required) instead of by time.
- **NCLT ground truth** (``groundtruth_<date>.csv``: ``utime,x,y,z,roll,pitch,yaw``), read by
  ``read_groundtruth_csv`` (which also handles its NaN rows).

Readers sort rows by time (warning) and drop rows with a duplicated stamp (warning, the first
kept). Malformed files raise ``DatasetError`` naming the file, the line and what was expected.
Writers write to a temporary file beside the target and rename it into place.
"""

from __future__ import annotations

import io
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np
from scipy.spatial.transform import Rotation

from blockloc.errors import DatasetError
from blockloc.fileio import atomic_write_text
from blockloc.geometry import Trajectory, xyzrpy_to_T

log = logging.getLogger(__name__)

FORMATS = ("tum", "kitti", "nclt")


@dataclass
class TrajectoryFile:
    """A trajectory as read from a file.

    timed: False when the file carries no stamps (KITTI without a times file); the stamps of
    ``trajectory`` are then the row indices.
    """

    trajectory: Trajectory
    path: Path
    fmt: str
    timed: bool = True


# ----------------------------------------------------------------------------- helpers


def _read_text(path: Path) -> str:
    path = Path(path)
    if not path.exists():
        raise DatasetError(f"{path}: no such trajectory file")
    if path.is_dir():
        raise DatasetError(f"{path}: is a directory, expected a trajectory file (TUM, KITTI or NCLT csv)")
    try:
        return path.read_text()
    except UnicodeDecodeError:
        raise DatasetError(f"{path}: not a text file, expected a trajectory file (TUM, KITTI or NCLT csv)") from None


def _data_lines(text: str):
    """(line number 1-based, fields) for every non-blank, non-comment line."""
    for lineno, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if not s or s.startswith("#") or s.startswith("//"):
            continue
        yield lineno, s.replace(",", " ").split()


class _LineNumbers:
    """Line numbers (1-based) of the data lines of a text, computed only when a message needs one."""

    def __init__(self, text: str):
        self._text = text
        self._numbers: list[int] | None = None

    def __getitem__(self, k: int) -> int:
        if self._numbers is None:
            self._numbers = [lineno for lineno, _ in _data_lines(self._text)]
        return self._numbers[int(k)]


def parse_rows(path: Path, text: str, ncols: int, what: str) -> tuple[np.ndarray, _LineNumbers]:
    """Rows of exactly ``ncols`` finite floats -> ((M, ncols) float64, line number of each row)."""
    linenos = _LineNumbers(text)
    if "," not in text:  # fast path (C parser); any problem falls through to the checking parser
        try:
            import warnings

            with warnings.catch_warnings():
                warnings.simplefilter("error")  # an empty file warns: let the slow path word it
                data = np.loadtxt(io.StringIO(text), comments="#", ndmin=2, dtype=np.float64)
            if data.shape[1] == ncols and len(data) and np.isfinite(data).all():
                return data, linenos
        except (ValueError, UserWarning):
            pass
    rows = []
    for lineno, fields in _data_lines(text):
        if len(fields) != ncols:
            raise DatasetError(f"{path}:{lineno}: expected {ncols} numbers ({what}), got {len(fields)}")
        rows.append(fields)
    if not rows:
        raise DatasetError(f"{path}: no poses, expected lines of {ncols} numbers ({what})")
    try:
        data = np.array(rows, dtype=np.float64)
    except ValueError:  # find the offending line for the message
        for k, fields in enumerate(rows):
            try:
                [float(f) for f in fields]
            except ValueError:
                raise DatasetError(f"{path}:{linenos[k]}: expected {ncols} numbers ({what}), "
                                   f"got {' '.join(fields)[:60]!r}") from None
        raise
    bad = np.flatnonzero(~np.isfinite(data).all(axis=1))
    if bad.size:
        raise DatasetError(f"{path}:{linenos[bad[0]]}: non-finite value, expected {ncols} finite numbers ({what})")
    return data, linenos


def _sorted_unique(path: Path, stamps: np.ndarray, poses: np.ndarray) -> Trajectory:
    """Sort by time and drop duplicated stamps, with a warning for each repair."""
    if np.any(np.diff(stamps) < 0):
        log.warning("%s: stamps out of order, sorted by time", path)
        order = np.argsort(stamps, kind="stable")
        stamps, poses = stamps[order], poses[order]
    dup = np.concatenate([[False], np.diff(stamps) == 0])
    if dup.any():
        log.warning("%s: %d rows with a duplicated stamp dropped (first kept)", path, int(dup.sum()))
        stamps, poses = stamps[~dup], poses[~dup]
    return Trajectory(stamps, poses)


def quat_xyzw_to_R(q: np.ndarray) -> np.ndarray:
    """(N, 4) quaternions qx qy qz qw (normalized here) -> (N, 3, 3) rotation matrices."""
    return Rotation.from_quat(np.asarray(q, dtype=np.float64)).as_matrix()


def R_to_quat_xyzw(R: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotation matrices -> (N, 4) unit quaternions qx qy qz qw with qw >= 0."""
    q = Rotation.from_matrix(np.asarray(R, dtype=np.float64)).as_quat()
    q[q[:, 3] < 0] *= -1.0  # one canonical sign so files diff cleanly
    return q


# ----------------------------------------------------------------------------- TUM


def read_tum(path: str | Path) -> Trajectory:
    """Read a TUM file -> Trajectory (stamps in s, poses ``T_map_body`` (N, 4, 4))."""
    path = Path(path)
    data, linenos = parse_rows(path, _read_text(path), 8, "t x y z qx qy qz qw")
    qnorm = np.linalg.norm(data[:, 4:8], axis=1)
    bad = np.flatnonzero(np.abs(qnorm) < 1e-9)
    if bad.size:
        raise DatasetError(f"{path}:{linenos[bad[0]]}: zero quaternion, expected a unit quaternion qx qy qz qw")
    off = np.flatnonzero(np.abs(qnorm - 1.0) > 1e-3)
    if off.size:
        log.warning("%s: %d quaternions not of unit norm (line %d: %.4f), normalized",
                    path, off.size, linenos[off[0]], qnorm[off[0]])
    poses = np.zeros((len(data), 4, 4))
    poses[:, :3, :3] = quat_xyzw_to_R(data[:, 4:8])
    poses[:, :3, 3] = data[:, 1:4]
    poses[:, 3, 3] = 1.0
    return _sorted_unique(path, data[:, 0], poses)


TUM_HEADER = "# timestamp x y z qx qy qz qw"


def tum_lines(stamps: np.ndarray, poses: np.ndarray) -> list[str]:
    """TUM rows (no newline) for stamps (N,) s and poses (N, 4, 4): stamps to 1 ns, positions to
    1 nm, quaternions (x y z w) to 1e-12."""
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
    q = R_to_quat_xyzw(poses[:, :3, :3]) if len(poses) else np.zeros((0, 4))
    return [f"{t:.9f} {x:.9f} {y:.9f} {z:.9f} {qx:.12f} {qy:.12f} {qz:.12f} {qw:.12f}"
            for t, (x, y, z), (qx, qy, qz, qw) in zip(np.asarray(stamps), poses[:, :3, 3], q)]


def format_tum(traj: Trajectory) -> str:
    """TUM text for ``traj`` (header line, then :func:`tum_lines`)."""
    return "\n".join([TUM_HEADER] + tum_lines(traj.stamps, traj.poses)) + "\n"


def write_tum(path: str | Path, traj: Trajectory) -> Path:
    """Write ``traj`` as TUM, atomically. Returns the path."""
    path = Path(path)
    atomic_write_text(path, format_tum(traj))
    return path


# ----------------------------------------------------------------------------- KITTI


def kitti_times_path(path: str | Path) -> Path | None:
    """The times file read for a KITTI pose file: ``<stem>.times.txt``, then ``times.txt``."""
    path = Path(path)
    for cand in (path.with_name(f"{path.stem}.times.txt"), path.with_name("times.txt")):
        if cand.exists() and cand != path:
            return cand
    return None


def read_kitti_file(path: str | Path) -> TrajectoryFile:
    """Read a KITTI pose file and its times file if present (see the module docstring)."""
    path = Path(path)
    data, linenos = parse_rows(path, _read_text(path), 12, "3x4 pose, row-major")
    poses = np.zeros((len(data), 4, 4))
    poses[:, :3, :] = data.reshape(-1, 3, 4)
    poses[:, 3, 3] = 1.0
    dets = np.linalg.det(poses[:, :3, :3])
    bad = np.flatnonzero(np.abs(dets - 1.0) > 1e-2)
    if bad.size:
        raise DatasetError(f"{path}:{linenos[bad[0]]}: rotation block has determinant {dets[bad[0]]:.4f}, "
                           f"expected a rotation (3x4 row-major [R|t])")
    # Re-orthonormalize the printed rotations (files carry ~6 decimals).
    poses[:, :3, :3] = Rotation.from_matrix(poses[:, :3, :3]).as_matrix()
    times_file = kitti_times_path(path)
    if times_file is None:
        log.info("%s: no times file beside it, poses are paired by index", path)
        return TrajectoryFile(Trajectory(np.arange(len(poses), dtype=np.float64), poses), path, "kitti", False)
    stamps, _ = parse_rows(times_file, _read_text(times_file), 1, "time in seconds")
    if len(stamps) != len(poses):
        raise DatasetError(f"{times_file}: {len(stamps)} stamps, expected one per pose of {path} ({len(poses)})")
    return TrajectoryFile(_sorted_unique(path, stamps[:, 0], poses), path, "kitti", True)


def read_kitti(path: str | Path) -> Trajectory:
    """Read a KITTI pose file -> Trajectory (stamps = row indices when no times file exists)."""
    return read_kitti_file(path).trajectory


def write_kitti(path: str | Path, traj: Trajectory, *, write_times: bool = True) -> Path:
    """Write ``traj`` as KITTI (3x4 row-major, 9 decimals), atomically.

    With ``write_times`` the stamps go to ``<stem>.times.txt`` beside it (read back by
    ``read_kitti``). Returns the pose file's path.
    """
    path = Path(path)
    rows = traj.poses[:, :3, :].reshape(-1, 12)
    text = "".join(" ".join(f"{v:.9e}" for v in row) + "\n" for row in rows)
    if write_times:
        atomic_write_text(path.with_name(f"{path.stem}.times.txt"),
                           "".join(f"{t:.9f}\n" for t in traj.stamps))
    atomic_write_text(path, text)
    return path


# ----------------------------------------------------------------------------- NCLT


def read_nclt_groundtruth(path: str | Path) -> Trajectory:
    """NCLT ``groundtruth_<date>.csv`` -> Trajectory (:func:`read_groundtruth_csv`)."""
    path = Path(path)
    if not path.exists():
        raise DatasetError(f"{path}: no such trajectory file")
    traj = read_groundtruth_csv(path)
    if len(traj) == 0:
        raise DatasetError(f"{path}: no valid poses, expected rows utime,x,y,z,roll,pitch,yaw")
    return traj


def text_lines(path: Path, expected: str) -> Iterator[tuple[int, str]]:
    """(line number, text) of a CSV file; DatasetError naming the file and line at the first
    bytes that are not UTF-8 text (a binary file given where a CSV of ``expected`` belongs)."""
    with open(path, "rb") as fh:
        for lineno, raw in enumerate(fh, start=1):
            try:
                yield lineno, raw.decode("utf-8")
            except UnicodeDecodeError as exc:
                raise DatasetError(f"{path}:{lineno}: binary bytes (not UTF-8 text at byte {exc.start} of "
                                   f"the line), expected a text CSV of {expected}") from None


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
    for lineno, line in text_lines(path, "utime,x,y,z,roll,pitch,yaw"):
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


# ----------------------------------------------------------------------------- sniffing


def sniff_format(path: str | Path) -> str:
    """'tum', 'kitti' or 'nclt' from the extension, else from the first data line's columns."""
    path = Path(path)
    ext = path.suffix.lower()
    if ext == ".tum":
        return "tum"
    if ext == ".kitti":
        return "kitti"
    text = _read_text(path)
    for lineno, fields in _data_lines(text):
        first = text.splitlines()[lineno - 1]
        if "," in first and len(fields) == 7:
            return "nclt"
        if len(fields) == 8:
            return "tum"
        if len(fields) == 12:
            return "kitti"
        if ext == ".csv" and len(fields) == 7:
            return "nclt"
        raise DatasetError(f"{path}:{lineno}: {len(fields)} columns, expected a trajectory file: TUM (8 numbers "
                           f"a line), KITTI (12) or NCLT csv (utime,x,y,z,roll,pitch,yaw)")
    raise DatasetError(f"{path}: no poses, expected a trajectory file (TUM, KITTI or NCLT csv)")


def read_trajectory_file(path: str | Path, fmt: str | None = None) -> TrajectoryFile:
    """Read any supported trajectory file; ``fmt`` None sniffs it (see ``sniff_format``)."""
    path = Path(path)
    fmt = fmt or sniff_format(path)
    if fmt == "tum":
        return TrajectoryFile(read_tum(path), path, "tum")
    if fmt == "kitti":
        return read_kitti_file(path)
    if fmt == "nclt":
        return TrajectoryFile(read_nclt_groundtruth(path), path, "nclt")
    raise DatasetError(f"{path}: unknown trajectory format {fmt!r}, expected one of {', '.join(FORMATS)}")


def read_trajectory(path: str | Path, fmt: str | None = None) -> Trajectory:
    """Read a TUM, KITTI or NCLT ground-truth file -> Trajectory (``T_map_body``, stamps in s)."""
    return read_trajectory_file(path, fmt).trajectory


def write_trajectory(path: str | Path, traj: Trajectory, fmt: str | None = None) -> Path:
    """Write ``traj`` as 'tum' or 'kitti' (``fmt`` None: from the extension, TUM unless ``.kitti``)."""
    path = Path(path)
    fmt = fmt or ("kitti" if path.suffix.lower() == ".kitti" else "tum")
    if fmt == "tum":
        return write_tum(path, traj)
    if fmt == "kitti":
        return write_kitti(path, traj)
    raise DatasetError(f"{path}: cannot write format {fmt!r}, expected 'tum' or 'kitti'")
