"""A scan is the same whatever number of threads its ray casts use (a map build's workers cast
in one, a serial build in open3d's default)."""

import numpy as np


def test_a_scan_does_not_depend_on_the_ray_cast_threads(monkeypatch):
    from blockloc.sim.stream import SimSequence
    from blockloc.sim.presets import get_preset
    from blockloc.threads import RAYCAST_THREADS_ENV, raycast_threads

    p = get_preset("small", azimuth_steps=300)
    frames = {}
    for n in ("0", "1", "2"):
        monkeypatch.setenv(RAYCAST_THREADS_ENV, n)
        assert raycast_threads() == int(n)
        seq = SimSequence(p, "loc", 1)  # a scene of its own: built with these threads too
        frames[n] = [seq.frame(i) for i in (0, len(seq) // 2)]
    for n in ("1", "2"):
        for f, g in zip(frames["0"], frames[n]):
            assert np.array_equal(f.points, g.points) and np.array_equal(f.intensity, g.intensity)
    monkeypatch.setenv(RAYCAST_THREADS_ENV, "many")
    assert raycast_threads() == 0


def test_a_bad_thread_count_is_named_in_a_warning_and_open3d_chooses(monkeypatch, caplog):
    from blockloc.threads import RAYCAST_THREADS_ENV, raycast_threads

    monkeypatch.setenv(RAYCAST_THREADS_ENV, "two")
    with caplog.at_level("WARNING"):
        assert raycast_threads() == 0
    assert RAYCAST_THREADS_ENV in caplog.text and "'two'" in caplog.text
