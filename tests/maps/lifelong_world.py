"""A small synthetic world for the lifelong-map tests, with known changes.

World (map frame, z up, metres): flat ground; a street along x (y = 0) between two long building
rows (y = +-11); a few pillars; on the mapping day a garden wall W at x 2..10, y 5.8..6.2.
On the run day: the wall W is gone (removed), a box B stands at x -8..-5, y -7.5..-4.5 (added),
a parked car C at x 4..8.5, y -6..-4.2 (1.5 m tall) is gone (removed) and a pedestrian walks
across the street at x = 12 (dynamic). Day "nowall": only W is gone.

A drive goes along y = 0 from x = -24 to 24, sensor 1.2 m above the ground, a scan every 0.25 m:
32 beams from -25 to +12 deg, 720 columns. Scans are cast with open3d's RaycastingScene.
Written as scan folders (``blockloc.datasets.scanfolder``: scans/*.bin, times.txt, poses.tum,
extrinsics.yaml: body = lidar, gravity -z) and a block map store (two blocks split at x = 0,
keyframes recorded), and run folders (poses.tum, diagnostics.csv, metrics.json) as
``blockloc track`` writes them.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

WALL_W = (2.0, 10.0, 5.8, 6.2, 0.0, 3.5)  # reaches into the place index's 2-4 m band
BOX_B = (-8.0, -5.0, -7.5, -4.5, 0.0, 2.0)
CAR_C = (4.0, 8.5, -6.0, -4.2, 0.0, 1.5)  # a parked car on the mapping day, gone on the run day
PED_X = 12.0
SENSOR_Z = 1.2


def _box(x0, x1, y0, y1, z0, z1):
    import open3d as o3d

    m = o3d.geometry.TriangleMesh.create_box(x1 - x0, y1 - y0, z1 - z0)
    m.translate((x0, y0, z0))
    return np.asarray(m.vertices, np.float32), np.asarray(m.triangles, np.uint32)


def static_boxes():
    return [(-40, 40, -40, 40, -1.0, 0.0),  # ground slab
            (-30, 30, 11, 13, 0, 8), (-30, 30, -13, -11, 0, 6),  # building rows
            (-15, -14.4, 7, 7.6, 0, 4), (16, 16.6, -8, -7.4, 0, 4), (-2, -1.4, -8.5, -7.9, 0, 4)]


def scene(day: str, t: float = 0.0):
    from blockloc.open3d_loader import open3d

    o3d = open3d()
    sc = o3d.t.geometry.RaycastingScene()
    boxes = list(static_boxes())
    if day == "map":
        boxes += [WALL_W, CAR_C]
    elif day == "nowall":  # only the wall gone: block 000 (x < 0) sees no change
        boxes.append(CAR_C)
    else:
        boxes.append(BOX_B)
        y = -8.0 + 1.4 * t  # walks +y at 1.4 m/s
        if -9 < y < 9:
            boxes.append((PED_X - 0.25, PED_X + 0.25, y - 0.25, y + 0.25, 0.0, 1.7))
    for b in boxes:
        V, F = _box(*b)
        sc.add_triangles(o3d.core.Tensor(V), o3d.core.Tensor(F))
    return sc


def beams(cols: int = 720) -> np.ndarray:
    el = np.deg2rad(np.linspace(-25, 12, 32))
    az = np.linspace(0, 2 * np.pi, cols, endpoint=False)
    E, A = np.meshgrid(el, az, indexing="ij")
    return np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], -1).reshape(-1, 3)


def drive(step_m: float = 0.25) -> np.ndarray:
    """(N, 4, 4) T_map_lidar along the street."""
    xs = np.arange(-24.0, 24.0 + 1e-9, step_m)
    T = np.tile(np.eye(4), (len(xs), 1, 1))
    T[:, 0, 3] = xs
    T[:, 2, 3] = SENSOR_Z
    return T


def cast(day: str, T_map_lidar: np.ndarray, t: float, max_range: float = 40.0) -> np.ndarray:
    """(N, 3) float32 points in the lidar frame."""
    from blockloc.open3d_loader import open3d

    o3d = open3d()
    d = beams()
    o = np.broadcast_to(T_map_lidar[:3, 3], d.shape)
    rays = np.concatenate([o, d], 1).astype(np.float32)
    hit = scene(day, t).cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
    ok = np.isfinite(hit) & (hit < max_range)
    return (d[ok] * hit[ok, None]).astype(np.float32)  # lidar frame = map axes (no rotation)


def write_scan_folder(out: Path, day: str, T: np.ndarray, t0: float = 1000.0, dt: float = 0.1) -> Path:
    from blockloc.trajectory_io import write_tum
    from blockloc.geometry import Trajectory

    (out / "scans").mkdir(parents=True)
    stamps = t0 + dt * np.arange(len(T))
    for i, T_i in enumerate(T):
        p = cast(day, T_i, i * dt)
        np.c_[p, np.full(len(p), 50.0, np.float32)].astype(np.float32).tofile(out / "scans" / f"{i:06d}.bin")
    (out / "times.txt").write_text("".join(f"{s:.6f}\n" for s in stamps))
    write_tum(out / "poses.tum", Trajectory(stamps, T.copy()))
    (out / "extrinsics.yaml").write_text("T_body_lidar: [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]\n"
                                         "gravity_map: [0, 0, -9.81]\n")
    return out


def build_map(out: Path, T: np.ndarray, voxel_m: float = 0.2) -> Path:
    """A block store of the mapping day's scans: block 000 holds the points with x < 0 and the
    keyframes there, 001 those with x >= 0 (a partition: a change on one side leaves the other
    block alone)."""
    from blockloc.maps.store import MapWriter
    from blockloc.voxels import voxel_downsample

    pts = {"000": [], "001": []}
    kf = {"000": [], "001": []}
    for i, T_i in enumerate(T):
        p = cast("map", T_i, 0.0).astype(np.float64) + T_i[:3, 3]
        pts["000"].append(p[p[:, 0] < 0])
        pts["001"].append(p[p[:, 0] >= 0])
        kf["000" if T_i[0, 3] < 0 else "001"].append(T_i[:3, 3])
    with MapWriter(out, "block", params={"block_size_m": 24.0, "voxel_size_m": voxel_m}) as w:
        for b in ("000", "001"):
            P, I = voxel_downsample(np.concatenate(pts[b]), voxel_m, np.full(sum(map(len, pts[b])), 50.0))
            w.add(b, P, I, keyframes=np.array(kf[b][::2]))
        return w.commit()


def write_run(out: Path, seq_dir: Path, T_map_body: np.ndarray, status: list[str], t0: float = 1000.0,
              dt: float = 0.1) -> Path:
    """A run folder as ``blockloc track`` leaves it: poses of every frame with a pose, statuses."""
    from blockloc.trajectory_io import write_tum
    from blockloc.geometry import Trajectory

    out.mkdir(parents=True)
    stamps = t0 + dt * np.arange(len(T_map_body))
    write_tum(out / "poses.tum", Trajectory(stamps, np.asarray(T_map_body)))
    lines = ["index,stamp,status,fitness"] + [f"{i},{s:.9f},{st},0.9" for i, (s, st) in enumerate(zip(stamps, status))]
    (out / "diagnostics.csv").write_text("\n".join(lines) + "\n")
    (out / "metrics.json").write_text(json.dumps({"sequence": str(seq_dir)}))
    return out


class ArraySequence:
    """The run day's drive as a Sequence (frames cast on demand), for the pure pipeline tests."""

    def __init__(self, day: str, T: np.ndarray, dt: float = 0.1):
        from blockloc.datasets.base import SequenceInfo

        self.day, self.T, self.dt = day, T, dt
        self.info = SequenceInfo(name=f"synthetic:{day}", T_body_lidar=np.eye(4), T_body_imu=np.eye(4),
                                 gravity_map=np.array([0.0, 0.0, -9.81]), lidar_rate_hz=10.0, imu_rate_hz=0.0)

    def __len__(self):
        return len(self.T)

    def frame(self, i):
        from blockloc.datasets.base import LidarFrame

        p = cast(self.day, self.T[i], i * self.dt)
        return LidarFrame(i, 1000.0 + i * self.dt, p, np.full(len(p), 50.0, np.float32), None, None)
