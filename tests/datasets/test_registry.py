"""open_sequence: names under a data root, paths, sim names, and the one-line errors."""

from __future__ import annotations

import sys
from types import SimpleNamespace
import types

import numpy as np
import pytest

from blockloc.config import DatasetConfig
from blockloc.app.catalog import open_sequence
from blockloc.datasets.nclt import NCLT_T_BODY_LIDAR, NcltSequence, write_session
from blockloc.app.catalog import M2DGR_T_BODY_LIDAR, resolve_data_root
from blockloc.datasets.rosbag import RosbagSequence, write_rosbag
from blockloc.errors import DatasetError


def test_nclt_name_official_layout(tmp_path, session_data):
    # <root>/nclt/2012-01-22/{velodyne_sync, velodyne_hits.bin, ms25.csv}; ground truth beside it
    sess = write_session(tmp_path / "nclt" / "2012-01-22", date="2012-01-22",
                         frames=session_data["frames"], imu=session_data["imu"],
                         ground_truth=session_data["gt"])
    (sess / "groundtruth_2012-01-22.csv").rename(tmp_path / "nclt" / "groundtruth_2012-01-22.csv")
    seq = open_sequence("nclt_2", data_root=tmp_path)
    assert isinstance(seq, NcltSequence) and seq.info.name == "nclt_2"
    assert len(seq) == 4 and len(seq.ground_truth()) == len(session_data["gt"])
    np.testing.assert_allclose(seq.info.T_body_lidar, NCLT_T_BODY_LIDAR)


def test_nclt_sensor_data_in_separate_tree(tmp_path, session_data, monkeypatch):
    # velodyne tarball under <root>/<date>/, sensor tarball under <root>/sensor_data/<date>/
    sess = write_session(tmp_path / "2012-05-11", date="2012-05-11", frames=session_data["frames"],
                         imu=session_data["imu"], ground_truth=session_data["gt"])
    (tmp_path / "sensor_data" / "2012-05-11").mkdir(parents=True)
    (sess / "ms25.csv").rename(tmp_path / "sensor_data" / "2012-05-11" / "ms25.csv")
    monkeypatch.setenv("BLOCKLOC_DATA", str(tmp_path))
    seq = open_sequence("nclt_5")
    assert len(seq.imu()) == len(session_data["imu"])


def test_missing_nclt_names_expected_path(tmp_path):
    with pytest.raises(DatasetError) as ei:
        open_sequence("nclt_1", data_root=tmp_path)
    msg = str(ei.value)
    assert "\n" not in msg
    assert f"{tmp_path}/nclt/2012-01-15/velodyne_sync/" in msg and "2012-01-15_vel.tar.gz" in msg


def test_data_root_precedence(tmp_path, monkeypatch):
    monkeypatch.setenv("BLOCKLOC_DATA", "/from/env")
    assert str(resolve_data_root()) == "/from/env"
    assert str(resolve_data_root(dataset_cfg=DatasetConfig(data_root="/from/cfg"))) == "/from/cfg"
    assert str(resolve_data_root("/arg", DatasetConfig(data_root="/from/cfg"))) == "/arg"
    monkeypatch.delenv("BLOCKLOC_DATA")
    assert str(resolve_data_root()) == "data"


def test_path_to_session_and_config_ranges(tmp_path, session_data):
    sess = write_session(tmp_path / "loc", date="2030-01-01", frames=session_data["frames"],
                         imu=session_data["imu"], ground_truth=session_data["gt"])
    near = open_sequence(str(sess), dataset_cfg=DatasetConfig(min_range_m=0.5, max_range_m=20.0))
    assert isinstance(near, NcltSequence)
    assert np.linalg.norm(near.frame(0).points, axis=1).max() <= 20.0
    assert len(open_sequence(sess).ground_truth()) == len(session_data["gt"])


@pytest.mark.parametrize("version", ["ros1", "ros2-sqlite3"])
def test_path_to_bags_and_topics(tmp_path, session_data, version):
    path = tmp_path / ("x.bag" if version == "ros1" else "x")
    write_rosbag(path, session_data["frames"], session_data["imu"], version=version,
                 lidar_topic="/points", imu_topic="/imu_raw")
    seq = open_sequence(path, lidar_topic="/points", imu_topic="/imu_raw")
    assert isinstance(seq, RosbagSequence) and len(seq) == 4
    seq2 = open_sequence(path, dataset_cfg=DatasetConfig(lidar_topic="/points", imu_topic="/imu_raw"))
    assert len(seq2.imu()) == len(session_data["imu"])
    with pytest.raises(DatasetError, match="no topic '/velodyne_points'"):
        open_sequence(path)


def test_m2dgr_name(tmp_path, session_data):
    (tmp_path / "m2dgr").mkdir()
    write_rosbag(tmp_path / "m2dgr" / "street_02.bag", session_data["frames"], session_data["imu"],
                 imu_topic="/handsfree/imu")
    (tmp_path / "m2dgr" / "street_02.txt").write_text("1326030000.0 1 2 3 0 0 0 1\n1326030000.1 2 2 3 0 0 0 1\n")
    seq = open_sequence("m2dgr_2", data_root=tmp_path)
    assert seq.info.name == "m2dgr_2"
    np.testing.assert_allclose(seq.info.T_body_lidar, M2DGR_T_BODY_LIDAR)
    np.testing.assert_allclose(seq.info.gravity_map, [0, 0, -9.81])
    assert len(seq.ground_truth()) == 2
    with pytest.raises(DatasetError, match=r"m2dgr_1: M2DGR street_01.bag not found: expected .*m2dgr/street_01.bag"):
        open_sequence("m2dgr_1", data_root=tmp_path)


def test_sim_names_dispatch(monkeypatch):
    calls = []
    mod = types.ModuleType("blockloc.sim.stream")
    mod.open_sim_sequence = lambda preset, session, seed: calls.append((preset, session, seed)) or SimpleNamespace(
        info="INFO")
    monkeypatch.setitem(sys.modules, "blockloc.sim.stream", mod)
    seq = open_sequence("sim:campus/loc@7", dataset_cfg=SimpleNamespace(min_range_m=2.0, max_range_m=80.0))
    # streamed: the dataset's range limits apply as the loaders apply them
    assert seq.info == "INFO" and (seq.min_range_m, seq.max_range_m) == (2.0, 80.0)
    assert open_sequence("sim:small/map").info == "INFO"
    assert calls == [("campus", "loc", 7), ("small", "map", 1)]
    # the changing world's later days open through blockloc.sim.changes
    later = types.ModuleType("blockloc.sim.changes")
    later.open_session = lambda preset, session, seed: calls.append(("changes", session)) or SimpleNamespace(
        info="LATER")
    monkeypatch.setitem(sys.modules, "blockloc.sim.changes", later)
    assert open_sequence("sim:small/loc_m12@2").info == "LATER" and calls[-1] == ("changes", "loc_m12")
    with pytest.raises(DatasetError, match=r"expected sim:<preset>/<session>\[@<seed>\]"):
        open_sequence("sim:campus")


def test_unknown_and_bad_paths(tmp_path):
    with pytest.raises(DatasetError, match=r"unknown sequence 'nclt_9': expected a path or one of nclt_1, .*m2dgr_2"):
        open_sequence("nclt_9")
    with pytest.raises(DatasetError, match="no such file or directory"):
        open_sequence(str(tmp_path / "missing" / "dir"))
    (tmp_path / "plain").mkdir()
    with pytest.raises(DatasetError, match="not a sequence; expected an NCLT-layout session"):
        open_sequence(tmp_path / "plain")
