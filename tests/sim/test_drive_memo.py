"""A drive's trajectory and mapping poses read back from the disk cache are the ones computed
afresh: the same poses, the same scans (a map build's workers read them from there)."""

import numpy as np
import pytest


@pytest.fixture
def memo_on_disk(tmp_path, monkeypatch):
    """A fresh cache root where even a tiny drive's trajectory and poses are written."""
    from blockloc.sim import stream

    monkeypatch.setenv("BLOCKLOC_CACHE", str(tmp_path))
    monkeypatch.setattr(stream, "DRIVE_MEMO_MIN_S", 0.0)
    stream.session_trajectory.cache_clear()
    yield tmp_path / "memo"
    stream.session_trajectory.cache_clear()


def _same_bytes(a, b) -> bool:
    a, b = np.asarray(a), np.asarray(b)
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


def test_a_drive_from_the_disk_cache_is_the_drive_computed_afresh(memo_on_disk, monkeypatch):
    from blockloc.sim import stream
    from blockloc.sim.presets import get_preset

    p = get_preset("tiny")
    first = stream.SimSequence(p, "map", 1)
    first.mapping_poses()
    names = sorted(f.name.split("-")[0] for f in memo_on_disk.glob("*.pkl"))
    assert names == ["mapping", "trajectory"]

    # a new process: nothing in memory, nothing may be recomputed
    stream.session_trajectory.cache_clear()
    direct_traj = stream.build_session_trajectory(p, 1, "map")
    direct_poses = first.compute_mapping_poses()
    with monkeypatch.context() as m:
        m.setattr(stream, "build_session_trajectory", lambda *a: pytest.fail("trajectory rebuilt"))
        m.setattr(stream.SimSequence, "compute_mapping_poses", lambda self: pytest.fail("poses rebuilt"))
        seq = stream.SimSequence(p, "map", 1)
        gt = seq.mapping_poses()
    t = np.linspace(0.0, direct_traj.duration, 2001)
    assert seq.trajectory.world is seq.world
    assert _same_bytes(seq.trajectory.T_world_flu(t), direct_traj.T_world_flu(t))
    for a, b in zip(seq.trajectory.imu_ideal(t), direct_traj.imu_ideal(t)):
        assert _same_bytes(a, b)
    assert _same_bytes(gt.stamps, direct_poses[0]) and _same_bytes(gt.poses, direct_poses[1])
    assert not gt.poses.flags.writeable
    # a scan renders from the cached trajectory as from the computed one
    i = len(seq) // 2
    seq_direct = stream.SimSequence(p, "map", 1)
    seq_direct.trajectory = direct_traj
    f, g = seq.frame(i), seq_direct.frame(i)
    assert _same_bytes(f.points, g.points) and _same_bytes(f.intensity, g.intensity)


def test_the_comparison_sees_a_changed_cache_entry(memo_on_disk):
    """The cache is trusted as written: a wrong entry reaches the sequence (so the test above
    would see one), and each session has its own entry."""
    import pickle

    from blockloc.sim import stream
    from blockloc.sim.presets import get_preset

    p = get_preset("tiny")
    stream.SimSequence(p, "map", 1).mapping_poses()
    stream.SimSequence(p, "loc", 1).mapping_poses()
    files = sorted(memo_on_disk.glob("mapping-poses-tiny-map-1-*.pkl"))
    assert len(files) == 1 and len(list(memo_on_disk.glob("mapping-poses-tiny-loc-1-*.pkl"))) == 1
    stamps, poses = pickle.loads(files[0].read_bytes())
    files[0].write_bytes(pickle.dumps((stamps, poses + 1e-9)))
    got = stream.SimSequence(p, "map", 1).mapping_poses().poses
    assert not _same_bytes(got, stream.SimSequence(p, "map", 1).compute_mapping_poses()[1])


def test_a_trajectory_builds_its_splines_on_first_use_with_the_same_poses(memo_on_disk):
    from blockloc.sim import stream
    from blockloc.sim.presets import get_preset
    from blockloc.sim.trajectory import SimTrajectory

    p = get_preset("tiny")
    built = stream.build_session_trajectory(p, 1, "map")
    t = np.linspace(0.0, built.duration, 50)
    T_built = built.T_world_flu(t)
    loaded = SimTrajectory.from_state(built.state(), built.world)
    # opened, not used: no spline held (a map-build worker opens every drive, renders some)
    assert "_planar_splines" not in vars(loaded) and "_tilt" not in vars(loaded)
    assert loaded.duration == built.duration
    assert _same_bytes(loaded.T_world_flu(t), T_built)
    assert "_planar_splines" in vars(loaded) and loaded._tilt is not None


def test_route_points_keep_no_trajectory_in_the_process(memo_on_disk):
    from blockloc.sim import stream
    from blockloc.sim.presets import get_preset

    p = get_preset("tiny")
    stream.route_points.cache_clear()
    pts = stream.route_points(p, 1)
    assert stream.session_trajectory.cache_info().currsize == 0
    assert any(f.name.startswith("routes-") for f in memo_on_disk.glob("*.pkl"))
    # read back (a new process) they are the points computed afresh
    stream.route_points.cache_clear()
    assert _same_bytes(stream.route_points(p, 1), pts)
    assert _same_bytes(stream._route_points(p, 1, 0.25), pts)
    stream.route_points.cache_clear()
