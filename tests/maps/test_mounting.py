"""The LiDAR mounting estimated from a mapping drive (blockloc.maps.mounting) and the map built with it."""

from __future__ import annotations

import numpy as np
import pytest

from blockloc.geometry import inv_T, make_T, so3_exp, so3_log
from blockloc.maps.build_plan import Drive, build_map_from_drives
from blockloc.datasets.base import RemountedSequence
from blockloc.maps.mounting import choose_pairs, solve_mounting, translation_determined

from .synthetic import MemorySequence, route, world_points

#: A LiDAR 1 m above the body origin, 0.3 m forward, turned 90 deg about z (NCLT-like).
X_NOMINAL = make_T(so3_exp(np.array([0.0, 0.0, np.pi / 2])), np.array([0.3, 0.0, 1.0]))


def _pose_exp(xi):
    import gtsam

    return gtsam.Pose3.Expmap(np.asarray(xi, float)).matrix()


def _planar_motions(rng, n, X_true, noise=(3e-4, 5e-3)):
    """(A, B): body motions of a ground robot (turns about z, small tilts) and the LiDAR motions
    a true mounting gives, with registration noise (rad, m)."""
    A, B = [], []
    for _ in range(n):
        yaw = rng.uniform(-np.pi, np.pi) if rng.random() < 0.5 else rng.normal(0.0, 0.05)
        a = make_T(so3_exp(np.r_[rng.normal(0.0, 0.01, 2), yaw]),
                   np.r_[rng.uniform(-15, 15, 2), rng.normal(0.0, 0.1)])
        b = inv_T(X_true) @ a @ X_true @ _pose_exp(np.r_[rng.normal(0, noise[0], 3), rng.normal(0, noise[1], 3)])
        A.append(a)
        B.append(b)
    return np.stack(A), np.stack(B)


def _body_frame_error(X, X_ref):
    """(rotation deg (3,), translation m (3,)) of X against X_ref, body frame."""
    return np.rad2deg(so3_log(X[:3, :3] @ X_ref[:3, :3].T)), X[:3, 3] - X_ref[:3, 3]


def test_solve_recovers_a_known_mounting_despite_outlier_pairs():
    rng = np.random.default_rng(3)
    X_true = X_NOMINAL @ _pose_exp(np.r_[np.deg2rad([0.2, -0.25, 0.3]), 0.01, -0.008, 0.0])
    A, B = _planar_motions(rng, 300, X_true)
    B[:20] = B[:20] @ _pose_exp([0.0, 0.0, 0.05, 1.0, 0.0, 0.0])  # 20 wrong registrations
    H = np.tile(np.diag([1e6] * 3 + [1e4] * 3), (300, 1, 1))
    sol = solve_mounting(A, B, H, X_NOMINAL)
    rot, trans = _body_frame_error(sol["T_body_lidar"], X_true)
    assert np.abs(rot).max() < 0.02
    assert np.abs(trans[:2]).max() < 0.002
    # the outliers are the pairs it trusts least
    assert sol["weights"][:20].max() < sol["weights"][20:].min()
    assert np.median(sol["cost_after"]) < 0.2 * np.median(sol["cost_before"])


def test_what_a_ground_robot_cannot_observe_stays_at_the_nominal_value():
    # rotations about z only never reveal the LiDAR's height: the prior keeps it, and says so
    rng = np.random.default_rng(4)
    X_true = X_NOMINAL @ _pose_exp([0.0, 0.0, 0.0, 0.0, 0.0, 0.03])  # 3 cm along the lidar z
    A, B = [], []
    for _ in range(200):
        a = make_T(so3_exp(np.r_[0.0, 0.0, rng.uniform(-np.pi, np.pi)]), np.r_[rng.uniform(-15, 15, 2), 0.0])
        A.append(a)
        B.append(inv_T(X_true) @ a @ X_true)
    sol = solve_mounting(np.stack(A), np.stack(B), np.tile(np.eye(6) * 1e4, (200, 1, 1)), X_NOMINAL)
    _, trans = _body_frame_error(sol["T_body_lidar"], X_NOMINAL)
    assert abs(trans[2]) < 0.005  # not moved toward the unobservable truth
    assert not sol["observed"][5] and sol["observed"][:5].all()


