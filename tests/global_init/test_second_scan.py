"""An ambiguous scan settled by the scans after it, where a user meets it: the no-hint start of
``blockloc track`` and the tracker's relocalization (``blockloc.app.recovery``).

The world: a street of identical boxes every 12 m (one scan fits several places along it, some of
them verified) and one box that stands nowhere else; a robot drives along it at 4 m/s. The map is
built from the world's points (``map build --from-pcd``), the session's scans are simulated with
motion distortion and an exact IMU (``tests.tracking.synthetic``)."""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import dataclass, field

import numpy as np
import pytest
import yaml

from blockloc.geometry import Trajectory, inv_T
from blockloc.global_init.relocalize import pose_error

from tests.tracking.synthetic import T_BODY_LIDAR, imu_from_trajectory, make_scan
from .synthetic import box_outline

T0 = 1.0
FRAMES = 12


@dataclass
class Straight:
    """T_map_body(t): along x at ``speed`` m/s from ``x0``, 1.8 m above the ground (z up)."""

    x0: float = 3.0
    speed: float = 4.0
    gravity_map: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, -9.81]))

    def pose(self, t) -> np.ndarray:
        t = np.atleast_1d(np.asarray(t, float))
        T = np.tile(np.eye(4), (len(t), 1, 1))
        T[:, 0, 3] = self.x0 + self.speed * t
        T[:, 2, 3] = 1.8
        return T


def street(rng, period: float = 12.0, length: float = 120.0) -> np.ndarray:
    """(N, 3) z up: flat ground 40 m wide, a box each side every ``period`` m along x, and one box
    (at x 34 m) that stands nowhere else."""
    g = np.arange(-length / 2, length / 2, 0.3)
    gx, gy = np.meshgrid(g, np.arange(-20.0, 20.0, 0.3))
    parts = [np.c_[gx.ravel(), gy.ravel(), rng.normal(0, 0.02, gx.size)]]
    for x in np.arange(-length / 2, length / 2, period):
        parts.append(box_outline(rng, x, 8.0, 3.0, 2.0, 3.0, 0.3, 0.0, per_m=150))
        parts.append(box_outline(rng, x + 4.0, -9.0, 2.0, 4.0, 3.0, -0.2, 0.0, per_m=150))
    parts.append(box_outline(rng, 34.0, 13.0, 6.0, 4.0, 3.0, 0.0, 0.0, per_m=150))
    return np.concatenate(parts)


@pytest.fixture(scope="module")
def street_run(tmp_path_factory):
    """{session, map, config}: the street's session (NCLT layout) and its block map."""
    from blockloc.datasets.nclt import write_session
    from blockloc.datasets.pointclouds import write_point_cloud
    from blockloc.maps.from_pcd import build_map_from_global_pcd
    from blockloc.trajectory_io import write_tum

    root = tmp_path_factory.mktemp("street")
    scene = street(np.random.default_rng(3))
    traj = Straight()
    stamps = T0 + np.arange(FRAMES) / 10.0
    frames = (make_scan(scene, traj, float(s), T_BODY_LIDAR, index=i, max_points=20000, max_range=25.0)
              for i, s in enumerate(stamps))
    t_gt = np.arange(T0 - 1.0, float(stamps[-1]) + 0.5, 0.01)
    session = write_session(root / "session", date="2020-01-01", frames=frames,
                            imu=imu_from_trajectory(traj, T0 - 1.0, float(stamps[-1]) + 0.5),
                            ground_truth=Trajectory(t_gt, traj.pose(t_gt)), T_body_lidar=T_BODY_LIDAR,
                            T_body_imu=np.eye(4), gravity_map=traj.gravity_map)
    write_point_cloud(root / "world.pcd", scene.astype(np.float32))
    t_map = np.arange(0.0, 27.5, 0.5)
    write_tum(root / "mapping.tum", Trajectory(t_map, Straight(x0=-55.0).pose(t_map)))
    build_map_from_global_pcd(root / "world.pcd", root / "mapping.tum", "block", root / "map", sensor_range_m=30.0,
                              block_size_m=60.0)
    config = root / "config.yaml"
    config.write_text(yaml.safe_dump({"lidar": {"rate_hz": 10.0, "max_points": 6000}, "map": {"prefetch": False},
                                      "evaluation": {"plots": False}}))
    return {"session": session, "map": root / "map", "config": config, "root": root}


def _prepared(seq, i):
    from blockloc.global_init.scan_prep import prepare_for_init

    return prepare_for_init(seq.frame(i), seq.imu(), seq.info)


