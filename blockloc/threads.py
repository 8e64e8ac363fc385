"""Thread limits set before numpy loads.

One BLAS thread: blockloc's matrix products are small (3x3 rotations of a few 100k points), where
BLAS threads only fight the NDT kernel's numba threads for the cores. Cropping a 505k-point map
for global init took 0.27-0.67 s with OpenBLAS's default threads on 2 shared cores and 0.10-0.14 s
with one (docs/bench/real.md). A value the user set wins.

The simulator's ray casts (open3d) use every core unless told otherwise
(:data:`RAYCAST_THREADS_ENV`): a map build's Dask workers are single-threaded processes, one per
core, where those threads only contend with the other workers.
"""

import os


def limit_blas_threads() -> None:
    """Default OPENBLAS_NUM_THREADS and MKL_NUM_THREADS to 1 (call before numpy is imported)."""
    for var in ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")


#: Threads of each open3d ray cast and scene build of the simulator; unset or 0: open3d's own
#: choice (every core). The Dask workers blockloc starts get 1 (:mod:`blockloc.maps.distributed`).
RAYCAST_THREADS_ENV = "BLOCKLOC_RAYCAST_THREADS"


def raycast_threads() -> int:
    """Threads an open3d ray cast may use (``$BLOCKLOC_RAYCAST_THREADS``; 0: open3d's choice).

    A cast's hits do not depend on it. On a single-threaded build worker the extra threads cost
    ~9% of a city scan's CPU outside the task's thread (uncounted by its timer) and ~3% more CPU
    in all than one thread (campus-like city keyframes, measured)."""
    value = os.environ.get(RAYCAST_THREADS_ENV, "0")
    try:
        return max(0, int(value))
    except ValueError:
        import logging

        logging.getLogger(__name__).warning("%s=%r: expected a whole number of threads; using open3d's choice",
                                            RAYCAST_THREADS_ENV, value)
        return 0
