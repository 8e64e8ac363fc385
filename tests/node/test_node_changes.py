"""``NodeChanges``, the node's frame hook for ``--detect-changes``: trusted by the run folder's
rule in the node's order, detected on a worker behind a bounded queue that drops (and counts)
scans for detection instead of making the node wait. The detector is a recorder here (the real
one against ``map changes``: tests/node/test_cli_node.py)."""

from __future__ import annotations

import threading
from types import SimpleNamespace

import numpy as np

from blockloc.app.runs import LiveChanges
from blockloc.maps.changes.runs import TrustedFrames, trusted_mask
from blockloc.node.changes import NodeChanges


class Recorder:
    """A detector that records what it is fed and, while ``gate`` is clear, waits (a slow one)."""

    def __init__(self) -> None:
        self.fed: list = []
        self.gate = threading.Event()
        self.gate.set()

    def add(self, stamp, T_map_body, trusted, frame=None):
        self.gate.wait(10)
        self.fed.append((round(stamp, 3), trusted, frame is not None))
        return 0


def hook(settle: int, stride: int = 1, **kw) -> tuple[NodeChanges, Recorder]:
    live = LiveChanges(stride=stride, settle_frames=settle)
    live.detector, live._trusted = Recorder(), TrustedFrames(settle)  # what begin(session) sets up
    changes = NodeChanges(live, **kw)
    if changes.threaded:
        changes._worker = threading.Thread(target=changes._work, daemon=True)
        changes._worker.start()
    return changes, live.detector


def emit(changes: NodeChanges, i: int, status: str) -> None:
    frame = SimpleNamespace(index=i, stamp=1.0 + 0.1 * i)
    est = SimpleNamespace(T_map_body=None if status == "uninitialized" else np.eye(4),
                          diagnostics=SimpleNamespace(status=status))
    changes(frame, est)


def test_the_node_hook_trusts_by_the_run_folders_rule_a_relocalization_included():
    statuses = ["uninitialized", "recovered"] + ["ok"] * 6 + ["rejected", "ok", "ok", "ok", "recovered"] + ["ok"] * 5
    for threaded in (True, False):
        changes, det = hook(2, threaded=threaded)
        for i, s in enumerate(statuses):
            emit(changes, i, s)
        changes.close()
        assert [t for _, t, _ in det.fed] == trusted_mask(statuses, 2).tolist()
        assert [has for _, _, has in det.fed] == [t for _, t, _ in det.fed]  # a scan only with a trusted frame
        assert changes.scans_dropped == 0 and changes.live.frames_tracked == len(statuses)
    # with a stride only the frames the detector uses carry their scan (every 3rd trusted one)
    changes, det = hook(2, stride=3)
    for i, s in enumerate(statuses):
        emit(changes, i, s)
    changes.close()
    trusted = [t for _, t, _ in det.fed]
    k = np.cumsum(trusted) - 1
    assert [has for _, _, has in det.fed] == [t and k[i] % 3 == 0 for i, t in enumerate(trusted)]


def test_a_slow_detector_drops_scans_for_detection_never_the_nodes_time():
    changes, det = hook(0, threaded=True, queue_scans=2)
    det.gate.clear()  # the detector is stuck on the first scan
    for i in range(8):
        emit(changes, i, "ok")  # returns at once: the node is not held
    assert changes.max_waiting <= 2 + 1  # two waiting, one being detected
    det.gate.set()
    changes.close()
    fed = det.fed
    assert [s for s, _, _ in fed] == [round(1.0 + 0.1 * i, 3) for i in range(8)]  # every pose, in order
    dropped = [i for i, (_, t, _) in enumerate(fed) if not t]
    assert changes.scans_dropped == len(dropped) >= 4 and dropped == list(range(8 - len(dropped), 8))
    cost = changes.cost()
    assert cost["scans_dropped"] == changes.scans_dropped and cost["queue_scans"] == 2
    assert cost["node_thread"].startswith("worker")


def test_with_a_stride_only_scans_to_use_wait_and_a_dropped_one_passes_its_turn_on():
    changes, det = hook(0, stride=2, threaded=True, queue_scans=1)
    det.gate.clear()
    for i in range(12):
        emit(changes, i, "ok")
    det.gate.set()
    changes.close()
    fed = det.fed
    assert len(fed) == 12 and all(has <= t for _, t, has in fed)
    # the detector's own count: every 2nd trusted frame it is fed carries its scan
    trusted = [t for _, t, _ in fed]
    k = np.cumsum(trusted) - 1
    assert [has for _, _, has in fed] == [t and k[i] % 2 == 0 for i, t in enumerate(trusted)]
    assert changes.scans_dropped == trusted.count(False) >= 1 and changes.max_waiting <= 2