def test_the_motion_between_two_scans_is_registered_and_a_scan_of_elsewhere_is_refused(street_run):
    from blockloc.datasets.nclt import NcltSequence
    from blockloc.global_init.second_scan import TARGET_VOXEL_M, motion_points, scan_motion
    from blockloc.registration.engines import make_engine

    seq = NcltSequence(street_run["session"])
    gt = seq.ground_truth()
    engine = make_engine("ndt", resolution_m=1.0, num_threads=1)
    a, b = _prepared(seq, 0), _prepared(seq, 5)  # 2 m apart
    first = motion_points(a.points_body, TARGET_VOXEL_M, 60.0, 30000)
    T, fit = scan_motion(engine, first, motion_points(b.points_body, 0.5))
    T_true = inv_T(gt.interpolate(a.stamp)[0]) @ gt.interpolate(b.stamp)[0]
    assert T is not None and fit >= 0.8
    assert pose_error(T, T_true)[0] < 0.05, (T[:3, 3], T_true[:3, 3])
    # a scan turned half round and lifted 30 m fits the first from no start: no motion
    flipped = motion_points(b.points_body, 0.5) @ np.diag([-1.0, -1.0, 1.0]) + [0.0, 0.0, 30.0]
    assert scan_motion(engine, first, flipped)[0] is None


def test_the_relocalization_keeps_an_ambiguity_and_settles_it_with_a_later_scan(street_run):
    """Session.relocalize (the tracker's recovery, whole map): the first scan is ambiguous, nothing
    is returned and its hypotheses wait; the scan of the tracker's next attempt (5 frames, 2 m on) is
    registered to it and settles them."""
    from blockloc.app.runs import open_session
    from blockloc.config import load_config

    session = open_session(str(street_run["session"]), cfg=load_config(str(street_run["config"])),
                           map_path=str(street_run["map"]))
    try:
        seq, gt = session.seq, session.ground_truth
        pts = {i: np.asarray(seq.frame(i).points, float) for i in (0, 5)}
        g = _prepared(seq, 0).gravity_body
        assert session.relocalize(pts[0], None, g, float(seq.frame(0).stamp)) is None
        assert session.reloc_log[-1]["ambiguous"] and session.recovery.ambiguity is not None
        T = session.relocalize(pts[5], None, g, float(seq.frame(5).stamp))
        assert T is not None
        assert "second_scan" in session.reloc_log[-1] and session.reloc_log[-1]["verified"]
        assert pose_error(T, gt.interpolate(np.array([float(seq.frame(5).stamp)]))[0])[0] < 0.3
        assert session.recovery.ambiguity is None
    finally:
        session.close()


