"""Export any sequence with poses in the DynamicMap Benchmark layout (``blockloc export dynamicmap``).

Each frame is deskewed into the map frame with the poses (``blockloc.maps.mapping.scan_to_map``,
as a map build does) and written by :class:`blockloc.datasets.dynamicmap.DynamicMapWriter` with
its sensor pose (the pose at the frame's stamp) in VIEWPOINT. Ground-truth labels come from the
simulator: a changed day (``sim:P/loc_m12@S``, ``map_m12``...) rendered live, or a session
``blockloc sim --months`` wrote (its ``point_labels/``); a point is dynamic when it hit a moving
pedestrian or vehicle (``LABEL_MOVING``; structure changed since the mapping day is static on
its own day). The mapping day ``map`` has no moving actors at all (the simulator maps on a quiet
day): every point static.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace
from typing import Callable

import numpy as np

from blockloc.errors import DatasetError

log = logging.getLogger(__name__)

#: The benchmark's KITTI extraction keeps points within 50 m (its labels are wrong further out).
DEFAULT_MAX_RANGE_M = 50.0
#: Points this close are the vehicle itself (the simulator's body returns lie within ~2 m; DUFOMap drops
#: points within 0.2 m of the sensor).
DEFAULT_MIN_RANGE_M = 2.5


@dataclass
class ExportSummary:
    out: Path
    scans: int
    points: int
    dynamic_points: int
    labelled: bool
    first_frame: int
    last_frame: int


def _labels_fn(seq) -> Callable[[int], tuple] | None:
    """frame index -> (frame, (N,) bool dynamic) for a labelled sequence, else None."""
    from blockloc.sim.changes import LABEL_MOVING, LABELS_DIR, read_point_labels

    if callable(getattr(seq, "frame_labels", None)):  # a changed day of the simulator
        def sim_labels(i: int):
            frame, lab = seq.frame_labels(i)
            return frame, np.asarray(lab) == LABEL_MOVING
        return sim_labels
    session_dir = getattr(seq, "session_dir", None)
    if session_dir is not None and (Path(session_dir) / LABELS_DIR).is_dir():
        def file_labels(i: int):
            frame = seq.frame(i)
            lab = read_point_labels(session_dir, int(round(frame.stamp * 1e6)))
            if len(lab) != len(frame.points):
                raise DatasetError(f"{session_dir}/{LABELS_DIR}: {len(lab)} labels for frame {i}'s "
                                   f"{len(frame.points)} points (expected one per point of the scan file)")
            return frame, lab == LABEL_MOVING
        return file_labels
    return None


def export_dynamicmap(seq_name: str, out: str | Path, *, poses: str | Path | None = None, start: int = 0,
                      frames: int | None = None, step: int = 1, min_range_m: float = DEFAULT_MIN_RANGE_M,
                      max_range_m: float = DEFAULT_MAX_RANGE_M, data_root: str | Path | None = None,
                      progress: Callable[[int, int], None] | None = None) -> ExportSummary:
    """Write frames ``start, start+step, ...`` (``frames`` of them; None: to the end) of
    ``seq_name`` to ``out`` in the DynamicMap layout. poses: a trajectory file (T_map_body; TUM,
    KITTI, NCLT csv) instead of the sequence's ground truth (or mapping poses). Points outside
    [min_range_m, max_range_m] from the sensor are left out. ``out`` is written whole (a temp
    folder renamed at the end) and replaces only a folder this command wrote."""
    from blockloc.app.catalog import open_sequence
    from blockloc.datasets.dynamicmap import DynamicMapWriter
    from blockloc.datasets.with_poses import load_trajectory
    from blockloc.fileio import atomic_dir
    from blockloc.maps.mapping import scan_to_map
    from blockloc.outdir import DYNAMIC_MAP

    # every point as the file holds it: the range filter below applies to points and labels alike
    seq = open_sequence(seq_name, data_root=data_root,
                        dataset_cfg=SimpleNamespace(min_range_m=0.0, max_range_m=1e9))
    if poses is not None:
        traj = load_trajectory(poses, what="--poses")[0]
    else:
        traj = seq.ground_truth()
        if traj is None or not len(traj):
            traj = seq.mapping_poses()
    if traj is None or not len(traj):
        raise DatasetError(f"{seq_name}: no ground truth or mapping poses; give --poses TRAJECTORY")
    n = len(seq)
    if not 0 <= start < n:
        raise DatasetError(f"--start {start}: the sequence has frames 0..{n - 1}")
    idx = np.arange(start, n, max(1, int(step)))
    if frames is not None:
        idx = idx[: int(frames)]
    stamps = seq.frame_stamps()[idx]
    inside = (stamps >= traj.stamps[0] - 0.05) & (stamps <= traj.stamps[-1] + 0.05)
    if not inside.all():
        log.warning("%s: %d of %d frames outside the poses' time span, left out", seq_name,
                    int((~inside).sum()), len(idx))
        idx = idx[inside]
    if not len(idx):
        raise DatasetError(f"{seq_name}: no frame within the poses' time span")
    T_body_lidar = np.asarray(seq.info.T_body_lidar, float)
    labelled = _labels_fn(seq)
    with atomic_dir(out, DYNAMIC_MAP) as tmp:
        w = DynamicMapWriter(tmp)
        for done, i in enumerate(idx, 1):
            if labelled is not None:
                frame, dyn = labelled(int(i))
            else:
                frame, dyn = seq.frame(int(i)), None
            pts = np.asarray(frame.points, np.float64)
            r2 = np.einsum("ij,ij->i", pts, pts)
            keep = np.isfinite(r2) & (r2 >= min_range_m ** 2) & (r2 <= max_range_m ** 2)
            offsets = None if frame.time_offsets is None else np.asarray(frame.time_offsets)[keep]
            pw = scan_to_map(pts[keep], offsets, frame.stamp, traj, T_body_lidar)
            T_world_lidar = traj.interpolate(np.array([frame.stamp]))[0] @ T_body_lidar
            inten = None if frame.intensity is None else np.asarray(frame.intensity)[keep]
            w.add_scan(pw, T_world_lidar, None if dyn is None else dyn[keep], intensity=inten)
            if progress is not None:
                progress(done, len(idx))
        w.finish()
    return ExportSummary(Path(out), w.scans, w.points, w.dynamic_points, labelled is not None,
                         int(idx[0]), int(idx[-1]))
