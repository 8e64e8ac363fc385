"""The localizer's worker threads (``GlobalLocalizer._map``)."""

import threading
import time
from types import SimpleNamespace

import pytest

from blockloc.global_init.relocalize import GlobalLocalizer


def test_a_failing_call_is_raised_only_after_every_other_call_ended():
    """A call still running after another failed would write to the localizer (its structure sets)
    while the next search runs: ``_map`` raises only when every call has ended."""
    fake = SimpleNamespace(params=SimpleNamespace(refine_workers=2, num_threads=2), _pool=None, place_source=None,
                           coverage_source=None)
    ended = threading.Event()

    def fn(i):
        if i == 0:
            raise ValueError("a sparse target")
        time.sleep(0.3)
        ended.set()
        return i

    try:
        with pytest.raises(ValueError, match="sparse target"):
            GlobalLocalizer._map(fake, fn, [0, 1])
        assert ended.is_set()
        assert GlobalLocalizer._map(fake, lambda i: i * i, [1, 2, 3]) == [1, 4, 9]  # in order
    finally:
        fake._pool.shutdown()


def test_the_workers_share_the_cores_rather_than_each_taking_them_all():
    """Two workers with two numba threads each on two cores wait on descheduled threads: each worker
    runs its kernels, alignments included (``NdtRegistration.num_threads`` asks for more), on
    ``num_threads // refine_workers`` threads; the caller's threads are left as they were."""
    import numba
    import numpy as np

    from blockloc.registration.ndt import NdtRegistration, NdtTarget

    rng = np.random.default_rng(0)
    scene = np.c_[rng.uniform(-10, 10, (4000, 2)), rng.normal(0, 0.05, 4000)]
    scene = np.vstack([scene, np.c_[rng.uniform(-10, 10, 2000), np.full(2000, 5.0), rng.uniform(0, 3, 2000)]])
    target = NdtTarget.build(scene, resolution=1.0)
    reg = NdtRegistration(num_threads=4)
    cores = numba.config.NUMBA_NUM_THREADS
    before = numba.get_num_threads()

    def threads_of_an_alignment(_):
        reg.align(target, scene[::3], np.eye(4))
        return numba.get_num_threads()

    for workers, num_threads in ((2, 2), (2, 4), (4, 2)):
        fake = SimpleNamespace(params=SimpleNamespace(refine_workers=workers, num_threads=num_threads), _pool=None,
                               place_source=None, coverage_source=None)
        try:
            got = GlobalLocalizer._map(fake, threads_of_an_alignment, range(2 * workers))
        finally:
            fake._pool.shutdown()
        assert set(got) == {min(max(1, num_threads // workers), cores)}, (workers, num_threads, got)
    assert numba.get_num_threads() == before
    # a thread with no cap takes what the registration asks for
    t = threading.Thread(target=lambda: got.append(threads_of_an_alignment(0)))
    t.start()
    t.join()
    assert got[-1] == min(4, cores)
