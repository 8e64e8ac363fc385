"""Shared steps of map building: keyframe selection, deskewed scans in the map frame, voxel filter.

Pure functions on numpy arrays, plus :func:`mapping_keyframes`, the generator that reads a mapping
sequence (a :class:`~blockloc.datasets.base.Sequence` with poses) and yields its keyframes'
points in the map frame.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Callable, Iterator

import numpy as np

from blockloc.datasets.with_poses import POSE_TIME_TOLERANCE_S  # frames outside: not mapped
from blockloc.errors import MapError
from blockloc.geometry import Trajectory, rotation_angle

log = logging.getLogger(__name__)

# Per-point deskew: poses are interpolated at this many instants across a sweep; at 10 Hz and
# 1.5 m/s one bin is 3 ms, i.e. < 5 mm of motion.
DESKEW_BINS = 32


@dataclass
class Keyframe:
    """A mapping keyframe: its frame index, ``T_map_lidar`` (4, 4) at the frame stamp, and its
    points (N, 3) float64 in the map frame (metres) with intensity (N,) float32 or None."""

    index: int
    T_map_lidar: np.ndarray
    points_map: np.ndarray
    intensity: np.ndarray | None

    @property
    def position(self) -> np.ndarray:
        return self.T_map_lidar[:3, 3]


def select_keyframes(poses: np.ndarray, distance_m: float, angle_deg: float) -> np.ndarray:
    """Indices of keyframes among ``poses`` (F, 4, 4): the first, then every pose farther than
    ``distance_m`` (3D) or rotated more than ``angle_deg`` from the previous keyframe."""
    if len(poses) == 0:
        return np.zeros(0, dtype=np.int64)
    keep = [0]
    last = poses[0]
    max_angle = np.deg2rad(angle_deg)
    for i in range(1, len(poses)):
        d = np.linalg.norm(poses[i, :3, 3] - last[:3, 3])
        a = rotation_angle(last[:3, :3].T @ poses[i, :3, :3])
        if d > distance_m or a > max_angle:
            keep.append(i)
            last = poses[i]
    return np.asarray(keep, dtype=np.int64)


def scan_to_map(points: np.ndarray, time_offsets: np.ndarray | None, stamp: float,
                trajectory: Trajectory, T_body_lidar: np.ndarray,
                deskew: bool = True) -> np.ndarray:
    """Points (N, 3) lidar frame -> (N, 3) float64 map frame through ``T_map_body @ T_body_lidar``.

    With per-point ``time_offsets`` (N,) seconds and ``deskew``, each point is moved with the pose
    at its own time (poses interpolated at :data:`DESKEW_BINS` instants across the sweep), which is
    how mapping data with known poses removes motion distortion.
    """
    pts = np.asarray(points, np.float64)
    lo_t = stamp + (float(np.min(time_offsets)) if time_offsets is not None and len(pts) else 0.0)
    hi_t = stamp + (float(np.max(time_offsets)) if time_offsets is not None and len(pts) else 0.0)
    trajectory = _window(trajectory, min(lo_t, stamp), max(hi_t, stamp))
    if not deskew or time_offsets is None or len(pts) == 0:
        T = trajectory.interpolate(np.array([stamp]))[0] @ T_body_lidar
        return pts @ T[:3, :3].T + T[:3, 3]
    dt = np.asarray(time_offsets, np.float64)
    lo, hi = float(dt.min()), float(dt.max())
    if hi - lo < 1e-6:
        T = trajectory.interpolate(np.array([stamp + lo]))[0] @ T_body_lidar
        return pts @ T[:3, :3].T + T[:3, 3]
    edges = np.linspace(lo, hi, DESKEW_BINS + 1)
    centres = 0.5 * (edges[:-1] + edges[1:])
    bins = np.clip(np.searchsorted(edges, dt, side="right") - 1, 0, DESKEW_BINS - 1)
    Ts = trajectory.interpolate(stamp + centres) @ T_body_lidar
    R = Ts[bins, :3, :3]
    t = Ts[bins, :3, 3]
    return np.einsum("nij,nj->ni", R, pts) + t


def _window(trajectory: Trajectory, t0: float, t1: float) -> Trajectory:
    """The poses bracketing [t0, t1] (interpolating over a long trajectory rebuilds its whole
    slerp table: a 100 Hz campus drive made each scan cost half a second)."""
    i0 = max(int(np.searchsorted(trajectory.stamps, t0, side="right")) - 2, 0)
    i1 = min(int(np.searchsorted(trajectory.stamps, t1, side="left")) + 2, len(trajectory))
    if i0 == 0 and i1 == len(trajectory):
        return trajectory
    return Trajectory(trajectory.stamps[i0:i1], trajectory.poses[i0:i1])


def mapping_poses_or_fail(seq) -> Trajectory:
    """The sequence's mapping poses (offline SLAM or ground truth), or MapError."""
    name = getattr(getattr(seq, "info", None), "name", "sequence")
    if len(seq) == 0:
        raise MapError(f"{name}: empty session (no LiDAR frames) to build a map from")
    traj = seq.mapping_poses()
    if traj is None or len(traj) == 0:
        raise MapError(f"{name}: no mapping poses (offline-SLAM or ground truth) to build a map from")
    return traj


