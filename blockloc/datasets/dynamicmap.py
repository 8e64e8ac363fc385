"""The DynamicMap Benchmark layout (KTH-RPL/DynamicMap_Benchmark): write it and read it back.

A sequence in that layout is a folder::

    DIR/pcd/000000.pcd ...   one scan per file, points in the world frame (x y z intensity,
                             float32), the sensor pose in the header's VIEWPOINT
                             (tx ty tz qw qx qy qz: T_world_lidar)
    DIR/gt_cloud.pcd         every scan's points together, intensity 1 = dynamic, 0 = static

which is what DUFOMap, ERASOR, Removert and the benchmark's evaluation read. As the benchmark's
own extraction does, a scan file's intensity holds its points' ground-truth label when the
labels are known (the sensor's intensity otherwise). The world frame is the sequence's map frame
(blockloc's: for NCLT and the simulator z points down; the methods take the sensor origin from
VIEWPOINT and do not assume an up axis).

Pure writing and reading: the scans come in already moved into the world frame (the caller
deskews them with its poses, ``blockloc.app.dynamicmap``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import numpy as np

from blockloc.errors import DatasetError

PCD_DIR = "pcd"
GT_CLOUD = "gt_cloud.pcd"


def viewpoint_of(T_world_lidar: np.ndarray) -> np.ndarray:
    """(7,) ``tx ty tz qw qx qy qz`` of a (4, 4) pose (PCD VIEWPOINT order, unit quaternion)."""
    from scipy.spatial.transform import Rotation

    T = np.asarray(T_world_lidar, float)
    qx, qy, qz, qw = Rotation.from_matrix(T[:3, :3]).as_quat()
    return np.array([T[0, 3], T[1, 3], T[2, 3], qw, qx, qy, qz])


def pose_of_viewpoint(viewpoint) -> np.ndarray:
    """(4, 4) T_world_lidar of a VIEWPOINT ``tx ty tz qw qx qy qz``."""
    from scipy.spatial.transform import Rotation

    v = np.asarray(viewpoint, float).reshape(7)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat([v[4], v[5], v[6], v[3]]).as_matrix()
    T[:3, 3] = v[:3]
    return T


@dataclass
class DynamicMapWriter:
    """Writes scans into ``root`` (an existing, empty folder) in the layout above.

    ``add_scan`` writes ``pcd/NNNNNN.pcd`` (numbered from 0 in call order) and, when the scan has
    labels, keeps its points for ``gt_cloud.pcd``, written by :meth:`finish` (when every scan had
    labels; a sequence without them gets the scans only).
    """

    root: Path
    scans: int = 0
    points: int = 0
    dynamic_points: int = 0
    _gt: list = field(default_factory=list)
    _unlabelled: int = 0

    def __post_init__(self):
        self.root = Path(self.root)
        (self.root / PCD_DIR).mkdir(parents=True, exist_ok=True)

    def add_scan(self, points_world: np.ndarray, T_world_lidar: np.ndarray,
                 dynamic: np.ndarray | None = None, intensity: np.ndarray | None = None) -> Path:
        """One scan. points_world: (N, 3) world frame, m. T_world_lidar: (4, 4) the sensor pose.
        dynamic: (N,) bool ground truth (True = a moving object), or None. intensity: (N,) written
        when there are no labels (zeros when None). Returns the scan's path."""
        from blockloc.datasets.pointclouds import write_point_cloud

        pts = np.asarray(points_world, np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise DatasetError(f"scan {self.scans}: points of shape {pts.shape}, expected (N, 3)")
        if dynamic is not None:
            lab = np.asarray(dynamic, bool).reshape(-1)
            if len(lab) != len(pts):
                raise DatasetError(f"scan {self.scans}: {len(lab)} labels for {len(pts)} points")
            value = lab.astype(np.float32)
            self._gt.append((pts.astype(np.float32), value))
            self.dynamic_points += int(lab.sum())
        else:
            self._unlabelled += 1
            value = (np.zeros(len(pts), np.float32) if intensity is None
                     else np.asarray(intensity, np.float32).reshape(-1))
        path = self.root / PCD_DIR / f"{self.scans:06d}.pcd"
        write_point_cloud(path, pts.astype(np.float32), intensity=value, viewpoint=viewpoint_of(T_world_lidar))
        self.scans += 1
        self.points += len(pts)
        return path

    def finish(self) -> Path | None:
        """Write ``gt_cloud.pcd`` (all labelled points) when every scan was labelled; its path or
        None."""
        from blockloc.datasets.pointclouds import write_point_cloud

        if not self._gt or self._unlabelled:
            return None
        pts = np.concatenate([p for p, _ in self._gt])
        lab = np.concatenate([v for _, v in self._gt])
        self._gt = []
        return write_point_cloud(self.root / GT_CLOUD, pts, intensity=lab)


def scan_paths(root: str | Path) -> list[Path]:
    """The scan files of a DynamicMap folder, in order; DatasetError when there are none."""
    d = Path(root) / PCD_DIR
    paths = sorted(d.glob("*.pcd")) if d.is_dir() else []
    if not paths:
        raise DatasetError(f"{d}: no scans (expected pcd/NNNNNN.pcd files, the DynamicMap Benchmark layout)")
    return paths


def read_scan(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(points (N, 3) float64 world frame, T_world_lidar (4, 4) from VIEWPOINT, intensity (N,))."""
    import pypcd4

    try:
        pc = pypcd4.PointCloud.from_path(str(path))
    except Exception as exc:  # pypcd4 raises several kinds on a malformed file
        raise DatasetError(f"{path}: not a readable PCD ({exc})") from None
    names = pc.fields
    a = pc.numpy()
    if not {"x", "y", "z"} <= set(names):
        raise DatasetError(f"{path}: fields {' '.join(names)}, expected x y z")
    pts = np.stack([a[:, names.index(k)] for k in "xyz"], axis=1).astype(np.float64)
    inten = a[:, names.index("intensity")].astype(np.float32) if "intensity" in names else np.zeros(len(pts), np.float32)
    return pts, pose_of_viewpoint(pc.metadata.viewpoint), inten


def iter_scans(root: str | Path) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """(points (N, 3) world, T_world_lidar (4, 4)) of each scan of a DynamicMap folder, in order."""
    for p in scan_paths(root):
        pts, T, _ = read_scan(p)
        yield pts, T


def read_gt_cloud(root: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(points (N, 3) world, dynamic (N,) bool) of ``gt_cloud.pcd``."""
    path = Path(root) / GT_CLOUD
    if not path.is_file():
        raise DatasetError(f"{path}: missing (the labelled ground-truth cloud; export a sequence with labels)")
    pts, _, inten = read_scan(path)
    return pts, inten > 0.5
