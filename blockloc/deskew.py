"""Scan preprocessing: range filter, voxel downsampling that keeps per-point times, deskewing.

Deskewing follows the block-map paper (eqs 8-10): each point, measured at its own time t_i, is
moved into the lidar frame at the scan time t_k with the relative motion T_{k,i}, whose rotation
comes from IMU integration and whose translation from the velocity at t_k (constant velocity):

    T_map_body(t_i) = [ R_imu(t_i) | p_k + v_k (t_i - t_k) ]
    p_k = (T_map_body(t_k) T_body_lidar)^-1  T_map_body(t_i) T_body_lidar  p_i

The motion is given as a small table of poses (one per IMU sample over the sweep); points are
interpolated inside it (slerp of rotation, linear translation), all vectorized: no per-point Python.
"""

from __future__ import annotations

import numpy as np

from blockloc.geometry import inv_T, so3_log


def range_filter(points: np.ndarray, min_range_m: float, max_range_m: float) -> np.ndarray:
    """Boolean mask (N,) of finite points whose range lies in [min_range_m, max_range_m]."""
    from blockloc.voxels import in_range

    return in_range(points, min_range_m, max_range_m)


def voxel_downsample_indices(points: np.ndarray, voxel_size_m: float, max_points: int = 0,
                             seed: int = 0, range_m: tuple[float, float] | None = None) -> np.ndarray:
    """Indices of one point per occupied voxel (the first in input order, ``blockloc.voxels.
    voxel_select``), sorted.

    points: (N, 3) any frame, metres. Keeping a real point (not a centroid) keeps its time offset
    exact for deskewing. range_m: (min, max) metres: only finite points in that range count (the
    range filter in the same pass). When more than ``max_points`` (> 0) remain, a fixed-seed
    random subset.
    """
    from blockloc.voxels import voxel_select

    idx = voxel_select(points, voxel_size_m, range_m)
    if max_points > 0 and len(idx) > max_points:
        rng = np.random.default_rng(seed)
        idx = np.sort(rng.choice(idx, size=max_points, replace=False))
    return idx


def lidar_motion_table(T_map_body: np.ndarray, T_body_lidar: np.ndarray, ref: int | np.ndarray) -> np.ndarray:
    """(K, 4, 4) ``T_lidarref_lidar(t_j)`` from body poses (K, 4, 4) at the table times.

    ref: index into the table of the scan-time pose, or a (4, 4) T_map_body at the scan time.
    """
    T_map_lidar = T_map_body @ T_body_lidar
    T_ref = T_map_lidar[ref] if np.ndim(ref) == 0 else np.asarray(ref) @ T_body_lidar
    return inv_T(T_ref)[None] @ T_map_lidar


def _one_transform(pts: np.ndarray, table_times: np.ndarray, T_ref_table: np.ndarray) -> np.ndarray | None:
    """The points moved by the table's one transform when there is nothing to interpolate (one
    table entry or no points), else None."""
    if len(table_times) == 1 or len(pts) == 0:
        T = T_ref_table[0]
        return pts @ T[:3, :3].T + T[:3, 3]
    return None


def deskew_points(points: np.ndarray, times: np.ndarray, table_times: np.ndarray,
                  T_ref_table: np.ndarray) -> np.ndarray:
    """Move points measured at their own times into the reference lidar frame.

    points: (N, 3) lidar frame at each point's time, metres.
    times: (N,) seconds on the same clock as ``table_times``.
    table_times: (K,) increasing seconds, K >= 1; times outside are clamped to the ends.
    T_ref_table: (K, 4, 4) ``T_lidarref_lidar(table_times[j])``.
    Returns (N, 3) float64 in the reference lidar frame.
    """
    pts, table_times = np.asarray(points, dtype=np.float64), np.asarray(table_times, dtype=np.float64)
    rigid = _one_transform(pts, table_times, T_ref_table)
    if rigid is not None:
        return rigid
    K = len(table_times)
    R = np.ascontiguousarray(T_ref_table[:, :3, :3], dtype=np.float64)
    from blockloc._deskew_kernels import deskew_kernel, interval_rotvecs

    # Per-interval relative rotation vectors w_j = log(R_j^T R_{j+1}).
    w_int, ok = interval_rotvecs(R)
    if not ok:  # an interval turning by more than 3 rad: the log that is exact near pi
        w_int = np.ascontiguousarray(so3_log(np.swapaxes(R[:-1], 1, 2) @ R[1:]).reshape(K - 1, 3))
    trans = np.ascontiguousarray(T_ref_table[:, :3, 3])

    return deskew_kernel(np.ascontiguousarray(pts), np.ascontiguousarray(times, dtype=np.float64),
                         np.ascontiguousarray(table_times), R, w_int, trans)


def deskew_points_numpy(points: np.ndarray, times: np.ndarray, table_times: np.ndarray,
                        T_ref_table: np.ndarray) -> np.ndarray:
    """Reference (pure numpy) version of :func:`deskew_points`, same arguments and result."""
    pts, table_times = np.asarray(points, dtype=np.float64), np.asarray(table_times, dtype=np.float64)
    rigid = _one_transform(pts, table_times, T_ref_table)
    if rigid is not None:
        return rigid
    K = len(table_times)
    t = np.clip(np.asarray(times, dtype=np.float64), table_times[0], table_times[-1])
    j = np.clip(np.searchsorted(table_times, t, side="right") - 1, 0, K - 2)
    span = table_times[j + 1] - table_times[j]
    alpha = np.where(span > 0, (t - table_times[j]) / np.where(span > 0, span, 1.0), 0.0)
    R = T_ref_table[:, :3, :3]
    # Per-interval relative rotation vectors w_j = log(R_j^T R_{j+1}).
    w_int = so3_log(np.swapaxes(R[:-1], 1, 2) @ R[1:])  # (K-1, 3)
    w = w_int[j] * alpha[:, None]  # (N, 3)
    theta = np.linalg.norm(w, axis=1)
    small = theta < 1e-9
    k = w / np.where(small, 1.0, theta)[:, None]
    c, s = np.cos(theta), np.sin(theta)
    # Rodrigues: rotate p by exp(w), then by R_j, then add the interpolated translation.
    kxp = np.cross(k, pts)
    kdp = np.einsum("ij,ij->i", k, pts)
    rot = pts * c[:, None] + kxp * s[:, None] + k * (kdp * (1.0 - c))[:, None]
    rot = np.where(small[:, None], pts, rot)
    out = np.einsum("nij,nj->ni", R[j], rot)
    tr = T_ref_table[:, :3, 3]
    out += tr[j] + (tr[j + 1] - tr[j]) * alpha[:, None]
    return out
