"""blockloc: LiDAR-inertial localization in large prior maps, one block at a time."""

import os as _os

__version__ = "0.1.0"

# Numba's parallel kernels run on the OpenMP layer. Busy-waiting OpenMP threads make two
# threads 30x slower than one when the two cores are shared (measured, docs/bench/ndt.md), and
# naming the layer keeps numba from probing (and warning about) an old TBB. Both must be set
# before numba starts its thread pool, hence here; a user's own setting wins.
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
_os.environ.setdefault("NUMBA_THREADING_LAYER", "omp")