def test_the_nominal_mounting_is_kept_when_it_is_right():
    rng = np.random.default_rng(5)
    A, B = _planar_motions(rng, 200, X_NOMINAL)
    sol = solve_mounting(A, B, np.tile(np.diag([1e6] * 3 + [1e4] * 3), (200, 1, 1)), X_NOMINAL)
    rot, trans = _body_frame_error(sol["T_body_lidar"], X_NOMINAL)
    assert np.abs(rot).max() < 0.01 and np.abs(trans[:2]).max() < 0.002
    # the height is barely observed (tilts of 0.01 rad): it may move, within its own sigma
    assert abs(trans[2]) < 3 * sol["sigma"][5]


def test_the_translation_counts_as_determined_only_where_the_drive_reproduces_it():
    """Exact body poses: the block jackknife finds x and y to a fraction of a mm (z, which turns
    about z never show, is not judged). Body poses whose error is shared along runs of the drive
    (an offline SLAM's, 6 cm a run): the fit's own sigma still says ~3 mm, the jackknife says
    more than the 5 mm tolerance, and the estimate is indeed that far off."""
    rng = np.random.default_rng(6)
    X_true = X_NOMINAL @ _pose_exp(np.r_[np.deg2rad([0.2, -0.25, 0.3]), 0.02, -0.015, 0.0])
    A, B = _planar_motions(rng, 240, X_true)
    H = np.tile(np.diag([1e6] * 3 + [1e4] * 3), (240, 1, 1))
    determined, u = translation_determined(A, B, H, X_NOMINAL, solve_mounting(A, B, H, X_NOMINAL))
    assert determined.tolist() == [True, True, False] and np.isnan(u[2]) and u[:2].max() < 0.001
    for run in np.array_split(np.arange(240), 12):
        A[run, :2, 3] += rng.normal(0.0, 0.06, 2)
    sol = solve_mounting(A, B, H, X_NOMINAL)
    determined, u = translation_determined(A, B, H, X_NOMINAL, sol)
    _, err = _body_frame_error(sol["T_body_lidar"], X_true)
    assert not determined.any() and u[:2].min() > 0.005, u
    assert sol["sigma"][3:5].max() < 0.005 and np.abs(err[:2]).max() > 0.01, (sol["sigma"], err)
    # too few pairs for eight runs of three: nothing counts as determined
    determined, u = translation_determined(A[:20], B[:20], H[:20], X_NOMINAL, sol)
    assert not determined.any() and np.isinf(u[:2]).all()


def test_pairs_lie_within_the_baseline_band_and_prefer_turns():
    traj = route([[0, 0], [100, 0], [100, 100], [0, 100], [0, 0]], speed=1.0, rate=1.0)
    T = traj.poses
    pairs = choose_pairs(T, max_pairs=80, min_baseline_m=4.0, max_baseline_m=15.0)
    assert len(pairs) > 40
    d = np.linalg.norm(T[pairs[:, 0], :3, 3] - T[pairs[:, 1], :3, 3], axis=1)
    assert d.min() >= 4.0 and d.max() <= 15.0 + 1e-9
    assert (pairs[:, 0] < pairs[:, 1]).all() and len(np.unique(pairs, axis=0)) == len(pairs)
    heading = np.arctan2(T[:, 1, 0], T[:, 0, 0])
    turned = np.abs(np.angle(np.exp(1j * (heading[pairs[:, 0]] - heading[pairs[:, 1]])))) > np.deg2rad(30)
    # only keyframes near the four corners can pair across a turn: far fewer than half the anchors
    assert turned.sum() >= 8
    np.testing.assert_array_equal(pairs, choose_pairs(T, max_pairs=80))  # deterministic


@pytest.fixture(scope="module")
def mis_mounted_drive():
    """A square drive whose scans come from a LiDAR mounted 0.5 deg / 4 cm off the nominal
    mounting that the sequence reports."""
    world = world_points(extent=(-40, 170), seed=8, density=0.6)
    traj = route([[0, 0], [130, 0], [130, 130], [0, 130], [0, 0]], speed=4.0)
    X_true = X_NOMINAL @ _pose_exp(np.r_[np.deg2rad([0.3, -0.4, 0.5]), 0.04, -0.03, 0.0])
    rendered = MemorySequence(world, traj, radius=25.0, T_body_lidar=X_true, name="square")
    return world, RemountedSequence(rendered, X_NOMINAL), X_true


