"""The kidnapped robot, end to end: tracking on the `small` world, teleported 47 m mid-run.

The tracker must notice (its scans stop fitting the map around the predicted pose), report the
frames in between as not good, find itself again over the whole map with the place index (the
search around the last pose cannot: the robot is outside its window), and track on.
"""

import numpy as np
import pytest

from blockloc.maps.store import open_map
from blockloc.app.assemble import build_session

from .kidnap import SplicedSequence

# ~100 s on the shared 2-core machine (the tracking run and several 5-8 s relocalizations): over
# the 60 s budget of a test; marked slow.
pytestmark = pytest.mark.slow

FIRST = (140, 180)  # ends at (-24.4, 0.8) m on the small world's loop
# starts at (22.5, 1.8) m: 47 m away, beyond the 40 m local search window. 70 frames: on 2026-12-06
# it ended at 990, because on frames 993-1004 tracking from ground truth was itself 0.10-0.11 m off
# (the map then held the nominal mounting). On today's default map the same stretch tracked from
# ground truth stays within 0.023 m (2026-12-07, frames 950-1020), so the test holds every ok
# frame to 0.10 m over all of it again.
SECOND = (950, 1020)


@pytest.fixture(scope="module")
def kidnapped_run(small_world):
    from blockloc.app.catalog import open_sequence

    from dataclasses import replace

    paths, cfg = small_world
    # The place index alone (not the regions after it, tens of seconds for a scan it misses): the
    # recovery must come from the index.
    cfg = replace(cfg, global_init=replace(cfg.global_init, whole_map_fallback=False))
    seq = SplicedSequence(open_sequence(paths.loc, dataset_cfg=cfg.dataset), FIRST, SECOND)
    session = build_session(cfg, seq, open_map(paths.block_map), backend="block", keep_estimates=True)
    return session.run(init="gt"), seq


def test_the_splice_is_a_jump_of_more_than_the_local_search_window(kidnapped_run):
    _, seq = kidnapped_run
    gt = seq.ground_truth()
    before, after = gt.interpolate(np.array([seq.splice_stamp - 0.1, seq.splice_stamp]))[:, :3, 3]
    assert np.linalg.norm(after[:2] - before[:2]) > 40.0


def test_kidnapped_robot_is_detected_and_recovered_with_nothing_wrong_published(kidnapped_run):
    res, seq = kidnapped_run
    ests = res.estimates
    gt = seq.ground_truth()
    k0 = seq.splice_index
    status = [e.diagnostics.status for e in ests]
    err = np.array([np.linalg.norm(e.T_map_body[:3, 3] - gt.interpolate(np.array([e.stamp]))[0][:3, 3])
                    for e in ests])
    # Before the jump: tracking, accurate.
    assert all(s == "ok" for s in status[10:k0]) and err[10:k0].max() < 0.3
    # Divergence detected within 1 s of sensor time: the tracker declares itself lost (and, when
    # the relocalization it then runs succeeds at once, reports that frame as recovered).
    lost = next(k for k in range(k0, len(ests)) if status[k] in ("lost", "recovered"))
    assert ests[lost].stamp - seq.splice_stamp <= 1.0, status[k0:lost + 1]
    # Back within 3 s, by a relocalization counted in the metrics.
    back = next(k for k in range(k0, len(ests)) if status[k] == "recovered")
    assert ests[back].stamp - seq.splice_stamp <= 3.0, status[k0:back + 1]
    assert res.metrics["recoveries"] >= 1 and res.metrics["failures"] >= 1
    # Nothing between the jump and the recovery was published as good.
    assert all(s != "ok" for s in status[k0:back]), status[k0:back]
    # After the recovery: accurate again, from the recovered scan on, every scan within 0.10 m.
    # Measured 2026-12-06 (helper kidnap): the recovered pose 0.018 m off, then 0.017, 0.021,
    # 0.027 m ..., max 0.03 m over the 37 ok scans after it. Before: these scans overshot to
    # 0.25-0.35 m, reported ok (the first scan after the jump registered against the block the robot
    # came from, with the prediction and deskew of a robot at rest: now ``MapProvider.relocate``
    # waits for the new block and the tracker restarts with the last good body-frame velocity), and
    # the recovered pose itself was 0.13 m off (found on a scan deskewed with the diverged motion:
    # now deskewed again from the restarted state and registered, ``Estimator._refine_restart``).
    assert err[back] < 0.10
    good = [k for k in range(back, len(ests)) if status[k] == "ok"]
    assert len(good) > 0.9 * (len(ests) - back) and err[good].max() < 0.10, np.round(err[good], 3)
    assert np.median(err[good]) < 0.05
    # The whole-map search found it (the search around the last good pose could not).
    reloc = res.metrics["relocalizations"]
    assert any(r["verified"] and not r["hint"] for r in reloc)
    assert not any(r["verified"] and r["hint"] for r in reloc if r["stamp"] >= seq.splice_stamp)
