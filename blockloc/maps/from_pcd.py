"""Maps for users who have only a global point-cloud map and the trajectory it was built along.

Block maps (Algorithm 1) are stitched from keyframes; without the scans, each keyframe's points
are what it could see: the global map cropped to ``sensor_range_m`` (3D distance) around the
keyframe's sensor position. :func:`keyframes_from_global_map` yields those crops as ordinary
:class:`~blockloc.maps.mapping.Keyframe` objects, so :class:`~blockloc.maps.block_maps.BlockMapBuilder`
applies unchanged. Grid maps keep the part of the global map within sensor range of any keyframe.

The crops come from a grid index over the map (cells of half the sensor range, built once with
``grid_tiles.split_into_tiles``): a query visits the ~25 cells around the keyframe and tests only
their points, so a keyframe costs in proportion to its crop, not to the map.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from blockloc.errors import MapError
from blockloc.geometry import Trajectory
from blockloc.maps.mapping import Keyframe, select_keyframes
from blockloc.voxels import voxel_downsample

log = logging.getLogger(__name__)


class _GridIndex:
    """Points (N, 3) bucketed in square xy cells of ``cell_m``; ``within(c, r)`` -> indices of the
    points within 3D distance r of c (grouped by cell, a deterministic order)."""

    def __init__(self, points: np.ndarray, cell_m: float):
        from blockloc.maps.grid_tiles import split_into_tiles

        self.points = points
        self.cell_m = float(cell_m)
        self.cells = split_into_tiles(points, self.cell_m) if len(points) else {}

    def within(self, centre: np.ndarray, radius_m: float) -> np.ndarray:
        c = np.asarray(centre, np.float64)
        s = self.cell_m
        lo = np.floor((c[:2] - radius_m) / s).astype(np.int64)
        hi = np.floor((c[:2] + radius_m) / s).astype(np.int64)
        parts = []
        for ix in range(lo[0], hi[0] + 1):
            # nearest x of the cell column to the centre: skip columns wholly out of range
            dx = max(ix * s - c[0], 0.0, c[0] - (ix + 1) * s)
            for iy in range(lo[1], hi[1] + 1):
                dy = max(iy * s - c[1], 0.0, c[1] - (iy + 1) * s)
                idx = self.cells.get((ix, iy))
                if idx is not None and dx * dx + dy * dy <= radius_m * radius_m:
                    parts.append(idx)
        if not parts:
            return np.zeros(0, np.int64)
        idx = np.concatenate(parts)
        d = self.points[idx].astype(np.float64) - c
        return idx[np.einsum("ij,ij->i", d, d) <= radius_m * radius_m]  # cell by cell, not sorted


def _keyframe_crops(points: np.ndarray, trajectory: Trajectory, sensor_range_m: float,
                    keyframe_distance_m: float, keyframe_angle_deg: float,
                    T_body_lidar: np.ndarray | None, progress: Callable[[int, int], None] | None = None
                    ) -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
    """(pose row, T_map_lidar (4, 4), indices of the points within range) per keyframe.
    progress: called ``(keyframes done, keyframes)`` as each next crop is asked for (a keyframe
    counts once the caller has handled its crop)."""
    if not sensor_range_m > 0:
        raise MapError(f"sensor range {sensor_range_m!r} m: expected a positive number")
    if points.ndim != 2 or points.shape[1] != 3:
        raise MapError(f"points: expected an (N, 3) array, got shape {points.shape}")
    if len(trajectory) == 0:
        raise MapError("mapping trajectory has no poses: no keyframe to crop the global map for")
    T_bl = np.eye(4) if T_body_lidar is None else np.asarray(T_body_lidar, np.float64)
    poses = trajectory.poses @ T_bl
    chosen = select_keyframes(poses, keyframe_distance_m, keyframe_angle_deg)
    index = _GridIndex(points, cell_m=sensor_range_m / 2.0)
    log.info("%d keyframes from %d poses; crops of %.1f m from a %d-point map", len(chosen),
             len(poses), sensor_range_m, len(points))
    for k, i in enumerate(chosen):
        idx = index.within(poses[i, :3, 3], sensor_range_m)
        if len(idx) == 0:
            log.warning("keyframe %d at %s: no map point within %.1f m", int(i),
                        np.round(poses[i, :3, 3], 2).tolist(), sensor_range_m)
        yield int(i), poses[i], idx
        if progress is not None:
            progress(k + 1, len(chosen))


def keyframes_from_global_map(points: np.ndarray, intensity: np.ndarray | None,
                              trajectory: Trajectory, *, sensor_range_m: float = 60.0,
                              keyframe_distance_m: float = 1.0, keyframe_angle_deg: float = 15.0,
                              T_body_lidar: np.ndarray | None = None) -> Iterator[Keyframe]:
    """Keyframes of ``trajectory`` holding the global map's points within their sensor range.

    points: (N, 3) global map, map frame, metres (finite); intensity: (N,) or None.
    trajectory: T_map_body poses (stamps are not used; untimed files work); T_body_lidar (4, 4)
    places the sensor (identity: body = lidar). Keyframes are selected as for a sequence
    (``mapping.select_keyframes``: the first pose, then one per ``keyframe_distance_m`` or
    ``keyframe_angle_deg``); keyframe ``index`` = the pose's row. Yields in trajectory order;
    ``points_map`` (M, 3) float64, map frame.
    """
    pts = np.asarray(points)
    inten = None if intensity is None else np.asarray(intensity, np.float32)
    for i, T_map_lidar, idx in _keyframe_crops(pts, trajectory, sensor_range_m, keyframe_distance_m,
                                               keyframe_angle_deg, T_body_lidar):
        yield Keyframe(i, T_map_lidar, pts[idx].astype(np.float64),
                       None if inten is None else inten[idx])


def build_map_from_global_pcd(pcd_path: str | Path, traj_path, kind: str, out: str | Path, *,
                              sensor_range_m: float = 60.0, keyframe_distance_m: float = 1.0,
                              keyframe_angle_deg: float = 15.0, block_size_m: float = 100.0,
                              tile_size_m: float = 20.0, voxel_size_m: float = 0.2,
                              frame_name: str | None = None, T_body_lidar: np.ndarray | None = None,
                              overwrite: bool = False,
                              progress: Callable[[int, int], None] | None = None):
    """``blockloc map build --from-pcd``: a block or grid store from a global map and a trajectory.

    pcd_path: the global map (PCD, PLY or KITTI .bin; read by ``datasets.pointclouds``), map frame.
    traj_path: its mapping trajectory (TUM, KITTI, NCLT csv path, or a Trajectory), T_map_body.
    kind: 'block' (keyframe crops stitched by Algorithm 1, ``block_size_m``) or 'grid' (the map
    within sensor range of the trajectory, tiles of ``tile_size_m``). The map is voxel-filtered
    (``voxel_size_m``) once before cropping, so overlapping crops repeat identical points; a block
    is given each of its points once (see the loop), with the same result as feeding
    :func:`keyframes_from_global_map` to ``build_block_map``. frame_name: the trajectory's
    frame, recorded in the store (grid: manifest ``frame``; block: ``parameters.trajectory_frame``). Written atomically to
    ``out``; returns the opened MapStore. progress: called ``(keyframes done, keyframes)``.
    """
    from blockloc.datasets.pointclouds import read_point_cloud
    from blockloc.datasets.with_poses import load_trajectory

    if kind not in ("block", "grid"):
        raise MapError(f"map kind {kind!r}: expected block or grid")
    cloud = read_point_cloud(pcd_path)
    if len(cloud) == 0:
        raise MapError(f"{pcd_path}: holds no finite points, nothing to build a map from")
    traj, _, label = load_trajectory(traj_path, what="mapping trajectory")
    frame = frame_name or "map"
    pts, inten = voxel_downsample(cloud.points.astype(np.float64), voxel_size_m, cloud.intensity)
    pts = pts.astype(np.float32)
    log.info("%s: %d points, %d after the %.2f m voxel filter", pcd_path, len(cloud), len(pts),
             voxel_size_m)
    params = {"source": str(pcd_path), "trajectory": label, "trajectory_frame": frame,
              "sensor_range_m": sensor_range_m, "keyframe_distance_m": keyframe_distance_m,
              "keyframe_angle_deg": keyframe_angle_deg}
    crops = _keyframe_crops(pts, traj, sensor_range_m, keyframe_distance_m, keyframe_angle_deg,
                            T_body_lidar, progress)
    seen = np.zeros(len(pts), bool)
    count = 0

    def check_seen():
        if not seen.any():
            raise MapError(f"{pcd_path}: no map point within {sensor_range_m} m of the trajectory "
                           f"{label}: do the map and the trajectory share a frame?")
        log.info("%d of %d map points within %.1f m of %d keyframes", int(seen.sum()), len(pts),
                 sensor_range_m, count)

    if kind == "grid":
        from blockloc.maps.grid_tiles import tile_global_map

        for _, _, idx in crops:  # only which points some keyframe sees
            seen[idx] = True
            count += 1
        check_seen()
        return tile_global_map(pts[seen], None if inten is None else inten[seen], tile_size_m, out,
                               frame=frame, params={**params, "voxel_size_m": voxel_size_m,
                                                    "num_keyframes": count}, overwrite=overwrite)

    from blockloc.maps.block_maps import BlockMapBuilder, write_block_map

    builder = BlockMapBuilder(block_size_m, voxel_size_m)
    in_block = np.zeros(len(pts), bool)  # points the open block already holds
    first = None
    for i, T_map_lidar, idx in crops:
        seen[idx] = True
        count += 1
        position = T_map_lidar[:3, 3]
        # Algorithm 1 closes a block at the first keyframe farther than S from the block's first
        # keyframe, and that keyframe also starts the next block: it goes in whole. Any other
        # keyframe brings only the points its block lacks: the block's union of crops (so its
        # voxel-filtered points and centroid) is the same, but each point passes the builder's
        # voxel filter about once per block instead of once per keyframe.
        if first is None or np.linalg.norm(position - first) > block_size_m:
            in_block[:] = False
            first = position
            rows = idx
        else:
            rows = idx[~in_block[idx]]
        in_block[idx] = True
        builder.add(i, position, pts[rows].astype(np.float64), None if inten is None else inten[rows])
    check_seen()
    builder.finish()
    return write_block_map(builder, out, params=params, overwrite=overwrite)