def test_a_build_with_calibrate_mounting_finds_the_true_mounting_and_a_sharper_map(tmp_path, mis_mounted_drive):
    from scipy.spatial import cKDTree

    world, seq, X_true = mis_mounted_drive
    nominal = build_map_from_drives([Drive.of(seq)], "block", tmp_path / "nominal", block_size_m=60.0)
    mounted = build_map_from_drives([Drive.of(seq)], "block", tmp_path / "mounted", block_size_m=60.0,
                                    calibrate_mounting=True)
    assert "mounting" not in nominal.params
    m = mounted.params["mounting"]["square"]
    X = np.asarray(m["T_body_lidar"])
    rot, trans = _body_frame_error(X, X_true)
    assert np.abs(rot).max() < 0.1, m
    assert np.abs(trans[:2]).max() < 0.01, m
    assert m["used"] >= 50 and m["cost_after"] < m["cost_before"]
    # the map: its points lie closer to the world they were scanned from
    tree = cKDTree(world)

    def spread(store):
        pts = store.load_points([e.id for e in store.entries])
        return float(np.percentile(tree.query(pts)[0], 90))

    assert spread(mounted) < 0.7 * spread(nominal)


def test_tracking_takes_the_map_mounting_only_when_asked_and_warns_otherwise(caplog, mis_mounted_drive):
    from types import SimpleNamespace

    from blockloc.maps.mounting import map_mounting
    from blockloc.maps.mounting import with_map_mounting as _with_map_mounting

    _, seq, X_true = mis_mounted_drive
    store = SimpleNamespace(params={"mounting": {"square": {"T_body_lidar": X_true.tolist()}}})
    used = _with_map_mounting(seq, store, use=True)
    np.testing.assert_allclose(used.info.T_body_lidar, X_true)
    assert len(used) == len(seq) and used.frame(3).stamp == seq.frame(3).stamp
    with caplog.at_level("WARNING"):
        kept = _with_map_mounting(seq, store, use=False)
    assert kept is seq and "use_map_mounting" in caplog.text and "0.71 deg" in caplog.text
    assert _with_map_mounting(seq, SimpleNamespace(params={}), use=True) is seq
    # two robots' drives in one map: no single mounting to take
    other = X_true @ make_T(so3_exp(np.deg2rad([0.0, 0.0, 0.5])), np.zeros(3))
    assert map_mounting({"mounting": {"a": {"T_body_lidar": X_true.tolist()},
                                      "b": {"T_body_lidar": other.tolist()}}}) is None


@pytest.mark.parametrize("offset", [False, True], ids=["lidar-poses", "body-poses-0.6deg-5cm-off"])
def test_on_the_real_walk_the_mounting_is_found_or_left_alone(shared_data, tmp_path, offset):
    """The real hand-held walk's poses are the LiDAR's own (T_body_lidar = I). Given as they are,
    the estimate stays at the identity; given as the poses of a body the LiDAR sits 0.4/0.5/0.6 deg
    and 3/4/2 cm off, it finds that mounting's rotation and x/y translation. A hand-held walk
    turns every way: all six axes are observed (a ground robot's height is not), yet the height
    does not reproduce along the walk to the 5 mm the translation is held to."""
    from blockloc.app.catalog import SequenceRef
    from blockloc.trajectory_io import read_tum, write_tum
    from blockloc.geometry import Trajectory

    walk = shared_data / "balm_hilti_walk"
    poses = walk / "poses_T_world_lidar.tum"
    X = make_T(so3_exp(np.deg2rad([0.4, -0.5, 0.6])), np.array([0.03, -0.04, 0.02])) if offset else np.eye(4)
    if offset:
        traj = read_tum(poses)
        poses = write_tum(tmp_path / "body.tum", Trajectory(traj.stamps, traj.poses @ inv_T(X)))
    seq = SequenceRef.parse(str(walk)).open(poses=str(poses))
    store = build_map_from_drives([Drive.of(seq)], "block", tmp_path / "map", block_size_m=8.0,
                                  voxel_size_m=0.1, calibrate_mounting=True)
    (m,) = store.params["mounting"].values()
    rot, trans = _body_frame_error(np.asarray(m["T_body_lidar"]), X)
    assert all(m["observed"]) and m["used"] >= 50, m
    assert np.abs(rot).max() < 0.05, m
    # x and y: determined and estimated; z (the walk's jackknife: 9 mm, above the 5 mm
    # tolerance) stays nominal where the estimate does not reproduce it
    assert m["translation_estimated"].startswith("xy") and np.abs(trans[:2]).max() < 0.005, m
    if "z" in m["translation_estimated"]:
        assert abs(trans[2]) < 0.015, m
    else:
        assert m["translation_uncertainty_m"][2] > m["translation_tolerance_m"], m
        assert abs(np.asarray(m["T_body_lidar"])[2, 3]) < 1e-9, m  # the nominal height (0)


