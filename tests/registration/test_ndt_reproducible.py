"""NDT gives the same bits whether its kernels were compiled afresh or loaded from numba's cache.

A map build's blocks must be the same bytes however it runs (in this process, a fresh process,
Dask workers). With ``fastmath`` reassociation and FMA contraction, LLVM's choices depended on
how a kernel was compiled (afresh, within its caller, or loaded from the cache), so the serial
and the Dask build of the same drives differed in ~1% of a block's float32 points by one unit
in the last place, depending on what the process had compiled before (an intermittent CI failure
of tests/maps/test_distributed.py). The kernels are now strict IEEE arithmetic.
"""

from __future__ import annotations

import os
import subprocess
import sys

PROBE = r"""
import numpy as np
from blockloc.geometry import transform_points, xyzrpy_to_T
from blockloc.registration.ndt import NdtRegistration, NdtTarget

rng = np.random.default_rng(0)
def plane(o, e1, e2, l1, l2, n):
    a, b = rng.uniform(0, l1, (n, 1)), rng.uniform(0, l2, (n, 1))
    return np.asarray(o) + a * np.asarray(e1) + b * np.asarray(e2)
X, Y, Z = np.eye(3)
scene = np.vstack([plane([-20, -15, 0], X, Y, 40, 30, 30000), plane([-20, -15, 0], X, Z, 40, 5, 6000),
                   plane([-20, 15, 0], X, Z, 40, 5, 6000), plane([-20, -15, 0], Y, Z, 30, 5, 5000),
                   plane([3, 2, 0], X, Z, 2, 2, 800), plane([3, 2, 0], Y, Z, 2, 2, 800)])
scene += rng.normal(0, 0.01, scene.shape)
target = NdtTarget.build(scene, resolution=1.0)
T_true = xyzrpy_to_T(0.4, -0.3, 0.05, 0.01, -0.02, 0.08)
out = []
for n in (1500, 9000):  # one pass serial, one over parallel chunks
    src = transform_points(np.linalg.inv(T_true), scene[rng.choice(len(scene), n, replace=False)])
    for threads in (1, 2):
        reg = NdtRegistration(num_threads=threads)
        out.append(reg.align(target, src, np.eye(4)).T_target_source.tobytes().hex())
        T_pred = T_true @ xyzrpy_to_T(0.02, 0, 0, 0, 0, 0.002)
        out.append(reg.align_from_prediction(target, src, T_pred).T_target_source.tobytes().hex())
print(" ".join(out))
"""


def test_ndt_bits_do_not_depend_on_the_kernels_cache(tmp_path):
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba")}  # empty: the first run compiles

    def run() -> list[str]:
        res = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, env=env,
                             timeout=600)
        assert res.returncode == 0, res.stderr[-2000:]
        return res.stdout.split()

    fresh = run()
    assert any((tmp_path / "numba").rglob("*.nbc")), "the first run did not fill the cache"
    cached = run()
    assert len(fresh) == 8
    assert fresh == cached
