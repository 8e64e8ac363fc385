"""Property tests on random stamps and random SE(3) poses."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from blockloc.evaluation.metrics import absolute_pose_errors, associate, umeyama_alignment

SETTINGS = settings(max_examples=60, deadline=None, derandomize=True)


@SETTINGS
@given(seed=st.integers(0, 2**31 - 1), n_a=st.integers(0, 80), n_b=st.integers(0, 80),
       tol=st.floats(0.0, 0.5))
def test_association_is_one_to_one_within_tolerance(seed, n_a, n_b, tol):
    rng = np.random.default_rng(seed)
    a = np.sort(rng.uniform(0, 10, n_a))
    b = rng.uniform(0, 10, n_b)  # unsorted on purpose
    ia, ib = associate(a, b, tol)
    assert len(ia) == len(ib) <= min(n_a, n_b)
    assert len(set(ia.tolist())) == len(ia) and len(set(ib.tolist())) == len(ib)
    assert np.all(np.abs(a[ia] - b[ib]) <= tol)
    assert np.all(np.diff(ia) > 0)
    # no stamp is left out while its nearest partner is within tolerance and also unused
    free_b = np.setdiff1d(np.arange(n_b), ib)
    for i in np.setdiff1d(np.arange(n_a), ia):
        if len(free_b):
            d = np.abs(b - a[i])
            j = int(np.argmin(d))
            assert not (d[j] <= tol and j in set(free_b.tolist()))


@SETTINGS
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(3, 50))
def test_umeyama_recovers_any_rigid_transform(seed, n):
    rng = np.random.default_rng(seed)
    src = rng.normal(0, 5, (n, 3))
    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=seed).as_matrix()
    T[:3, 3] = rng.normal(0, 100, 3)
    dst = src @ T[:3, :3].T + T[:3, 3]
    np.testing.assert_allclose(umeyama_alignment(src, dst), T, atol=1e-8)


@SETTINGS
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 40))
def test_ate_full_combines_rotation_and_translation(seed, n):
    # ||E - I||_F^2 = ||R_E - I||_F^2 + ||t_E||^2 and ||R_E - I||_F = 2 sqrt(2) sin(angle / 2)
    rng = np.random.default_rng(seed)
    G = np.tile(np.eye(4), (n, 1, 1))
    G[:, :3, :3] = Rotation.random(n, random_state=seed).as_matrix()
    G[:, :3, 3] = rng.normal(0, 10, (n, 3))
    P = G.copy()
    P[:, :3, :3] = P[:, :3, :3] @ Rotation.random(n, random_state=seed + 1).as_matrix()
    P[:, :3, 3] += rng.normal(0, 1, (n, 3))
    ate = absolute_pose_errors(G, P)
    rot_fro = 2 * np.sqrt(2) * np.sin(np.radians(ate.rot_deg) / 2)
    np.testing.assert_allclose(ate.full, np.sqrt(rot_fro**2 + ate.trans_m**2), atol=1e-9)
    np.testing.assert_allclose(ate.trans_m, np.linalg.norm(P[:, :3, 3] - G[:, :3, 3], axis=1))
