"""Thread limits set before numpy loads.

One BLAS thread: blockloc's matrix products are small (3x3 rotations of a few 100k points), where
BLAS threads only fight the NDT kernel's numba threads for the cores. Cropping a 505k-point map
for global init took 0.27-0.67 s with OpenBLAS's default threads on 2 shared cores and 0.10-0.14 s
with one (docs/bench/real.md). A value the user set wins.
"""

import os


def limit_blas_threads() -> None:
    """Default OPENBLAS_NUM_THREADS and MKL_NUM_THREADS to 1 (call before numpy is imported)."""
    for var in ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")