def test_track_without_a_pose_starts_from_the_scans_after_an_ambiguous_one(street_run, tmp_path):
    """``blockloc track`` with no init option: the first scan fits several places along the
    street (not verified: no pose is reported for it), the next scans are registered to it and
    test its hypotheses; the pose they verify starts tracking, and every pose reported is right."""
    out = tmp_path / "run"
    r = subprocess.run([sys.executable, "-m", "blockloc.cli", "track", "--seq", str(street_run["session"]),
                        "--map", str(street_run["map"]), "--config", str(street_run["config"]),
                        "--out", str(out), "--no-record"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr[-2000:]
    m = json.loads((out / "metrics.json").read_text())
    init = m["init"]
    assert init["mode"] == "global" and init["verified"] and init["ambiguous_frames"] >= 1
    ss = init["second_scan"]
    assert ss["verified"] and ss["frame"] == init["first_frame"] > ss["from_frame"] >= 0
    assert ss["motion_fitness"] >= 0.5 and ss["hypotheses"] >= 2
    assert init["error_m"] < 0.15
    # no pose before the verified one; every pose after it on the street where the robot is
    assert m["estimated"] == FRAMES - init["first_frame"]
    assert not m["aligned"] and m["ate_trans_max_m"] < 0.3


def _street_localizer(street_run, tmp_path):
    from blockloc.datasets.nclt import NcltSequence
    from blockloc.global_init.relocalize import GlobalLocalizer, InitParams
    from blockloc.maps.store import open_map

    seq = NcltSequence(street_run["session"])
    return seq, GlobalLocalizer.for_store(open_map(street_run["map"]), seq.info.gravity_map, InitParams(),
                                          cache_dir=tmp_path)


def _shifted(T: np.ndarray, dx: float) -> np.ndarray:
    out = np.array(T, float)
    out[0, 3] += dx
    return out


def test_a_hypothesis_that_slides_along_the_street_is_not_confirmed(street_run, tmp_path):
    """A hypothesis is a pose: a scan that fits only after NDT moved the hypothesis more than
    ``ambiguity_distance_m`` does not confirm it (campus frame 39798: hypotheses sliding along a
    street ended in a pose 6.9 m off, verified). Started 0.9 m from the truth, NDT reaches the truth;
    the other hypothesis (two boxes on, where the unique box is not) fails. Without the rule that
    verified the slid one; with it the result stays ambiguous. Started 0.1 m off, it is confirmed."""
    from blockloc.global_init.second_scan import resolve_with_second_scan

    seq, loc = _street_localizer(street_run, tmp_path)
    scan = _prepared(seq, FRAMES - 1)
    T_true = seq.ground_truth().interpolate(scan.stamp)[0]
    close = resolve_with_second_scan(loc, [_shifted(T_true, 0.1), _shifted(T_true, 24.0)], np.eye(4),
                                     scan.points_body, scan.gravity_body)
    assert close.verified and close.stats["slid"] == 0
    assert pose_error(close.T_map_body, T_true)[0] < 0.1
    slid = resolve_with_second_scan(loc, [_shifted(T_true, 0.9), _shifted(T_true, 24.0)], np.eye(4),
                                    scan.points_body, scan.gravity_body)
    assert pose_error(slid.T_map_body, T_true)[0] < 0.1  # NDT did reach the truth from 0.9 m ...
    assert slid.stats["slid"] >= 1
    assert not slid.verified and slid.ambiguous  # ... but the hypothesis 0.9 m off is not confirmed


def test_a_hypothesis_confirmed_on_its_fit_alone_needs_a_strong_fit(street_run, tmp_path, monkeypatch):
    """Where the static-band coverage was not judged (an open stretch), a later scan confirms a
    hypothesis only when it fits strongly, as a search's first stage lets such a best stand
    (``search_on_unjudged``). Defaults' map ``--rng 7``, frame 39963 (8 m place windows): two
    hypotheses 11-12 m from the truth, none at it; three scans on, one fitting 0.77 lost its rival
    and was confirmed, 11.75 m off. Here the street's true hypothesis, its coverage made unjudged:
    confirmed when its fit clears the strong-fit floors, not when the floors are above it, and
    confirmed either way without the rule."""
    from blockloc.global_init import second_scan

    seq, loc = _street_localizer(street_run, tmp_path)
    scan = _prepared(seq, FRAMES - 1)
    T_true = seq.ground_truth().interpolate(scan.stamp)[0]
    hyps = [_shifted(T_true, 0.1), _shifted(T_true, 24.0)]
    from blockloc.global_init import verify

    monkeypatch.setattr(verify, "consistency_judged", lambda c: False)
    p = loc.params
    first = second_scan.resolve_with_second_scan(loc, hyps, np.eye(4), scan.points_body, scan.gravity_body)
    best = first.candidates[0]
    strong = (best.fitness - 0.01, best.structure_fitness - 0.01)
    for rule, (min_fit, min_struct), confirmed in ((True, strong, True), (True, (best.fitness + 0.01, 0.0), False),
                                                   (False, (best.fitness + 0.01, 0.0), True)):
        p.search_on_unjudged, p.unjudged_min_fitness, p.unjudged_min_structure_fitness = rule, min_fit, min_struct
        res = second_scan.resolve_with_second_scan(loc, hyps, np.eye(4), scan.points_body, scan.gravity_body)
        assert pose_error(res.T_map_body, T_true)[0] < 0.1
        assert res.verified is confirmed and res.ambiguous is not confirmed, (rule, min_fit, res.stats)
        assert res.stats.get("unjudged", False) is not confirmed


def test_a_followed_ambiguity_carries_its_hypotheses_where_the_motion_put_them(street_run, tmp_path):
    """After a follow-up scan the hypotheses are where the motions put them (the refinement's
    starts), not where refinement ended: creeping along a street adds up against the first scan."""
    from blockloc.global_init.second_scan import Ambiguity
    from blockloc.global_init.verify import InitCandidate, InitResult

    seq, loc = _street_localizer(street_run, tmp_path)
    scan = _prepared(seq, 0)
    starts = [_shifted(np.eye(4), 0.0), _shifted(np.eye(4), 12.0)]
    ends = [_shifted(T, 0.3) for T in starts]
    res = InitResult(ends[0], 1.0, 0.9, [InitCandidate(e, 1.0, 0.9, True, True, s, structure_fitness=0.9)
                                         for e, s in zip(ends, starts)], True, 0.1, False)
    first = Ambiguity.of(res, loc.params, scan.points_body, scan.stamp)
    later = Ambiguity.of(res, loc.params, scan.points_body, scan.stamp, scans=2)
    assert [h[0, 3] for h in first.hypotheses] == [0.3, 12.3]  # a search's result: where NDT ended
    assert [h[0, 3] for h in later.hypotheses] == [0.0, 12.0]  # a follow-up's: where the motion put them