def test_a_drive_too_short_to_calibrate_is_one_error_naming_it_and_leaves_nothing(tmp_path):
    from blockloc.errors import MapError

    world = world_points(extent=(-20, 40), seed=2, density=0.3)
    short = MemorySequence(world, route([[0, 0], [3, 0]], speed=1.0), radius=20.0, name="short")
    with pytest.raises(MapError, match=r"^short: .*--calibrate-mounting needs keyframes"):
        build_map_from_drives([Drive.of(short)], "block", tmp_path / "m", calibrate_mounting=True)
    assert list(tmp_path.iterdir()) == []  # no map, no half-built directory


def test_the_default_build_estimates_body_pose_drives_only_and_never_fails_on_the_estimate(tmp_path):
    """``calibrate_mounting="auto"`` (what `map build` does unless told otherwise): a drive whose
    poses are the LiDAR's (T_body_lidar = I) is left alone; a drive
    too short to estimate keeps its nominal mounting, with the reason in the manifest, where an
    explicit request (True) fails."""
    world = world_points(extent=(-20, 40), seed=2, density=0.3)
    lidar_poses = MemorySequence(world, route([[0, 0], [3, 0]], speed=1.0), radius=20.0, name="lidar")
    body_poses = MemorySequence(world, route([[0, 0], [3, 0]], speed=1.0), radius=20.0,
                                T_body_lidar=X_NOMINAL, name="body")
    store = build_map_from_drives([Drive.of(lidar_poses), Drive.of(body_poses)], "block", tmp_path / "m",
                                  calibrate_mounting="auto")
    assert "mounting" not in store.params
    src = store.params["mounting_source"]
    assert src["lidar"] == {"source": "lidar poses"}
    assert src["body"]["source"] == "nominal" and src["body"]["reason"].startswith("the estimate failed: ")
    # the same drives without the estimate: the same map
    plain = build_map_from_drives([Drive.of(lidar_poses), Drive.of(body_poses)], "block", tmp_path / "p")
    assert plain.params["mounting_source"] == {"lidar": {"source": "nominal", "reason": "not estimated"},
                                               "body": {"source": "nominal", "reason": "not estimated"}}
    assert [e.num_points for e in store.entries] == [e.num_points for e in plain.entries]
    with pytest.raises(Exception, match="calibrate_mounting 'yes'"):
        build_map_from_drives([Drive.of(body_poses)], "block", tmp_path / "x", calibrate_mounting="yes")


def test_the_default_build_finds_a_body_pose_drives_mounting(tmp_path, mis_mounted_drive):
    _, seq, X_true = mis_mounted_drive
    store = build_map_from_drives([Drive.of(seq)], "block", tmp_path / "m", block_size_m=60.0,
                                  calibrate_mounting="auto")
    assert store.params["mounting_source"] == {"square": {"source": "estimated"}}
    rot, trans = _body_frame_error(np.asarray(store.params["mounting"]["square"]["T_body_lidar"]), X_true)
    assert np.abs(rot).max() < 0.1 and np.abs(trans[:2]).max() < 0.01
