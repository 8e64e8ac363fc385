"""The 3D-BBS baseline's plumbing (bench/_bbs3d.py): frames, the search box, and the one-line reasons
it gives when it cannot be built. The end-to-end search runs only where the library can be built."""

from __future__ import annotations

import os

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bench import _bbs3d
from blockloc.global_init.projection import R_level_from_gravity


def _T(R, t):
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


class _Oracle:
    """Stands in for the driver: answers with the true T_L_lvl, and keeps what it was asked."""

    def __init__(self, T_L_lvl):
        self.T_L_lvl = T_L_lvl
        self.asked = None

    def localize(self, pts, lo, hi, **kw):
        self.asked = (np.asarray(pts), np.asarray(lo), np.asarray(hi))
        return _bbs3d.BBSResult(self.T_L_lvl, True, False, 1.0, 0.01)


def test_localize_hinted_composes_the_frames_back_to_T_map_body():
    rng = np.random.default_rng(0)
    R_map_L = Rotation.from_euler("xyz", [0.02, -0.03, 0.4]).as_matrix()  # a tilted map frame
    R_L_map = R_map_L.T
    T_map_body = _T(Rotation.from_euler("xyz", [0.05, -0.04, 2.0]).as_matrix(), [12.0, -7.0, 1.5])
    g_map = R_map_L @ np.array([0.0, 0.0, -9.81])
    g_body = T_map_body[:3, :3].T @ g_map
    R_lvl_body = R_level_from_gravity(g_body)
    T_L_lvl = _T(R_L_map, np.zeros(3)) @ T_map_body @ np.linalg.inv(_T(R_lvl_body, np.zeros(3)))
    oracle = _Oracle(T_L_lvl)
    pts = rng.uniform(-30, 30, (5000, 3))
    T, res = _bbs3d.localize_hinted(oracle, pts, g_body, R_L_map, np.array([10.0, -5.0]), 40.0, (-2.0, 8.0))
    assert res.localized
    np.testing.assert_allclose(T, T_map_body, atol=1e-9)
    scan, lo, hi = oracle.asked
    np.testing.assert_allclose(lo, [-10.0, -25.0, -2.0])
    np.testing.assert_allclose(hi, [30.0, 15.0, 8.0])
    assert len(scan) < len(pts)  # thinned to its 2 m voxels
    # The scan it gets is levelled: its points are the body's rotated by R_lvl_body.
    lvl = pts @ R_lvl_body.T
    assert np.isin(scan.round(9), lvl.round(9)).all()


def test_a_source_that_is_not_3d_bbs_is_one_line(tmp_path, monkeypatch):
    monkeypatch.setenv("BLOCKLOC_CACHE", str(tmp_path / "cache"))
    monkeypatch.setenv("BLOCKLOC_BBS3D_SRC", str(tmp_path))
    (tmp_path / "cache").mkdir()
    with pytest.raises(_bbs3d.Unavailable) as e:
        _bbs3d._source()
    assert str(tmp_path) in str(e.value) and "\n" not in str(e.value)


def _buildable() -> str | None:
    try:
        _bbs3d.ensure_built()
    except _bbs3d.Unavailable as e:
        return str(e)
    return None


@pytest.mark.skipif(not os.environ.get("BLOCKLOC_BBS3D_SRC"),
                    reason="3D-BBS sources not given (BLOCKLOC_BBS3D_SRC): the baseline is built only for benchmarks")
def test_the_driver_finds_a_known_pose(tmp_path):
    why = _buildable()
    if why and ("not installed" in why or "headers missing" in why):
        pytest.skip(f"3D-BBS cannot be built here: {why}")  # an absent compiler or library, not our driver
    assert why is None, f"the 3D-BBS driver did not build from the given sources: {why}"
    rng = np.random.default_rng(1)
    # A walled yard with a few posts: structure in every direction.
    walls = [rng.uniform([-20, -20, 0], [20, -19.8, 4], (6000, 3)), rng.uniform([-20, 19.8, 0], [20, 20, 4], (6000, 3)),
             rng.uniform([-20, -20, 0], [-19.8, 12, 4], (5000, 3)), rng.uniform([19.8, -5, 0], [20, 20, 4], (5000, 3)),
             rng.uniform([-3, 4, 0], [-2, 5, 3], (800, 3)), rng.uniform([6, -9, 0], [8, -8, 2], (800, 3)),
             rng.uniform([-20, -20, -0.05], [20, 20, 0.05], (20000, 3))]
    world = np.vstack(walls)
    T_map_body = _T(Rotation.from_euler("z", 1.1).as_matrix(), [3.0, -2.0, 1.0])
    scan = (world - T_map_body[:3, 3]) @ T_map_body[:3, :3]  # the whole yard seen from the body
    with _bbs3d.BBS3D(world, min_level_res=0.5, max_level=5) as drv:
        T, res = _bbs3d.localize_hinted(drv, scan, np.array([0, 0, -9.81]), np.eye(3), np.array([0.0, 0.0]),
                                        20.0, (-1.0, 3.0), scan_voxel_m=1.0, timeout_s=30.0)
    assert res.localized
    assert np.linalg.norm(T[:3, 3] - T_map_body[:3, 3]) < 1.0