@dataclass
class KeyframePlan:
    """Which frames of a mapping sequence are keyframes, and their poses: what map building needs
    before any scan is read.

    frames: (K,) int64 frame indices, time order. T_map_lidar: (K, 4, 4) at the frame stamps.
    stamps: (K,) float64 seconds. num_frames: frames considered (the slice's length).
    """

    frames: np.ndarray
    T_map_lidar: np.ndarray
    stamps: np.ndarray
    num_frames: int

    @property
    def positions(self) -> np.ndarray:
        """(K, 3) sensor positions, map frame, metres."""
        return self.T_map_lidar[:, :3, 3]


def plan_keyframes(seq, *, keyframe_distance_m: float, keyframe_angle_deg: float,
                   start: int = 0, stop: int | None = None) -> KeyframePlan:
    """Keyframes among frames ``start..stop-1`` of a mapping sequence (no scan is read).

    Poses come from ``seq.mapping_poses()`` interpolated at the frame stamps; frames outside the
    poses' time range, and frames the sequence lists in ``uncovered_frames()`` (a trajectory with
    gaps, :mod:`blockloc.datasets.with_poses`), are skipped: poses are never extrapolated.
    """
    traj = mapping_poses_or_fail(seq)
    all_stamps = np.asarray(seq.frame_stamps(), np.float64)
    stop = len(all_stamps) if stop is None else min(int(stop), len(all_stamps))
    start = max(int(start), 0)
    stamps = all_stamps[start:stop]
    ok = ((stamps >= traj.stamps[0] - POSE_TIME_TOLERANCE_S)
          & (stamps <= traj.stamps[-1] + POSE_TIME_TOLERANCE_S))
    uncovered = getattr(seq, "uncovered_frames", None)
    if uncovered is not None:
        skip = np.asarray(uncovered(), np.int64) - start
        ok[skip[(skip >= 0) & (skip < len(ok))]] = False
    inside = np.flatnonzero(ok)
    name = seq.info.name
    if len(inside) == 0:
        raise MapError(f"{name}: no LiDAR frame {start}..{stop - 1} lies within the mapping poses' "
                       f"time range [{traj.stamps[0]:.3f}, {traj.stamps[-1]:.3f}] s")
    T_body_lidar = np.asarray(seq.info.T_body_lidar, np.float64)
    # the poses bracketing the slice only: interpolating over a whole city drive (~340k poses)
    # builds its slerp table, ~0.5 s, for the 4000 frames of a short build (the same values)
    span = _window(traj, float(stamps[inside[0]]), float(stamps[inside[-1]]))
    poses = span.interpolate(stamps[inside]) @ T_body_lidar
    chosen = select_keyframes(poses, keyframe_distance_m, keyframe_angle_deg)
    log.info("%s: %d keyframes from %d frames", name, len(chosen), len(stamps))
    return KeyframePlan((inside[chosen] + start).astype(np.int64), poses[chosen],
                        stamps[inside[chosen]], len(stamps))


def keyframe_points(seq, index: int, trajectory: Trajectory, T_body_lidar: np.ndarray,
                    deskew: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
    """Frame ``index`` read and moved into the map frame: points (N, 3) float64 (deskewed with
    per-point times when ``deskew``), intensity (N,) or None."""
    frame = seq.frame(int(index))
    pts_map = scan_to_map(frame.points, frame.time_offsets, frame.stamp, trajectory, T_body_lidar,
                          deskew=deskew)
    return pts_map, frame.intensity


def mapping_keyframes(seq, *, keyframe_distance_m: float, keyframe_angle_deg: float,
                      deskew: bool = True, progress: Callable[[int, int], None] | None = None,
                      max_frames: int | None = None) -> Iterator[Keyframe]:
    """Keyframes of a mapping sequence with their (deskewed) points in the map frame
    (:func:`plan_keyframes`, then :func:`keyframe_points`). Only the keyframes' scans are read.
    progress: called ``(keyframes done, keyframes planned)`` as each next keyframe is asked for,
    so a keyframe counts once the caller has handled it."""
    plan = plan_keyframes(seq, keyframe_distance_m=keyframe_distance_m,
                          keyframe_angle_deg=keyframe_angle_deg, stop=max_frames)
    traj = mapping_poses_or_fail(seq)
    T_body_lidar = np.asarray(seq.info.T_body_lidar, np.float64)
    total = len(plan.frames)
    for k, (i, T_map_lidar) in enumerate(zip(plan.frames.tolist(), plan.T_map_lidar)):
        pts_map, intensity = keyframe_points(seq, i, traj, T_body_lidar, deskew)
        yield Keyframe(int(i), T_map_lidar, pts_map, intensity)
        if progress is not None:
            progress(k + 1, total)
