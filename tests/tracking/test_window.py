import numpy as np
import pytest

from blockloc.tracking.window import SlidingWindow, keys_of


def _chain(n, seed=0):
    """Poses along x with noisy absolute and relative measurements (a 1-D-ish SLAM chain)."""
    import gtsam

    rng = np.random.default_rng(seed)
    truth = [gtsam.Pose3(gtsam.Rot3.Rz(0.1 * i), np.array([i * 1.0, 0.2 * i, 0.0])) for i in range(n)]
    prior_noise = gtsam.noiseModel.Diagonal.Sigmas(np.r_[np.full(3, 0.05), np.full(3, 0.3)])
    odo_noise = gtsam.noiseModel.Diagonal.Sigmas(np.r_[np.full(3, 0.01), np.full(3, 0.05)])
    factors, initial = [], []
    for i in range(n):
        meas = truth[i].retract(rng.normal(scale=[0.05] * 3 + [0.3] * 3))
        factors.append((i, gtsam.PriorFactorPose3(keys_of(i)[0], meas, prior_noise)))
        if i:
            rel = truth[i - 1].between(truth[i]).retract(rng.normal(scale=[0.01] * 3 + [0.05] * 3))
            factors.append((i, gtsam.BetweenFactorPose3(keys_of(i - 1)[0], keys_of(i)[0], rel, odo_noise)))
        initial.append(truth[i].retract(rng.normal(scale=0.05, size=6)))
    return factors, initial


def _add(win, i, factors, initial):
    import gtsam

    v = gtsam.Values()
    v.insert(keys_of(i)[0], initial[i])
    win.add_keyframe(i, float(i), v)
    for j, f in factors:
        if j == i:
            win.add_factor(f)


def test_marginalizing_into_a_prior_keeps_the_estimate_and_covariance():
    """Schur complement at the optimum: the kept poses' mean and covariance equal the full graph's."""
    n = 12
    factors, initial = _chain(n)
    full = SlidingWindow(max_size=100, max_iterations=50)
    for i in range(n):
        _add(full, i, factors, initial)
    full.optimize()

    win = SlidingWindow(max_size=100, max_iterations=50)
    for i in range(8):
        _add(win, i, factors, initial)
    win.optimize()
    dropped = win.marginalize_to(3)
    assert dropped == 5 and len(win) == 3 and win.keyframes == [5, 6, 7]
    assert not win.values.exists(keys_of(0)[0])
    for i in range(8, n):
        _add(win, i, factors, initial)
    win.optimize()
    assert len(win) == 7  # grows back
    last = keys_of(n - 1)[0]
    np.testing.assert_allclose(win.values.atPose3(last).matrix(), full.values.atPose3(last).matrix(),
                               atol=2e-3)
    np.testing.assert_allclose(win.covariance(last), full.covariance(last), rtol=0.05, atol=1e-5)


def test_marginalization_differs_from_dropping():
    """Dropping old factors (what a reset does) loses information; the prior keeps it."""
    factors, initial = _chain(10, seed=3)
    marg = SlidingWindow(max_size=100, max_iterations=50)
    for i in range(10):
        _add(marg, i, factors, initial)
    marg.optimize()
    marg.marginalize_to(2)
    marg.optimize()
    cov_marg = marg.covariance(keys_of(9)[0])

    fresh = SlidingWindow(max_size=100, max_iterations=50)
    for i in (8, 9):
        import gtsam

        v = gtsam.Values()
        v.insert(keys_of(i)[0], initial[i])
        fresh.add_keyframe(i, float(i), v)
    for j, f in factors:
        if j == 9 or (j == 8 and len(f.keys()) == 1):
            fresh.add_factor(f)
    fresh.optimize()
    cov_fresh = fresh.covariance(keys_of(9)[0])
    assert np.trace(cov_marg[3:, 3:]) < 0.8 * np.trace(cov_fresh[3:, 3:])


def test_enforce_size_shrinks_on_switch_only():
    factors, initial = _chain(30, seed=1)
    win = SlidingWindow(max_size=20)
    sizes = []
    for i in range(30):
        _add(win, i, factors, initial)
        win.optimize()
        win.enforce_size(switched=(i == 24), size_on_switch=5)
        sizes.append(len(win))
    assert sizes[:20] == list(range(1, 21))
    assert sizes[20:24] == [20] * 4
    assert sizes[24] == 5 and sizes[25:] == [6, 7, 8, 9, 10]


def test_bad_window_size():
    with pytest.raises(ValueError):
        SlidingWindow(max_size=0)


def test_one_iteration_near_the_optimum_more_after_a_large_step():
    """optimize stops after one LM iteration when no pose moved by one_step_m / one_step_rad (and
    lands where converged iterations land), and iterates on from a start far from the optimum."""
    import gtsam

    factors, initial = _chain(12, seed=2)
    win = SlidingWindow(max_size=100, max_iterations=50)
    for i in range(12):
        _add(win, i, factors, initial)
    start = gtsam.Values(win.values)
    win.optimize()  # from 5 cm / 3 deg off: more than one iteration
    assert win.stats.iterations > 1
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-12)
    params.setAbsoluteErrorTol(1e-12)
    params.setMaxIterations(50)
    converged = gtsam.LevenbergMarquardtOptimizer(win.graph(), start, params).optimize()
    # every pose 1 mm / 0.3 mrad from the optimum, as a tracked scan's window starts
    near = gtsam.Values()
    for i in range(12):
        k = keys_of(i)[0]
        near.insert(k, converged.atPose3(k).retract(np.r_[np.full(3, 0.0002), np.full(3, 0.0006)]))
    win.values = near
    win.optimize()
    assert win.stats.iterations == 1
    for i in range(12):
        k = keys_of(i)[0]
        np.testing.assert_allclose(win.values.atPose3(k).matrix(), converged.atPose3(k).matrix(), atol=1e-5)
    # the same start with the shortcut off: LM's own test, a second iteration
    off = SlidingWindow(max_size=100, max_iterations=50, one_step_m=0.0, one_step_rad=0.0)
    for i in range(12):
        _add(off, i, factors, initial)
    off.values = gtsam.Values(near)
    off.optimize()
    assert off.stats.iterations == 2
