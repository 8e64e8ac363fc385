"""Lifelong maps (issue 43): change detection against the simulator's truth, tracking months
later on a stale, an updated and a fresh map, and what an update costs. Writes docs/bench/lifelong.md.

    python -m bench.lifelong                                   # tiny preset, seed 1, every part
    python -m bench.lifelong --preset small --frames 400       # the first 400 frames of each session
    python -m bench.lifelong --parts detect --sessions loc_m12 # detection only

Everything runs as a user types it (the maps and runs are kept in --work and reused when there):

- ``blockloc map build --seq sim:P/map@S --kind block`` (the stale map, month 0);
- ``blockloc track --seq sim:P/SESSION@S --map MAP --init gt --no-record [--max-frames N]`` for
  each session (``loc_m3``, ``loc_m12``) on the stale map;
- **detect**: the detection of ``blockloc map changes`` (through the API, to score its voxels)
  on each session's run, scored against the truth (below);
- **unchanged**: block precision where nothing changed: ``blockloc map changes --map MAP --run
  RUN_loc --stride STRIDE`` (the app's recipe, :func:`unchanged_day`) on the stale-map run of
  month 0's ``loc`` drive (another drive of the mapping day: no structure changed, so every
  confirmed block and every removed or added voxel is false), beside the simulator's change list
  per block of the map for ``--sessions`` (:func:`changes_per_block`): which blocks any drive can
  find unchanged;
- **loc**: ``blockloc map update MAP --run RUN_loc_m3 --out MAP_upd`` (updated from another day;
  ``--update-from map_m12``: from the stale-map run of the 12-month mapping drive instead;
  ``--update-from loc_m3+map_m12``: from both runs in one update; repeat ``--update-from`` for
  several updated maps in one bench),
  ``blockloc map build --seq sim:P/map_m12@S --kind block`` (fresh), the same with ``--poses`` of
  the stale map's mapping error (:func:`same_error_poses`), then ``loc_m12`` tracked on the stale,
  the updated and both fresh maps, and ``loc`` (month 0, nothing changed) on the stale map: ATE,
  failures, rejected scans, the worst tenth of the route against the stale map; each map drive's
  mapping-pose error where ``loc_m12`` drives; per tenth of ``loc_m12``, each updated map against
  the fresh map with the stale map's mapping error, beside what the update did to the blocks
  driven there and the true changes in reach (:func:`where_worse`). Maps and runs kept in ``--work`` carry their
  maker's key (:func:`cache_keys`): a map of an older builder is never reused;
- **cost**: the update's time per changed block (wall and CPU of the command), the unchanged
  blocks' files hashed against the stale map's, the updated map's size against the fresh one's.
- **track**: ``blockloc track --seq sim:P/loc_m12@S --map MAP --init gt --no-record --max-frames N
  --detect-changes --changes-stride STRIDE`` (``--detect-frames N``, default 200): the detection's
  wall and CPU time (its ``changes.json`` ``cost``: the detector is fed each frame as the tracking
  loop emits it) per frame tracked and per scan used, p50 / p99 / max, and the classification at
  the end, beside the tracking's own per-scan update time (median / p99) and the command's CPU;
- ``--dynamic``: the dynamic-points comparison with DUFOMap (``bench._dynamic``, another
  module; called with this bench's work directory when present).

Truth (voxels of ``voxel_m``, the detector's, in the map frame):

- **removed**: map voxels with a map point inside the box of a removed change (grown 0.25 m) and
  every map point in them more than 0.3 m above the terrain (a voxel that still holds ground is
  not removed), which the run's rays crossed in ``min_scans`` scans or more (from the true poses,
  no margin: what the run could see);
- **added**: voxels holding points the simulator labels ``changed`` (true poses) in
  ``min_scans`` scans or more.

A detected voxel counts as right when a truth voxel of its class is within one voxel (26
neighbours), a truth voxel as found when a detected one is: a tolerance of one voxel for the
pose and the voxel grid. Per block: a block changed when its truth voxels (removed: in its
voxels, every block that holds them, since blocks overlap; added: by the nearest keyframe; as
``changes.json`` assigns them, :func:`block_truth`) form one 26-connected
cluster of ``min_block_voxels`` (8: 1 m^3 at 0.5 m) or more, i.e. an object the run observed
changed, not scattered voxels; detected when ``changes.json`` marks it confirmed. Vegetation is
static in the truth: crowns whose density differs between days (``foliage_change``) are not a
change. Both the truth scans and the detection's are deskewed (true poses, run poses).
``false_*_where`` sorts the false detections by place (:func:`where_voxels`).

Beside the truth (``emptied``, not instead of it): the same scores against the removed truth less
the voxels today's static or changed returns (true poses) still fill in half of the scans that see
them or more (:func:`still_filled`). A removed object's box, grown 0.25 m, takes in what it stood
against (a fence behind a parked car's end) and what stands in its place today (the end of the car
parked where it stood); rays cannot find those voxels emptied.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "docs" / "bench" / "lifelong.md"
PARTS = ("detect", "unchanged", "loc", "cost", "track")


def _child_cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def _run(cmd: list[str]) -> tuple[float, float]:
    """Run a command; (wall s, CPU s of it)."""
    t0, c0 = time.perf_counter(), _child_cpu()
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    return time.perf_counter() - t0, _child_cpu() - c0


def _once(cmd: list[str], done: Path, log: list) -> None:
    """Run ``cmd`` unless ``done`` exists; log (command, reused, wall, cpu)."""
    if done.exists():
        log.append((cmd, True, None, None))
    else:
        log.append((cmd, False, *_run(cmd)))


class _Recording:
    """A changed session whose frames, as detection reads them, are scored too: each frame is cast
    once, with its labels; its ``changed`` points' voxels and the voxels its rays cross (true pose,
    no margin) are kept."""

    def __init__(self, seq, voxel_m: float):
        self.seq, self.info, self.voxel_m = seq, seq.info, voxel_m
        gt = seq.ground_truth()
        self._gt_stamps, self._gt_poses = np.asarray(gt.stamps), np.asarray(gt.poses)
        self.changed, self.seen, self.occupied = [], [], []
        self.seconds = 0.0

    def __len__(self):
        return len(self.seq)

    def frame(self, i):
        from blockloc.maps.changes.detect import ray_free_keys, voxel_keys
        from blockloc.voxels import voxel_select

        from blockloc.geometry import Trajectory
        from blockloc.maps.mapping import scan_to_map

        t0 = time.process_time()  # casting the frame and scoring it: not the detection's cost
        frame, labels = self.seq.frame_labels(i)
        # the truth places the points with the true poses and the robot's true mounting (the
        # sequence's info carries the nominal one, 0.3-0.6 deg off on the small world)
        Tbl = np.asarray(getattr(self.seq, "T_body_lidar_true", self.info.T_body_lidar), float)
        a = max(int(np.searchsorted(self._gt_stamps, frame.stamp - 0.2)) - 1, 0)
        b = int(np.searchsorted(self._gt_stamps, frame.stamp + 0.4)) + 1  # the sweep's span
        gt = Trajectory(self._gt_stamps[a:b], self._gt_poses[a:b])
        T = gt.interpolate(np.array([frame.stamp]))[0] @ Tbl
        p = np.asarray(frame.points, float)[:, :3]
        ok = np.isfinite(p).all(1) & (np.linalg.norm(p, axis=1) <= 40.0)
        dt = None if frame.time_offsets is None else np.asarray(frame.time_offsets, float)[ok]
        pm = scan_to_map(p[ok], dt, float(frame.stamp), gt, Tbl)  # the true poses, deskewed
        lab = np.asarray(labels)[ok]
        self.changed.append(np.unique(voxel_keys(pm[lab == 1], self.voxel_m)))
        self.occupied.append(np.unique(voxel_keys(pm[lab != 2], self.voxel_m)))  # static or changed returns
        sel = voxel_select(pm, self.voxel_m / 2)
        self.seen.append(ray_free_keys(T[:3, 3], pm[sel], self.voxel_m, 0.0))
        self.seconds += time.process_time() - t0
        return frame


def _count(per_scan: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    if not per_scan:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    return np.unique(np.concatenate(per_scan), return_counts=True)


def _prf(det: np.ndarray, truth: np.ndarray) -> dict:
    """Precision / recall / F1 with a one-voxel tolerance (module docstring)."""
    from blockloc.maps.changes.detect import near_sorted

    det, truth = np.unique(det), np.unique(truth)
    tp_d = int(near_sorted(det, truth).sum()) if len(det) else 0
    tp_t = int(near_sorted(truth, det).sum()) if len(truth) else 0
    p = tp_d / len(det) if len(det) else float("nan")
    r = tp_t / len(truth) if len(truth) else float("nan")
    f = 2 * p * r / (p + r) if len(det) and len(truth) and p + r > 0 else float("nan")
    return {"detected": len(det), "truth": len(truth), "precision": p, "recall": r, "f1": f}


def _truth_removed(seq, block_points: dict, voxel_m: float) -> np.ndarray:
    """Removed truth voxels among the examined blocks' (module docstring), before observability.
    block_points: block id -> (N, 3) map points."""
    from blockloc.maps.changes.detect import voxel_keys

    boxes = [c.box_map() for c in seq.changes() if c.action == "removed"]
    H = seq.world.terrain.height
    out = []
    for pts in block_points.values():
        inside = np.zeros(len(pts), bool)
        for x0, x1, y0, y1, z0, z1 in boxes:
            pad = 0.25
            inside |= ((pts[:, 0] > x0 - pad) & (pts[:, 0] < x1 + pad) & (pts[:, 1] > y0 - pad)
                       & (pts[:, 1] < y1 + pad) & (pts[:, 2] > z0 - pad) & (pts[:, 2] < z1 + pad))
        k = voxel_keys(pts, voxel_m)
        above = -pts[:, 2] - H(pts[:, 0], -pts[:, 1])  # map frame = world (x, -y, -z)
        low = np.unique(k[above <= 0.3])
        cand = np.unique(k[inside])
        out.append(cand[~np.isin(cand, low)])
    return np.unique(np.concatenate(out)) if out else np.zeros(0, np.int64)


def where_voxels(seq, keys: np.ndarray, voxel_m: float) -> dict:
    """Where voxels (map frame keys) lie in the simulated world: inside a vegetation volume (a
    crown, bush or hedge ellipsoid grown by half a voxel), else within 0.5 m of the terrain
    (ground), else elsewhere (walls, poles, cars...). Counts of each."""
    from blockloc.maps.changes.detect import unpack_keys

    c = (unpack_keys(keys) + 0.5) * voxel_m
    w = np.c_[c[:, 0], -c[:, 1], -c[:, 2]]  # the world frame (x, -y, -z of the map's)
    veg = np.zeros(len(w), bool)
    vol = seq.world.volumes
    if vol is not None and len(vol) and len(w):
        from scipy.spatial import cKDTree

        reach = float(vol.radii.max()) + voxel_m
        tree = cKDTree(w)
        for i in range(len(vol)):
            j = np.asarray(tree.query_ball_point(vol.center[i], reach), dtype=np.int64)
            if len(j):
                d = (((w[j] - vol.center[i]) / (vol.radii[i] + voxel_m / 2)) ** 2).sum(1)
                veg[j[d <= 1.0]] = True
    above = w[:, 2] - seq.world.terrain.height(w[:, 0], w[:, 1]) if len(w) else np.zeros(0)
    ground = ~veg & (above <= 0.5)
    return {"vegetation": int(veg.sum()), "ground": int(ground.sum()), "other": int((~veg & ~ground).sum())}


def block_truth(truth_rm: np.ndarray, truth_ad: np.ndarray, res, voxel_m: float) -> dict:
    """Block id -> sorted truth voxels it owns, as ``changes.json`` assigns detected ones: a
    removed voxel to **every** block whose voxels hold it (the blocks overlap: each keeps the scans
    of its keyframes out to the sensor's range, so a removed hedge sits in the files of every
    block that saw it, and each of them must be rebuilt), an added voxel to the block of the
    nearest keyframe."""
    from scipy.spatial import cKDTree

    from blockloc.maps.changes.detect import unpack_keys

    ids = list(res.block_keyframes)
    kf = np.concatenate([np.asarray(res.block_keyframes[b]).reshape(-1, 3) for b in ids])
    owner = np.concatenate([[b] * len(np.asarray(res.block_keyframes[b]).reshape(-1, 3)) for b in ids])
    ad_owner = (owner[cKDTree(kf).query((unpack_keys(truth_ad) + 0.5) * voxel_m)[1]] if len(truth_ad)
                else np.zeros(0, dtype=object))
    return {b: np.unique(np.concatenate([truth_rm[np.isin(truth_rm, res.block_keys[b])], truth_ad[ad_owner == b]]))
            for b in res.block_keys}


def score_detection(P: str, S: int, session: str, mp: Path, run_dir: Path, stride: int, min_scans: int = 5) -> dict:
    """Detection on ``run_dir`` against ``session``'s truth (module docstring)."""
    from blockloc.maps.changes.detect import Thresholds, near_sorted
    from blockloc.maps.changes.pipeline import detect_changes
    from blockloc.maps.changes.runs import read_run
    from blockloc.maps.mounting import with_map_mounting
    from blockloc.maps.store import open_map
    from blockloc.sim.changes import open_session

    th = Thresholds()
    seq = open_session(P, session, S)
    rec = _Recording(seq, 0.5)
    run = read_run(run_dir)
    t0, c0 = time.perf_counter(), time.process_time()
    store = open_map(mp)
    # the scans placed with the mounting the run tracked with, as `map changes` places them
    res = detect_changes(store, with_map_mounting(rec, store, True), run, stride=stride, thresholds=th)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0 - rec.seconds
    vm = res.voxels.voxel_m
    seen_k, seen_n = _count(rec.seen)
    observed = seen_k[seen_n >= min_scans]
    rm_all = _truth_removed(seq, {b: store.load(b)[0][:, :3].astype(float) for b in res.block_keys}, vm)
    truth_rm = rm_all[np.isin(rm_all, observed)]
    ch_k, ch_n = _count(rec.changed)
    truth_ad = ch_k[ch_n >= min_scans]
    out = {"session": session, "frames_trusted": res.frames_trusted, "scans_used": res.scans_used,
           "scans_rejected": res.scans_rejected, "wall_s": wall, "cpu_s": cpu,
           "cpu_per_scan_s": cpu / max(res.scans_used, 1), "load1": os.getloadavg()[0],
           "removed": _prf(res.voxels.removed, truth_rm), "added": _prf(res.voxels.added, truth_ad),
           "removed_truth_unobserved": int(len(rm_all) - len(truth_rm)),
           "false_removed_where": where_voxels(seq, res.voxels.removed[~near_sorted(res.voxels.removed, truth_rm)], vm),
           "false_added_where": where_voxels(seq, res.voxels.added[~near_sorted(res.voxels.added, truth_ad)], vm)}
    out.update(_block_scores(res, truth_rm, truth_ad, vm, th))
    # the removed truth voxels today's static or changed returns still fill (true poses): in half
    # of the scans that see them or more. The box of a removed object, grown 0.25 m, takes in a
    # fence it stood against, or the end of the car parked in its place; no ray can tell those
    # voxels emptied. Scored beside the truth, not instead of it (docs/bench/lifelong.md, detect6)
    still = still_filled(truth_rm, (seen_k, seen_n), _count(rec.occupied))
    empty_rm = truth_rm[~still]
    alt = _block_scores(res, empty_rm, truth_ad, vm, th)
    out["emptied"] = {"removed_truth_still_filled": int(still.sum()), "removed": _prf(res.voxels.removed, empty_rm),
                      "block_precision": alt["block_precision"], "block_recall": alt["block_recall"],
                      "block_counts": alt["block_counts"],
                      "missed": [b["block"] for b in alt["blocks"] if b["changed"] and not b["confirmed"]]}
    return out


def still_filled(keys: np.ndarray, seen: tuple, occupied: tuple, share: float = 0.5) -> np.ndarray:
    """(K,) bool: each voxel of ``keys`` holds today's returns in ``share`` or more of the scans
    that see it. seen, occupied: (sorted keys, scans) of the voxels rays crossed and of the voxels
    holding returns (:func:`_count`); a scan with a return in a voxel saw it."""
    n_occ = _lookup(*occupied, keys)
    n_seen = np.maximum(_lookup(*seen, keys), n_occ)
    return (n_occ > 0) & (n_occ >= share * n_seen)


def _lookup(keys: np.ndarray, counts: np.ndarray, want: np.ndarray) -> np.ndarray:
    """(len(want),) the count of each of ``want`` in the sorted ``keys`` (0 where absent)."""
    if not len(keys):
        return np.zeros(len(want), np.int64)
    j = np.minimum(np.searchsorted(keys, want), len(keys) - 1)
    return np.where(keys[j] == want, counts[j], 0)


def _block_scores(res, truth_rm: np.ndarray, truth_ad: np.ndarray, vm: float, th) -> dict:
    """Per block, against the truth voxels ``truth_rm`` / ``truth_ad`` (module docstring): the rows,
    block precision and recall and their counts."""
    from blockloc.maps.changes.detect import cluster_sizes

    owned = block_truth(truth_rm, truth_ad, res, vm)
    rows, tp, fp, fn = [], 0, 0, 0
    for b in res.blocks:
        mine = owned[b["block"]]
        n_truth = len(mine)
        largest = int(cluster_sizes(mine).max()) if n_truth else 0
        changed, det = largest >= th.min_block_voxels, bool(b["confirmed"])
        tp += changed and det
        fp += det and not changed
        fn += changed and not det
        rows.append({"block": b["block"], "truth_voxels": n_truth, "truth_largest_voxels": largest,
                     "changed": changed, "removed_voxels": b["removed_voxels"], "added_voxels": b["added_voxels"],
                     "largest_change_m3": b.get("largest_change_m3"), "confirmed": det})
    # the examined blocks that did not change: what block precision is tested on (a detector
    # confirming every block scores precision 1.00 where there are none)
    tn = sum(1 for row in rows if not row["changed"] and not row["confirmed"])
    return {"blocks": rows, "block_precision": tp / (tp + fp) if tp + fp else float("nan"),
            "block_recall": tp / (tp + fn) if tp + fn else float("nan"),
            "block_counts": {"tp": tp, "fp": fp, "fn": fn, "tn": tn, "unchanged": tn + fp, "examined": len(rows)}}


def unchanged_day(P: str, S: int, mp: Path, run_dir: Path, stride: int) -> dict:
    """What ``blockloc map changes --map mp --run run_dir --stride stride`` finds on a run of
    month 0's ``loc`` drive: the mapping day's structure (no building, wall, hedge or site
    changed), but, as on every day the simulator makes, its parked cars and bins rearranged
    (``blockloc.sim.movables.session_movables``), the moving cars and walkers and the day's sensor
    noise. The truth is those rearranged movables (``_movable_changes``, as the changed sessions
    list them): a detected voxel is explained when it lies in a changed movable's box grown by one
    voxel; a confirmed block is falsely confirmed unless its explained voxels alone hold a
    26-connected cluster of the detector's ``min_block_m3``; ``false_alone``: its unexplained
    voxels alone hold one (a false alarm a true change next to it hides). Per block: detected and
    explained voxels, their largest clusters, the true movable changes the block holds
    (:func:`changes_per_block`), confirmed and false; where the unexplained voxels lie
    (:func:`where_voxels`); the detection's wall and CPU time (s) and the 1-min load average."""
    from blockloc.app.lifelong import detect_run_changes, open_block_store
    from blockloc.sim.changes import open_session

    t0, c0 = time.perf_counter(), time.process_time()
    rc = detect_run_changes(open_block_store(mp), run_dir, stride=stride)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    from scipy.spatial import cKDTree

    from blockloc.maps.changes.detect import Thresholds, cluster_sizes, unpack_keys

    res, seq = rc.result, open_session(P, "loc", S)
    vm = res.voxels.voxel_m
    boxes = np.array([c.box_map() for c in _day_changes(P, S, "loc")], float).reshape(-1, 6)

    def explained(keys: np.ndarray) -> np.ndarray:
        c = (unpack_keys(keys) + 0.5) * vm
        m = np.zeros(len(c), bool)
        for x0, x1, y0, y1, z0, z1 in boxes:
            m |= ((c[:, 0] > x0 - vm) & (c[:, 0] < x1 + vm) & (c[:, 1] > y0 - vm) & (c[:, 1] < y1 + vm)
                  & (c[:, 2] > z0 - vm) & (c[:, 2] < z1 + vm))
        return m

    rm, ad = np.asarray(res.voxels.removed, np.int64), np.asarray(res.voxels.added, np.int64)
    rm_ok, ad_ok = explained(rm), explained(ad)
    ids = list(res.block_keyframes)
    kf = [np.asarray(res.block_keyframes[b], float).reshape(-1, 3) for b in ids]
    owner = np.concatenate([[b] * len(k) for b, k in zip(ids, kf)]).astype(object)
    ad_owner = owner[cKDTree(np.concatenate(kf)).query((unpack_keys(ad) + 0.5) * vm)[1]] if len(ad) else owner[:0]
    truth = changes_per_block(P, S, "loc", mp)
    blocks = []
    th = Thresholds()

    def largest_m3(keys: np.ndarray) -> float:
        return float(cluster_sizes(np.unique(keys)).max()) * vm ** 3 if len(keys) else 0.0

    for b in res.blocks:
        i = b["block"]
        in_b, ad_b = np.isin(rm, res.block_keys[i]), ad_owner == i
        ok = np.concatenate([rm[in_b & rm_ok], ad[ad_b & ad_ok]])
        bad = np.concatenate([rm[in_b & ~rm_ok], ad[ad_b & ~ad_ok]])
        # confirmed truly when the explained voxels alone hold a change the detector confirms on
        # (one 26-connected cluster of min_block_m3), falsely otherwise; and whether the
        # unexplained ones alone would have confirmed the block (a false alarm hidden by a true one)
        ok_m3, bad_m3 = largest_m3(ok), largest_m3(bad)
        blocks.append({**{k: b.get(k) for k in ("block", "removed_voxels", "added_voxels", "dynamic_voxels",
                                                 "largest_change_m3", "confirmed")},
                       "detected_voxels": int(len(ok) + len(bad)), "explained_voxels": int(len(ok)),
                       "explained_largest_m3": ok_m3, "unexplained_largest_m3": bad_m3,
                       "true_changes": truth.get(i, []),
                       "false": bool(b["confirmed"]) and ok_m3 < th.min_block_m3 - 1e-9,
                       "false_alone": bad_m3 >= th.min_block_m3 - 1e-9})
    return {"session": "loc", "sequence": rc.sequence_name, "frames_trusted": res.frames_trusted,
            "scans_used": res.scans_used, "scans_rejected": res.scans_rejected,
            "examined": len(res.blocks), "confirmed": [b["block"] for b in blocks if b["confirmed"]],
            "false_confirmed": [b["block"] for b in blocks if b["false"]],
            "false_alone": [b["block"] for b in blocks if b["false_alone"]],
            "without_true_change": [b["block"] for b in blocks if not b["true_changes"]],
            "blocks": blocks, "min_block_m3": th.min_block_m3,
            "removed_voxels": int(len(rm)), "added_voxels": int(len(ad)),
            "removed_explained": int(rm_ok.sum()), "added_explained": int(ad_ok.sum()),
            "dynamic_voxels": int(len(res.voxels.dynamic)),
            "false_removed_where": where_voxels(seq, rm[~rm_ok], vm),
            "false_added_where": where_voxels(seq, ad[~ad_ok], vm),
            "wall_s": wall, "cpu_s": cpu, "load1": os.getloadavg()[0]}


def _day_changes(P: str, S: int, session: str) -> list:
    """The simulator's changes of ``session`` against the mapping day: a changed session's
    ``changes()``; for month 0's ``loc``, its rearranged parked cars and bins (the only change the
    simulator makes on that day; ``blockloc.sim.changes._movable_changes``, as the changed sessions
    list theirs)."""
    from blockloc.sim.changes import _movable_changes, open_session

    seq = open_session(P, session, S)
    if session == "loc":
        return _movable_changes(seq.world, "loc")[2]
    return seq.changes()


def _keyframe_tree(store):
    """A KD-tree over every block's mapping keyframes (its centroid where it keeps none), map frame,
    metres, and (K,) the block id of each keyframe: which block a place belongs to."""
    from scipy.spatial import cKDTree

    ids, kf = [], []
    for b in store.ids:
        e = store.entry(b)
        k = np.asarray(e.keyframes if e.keyframes is not None else e.centroid[None], float).reshape(-1, 3)
        ids += [b] * len(k)
        kf.append(k)
    return cKDTree(np.concatenate(kf)), np.asarray(ids, object)


def changes_per_block(P: str, S: int, session: str, mp: Path) -> dict:
    """Block id of the map ``mp`` -> the kinds of the simulator's changes of ``session`` (its
    ``changes()``) the block holds: a removed (or moved-away) object's box holding any of the
    block's map points, grown 0.25 m (the blocks overlap: every block that holds it); an added one
    by the block of the keyframe nearest its box's centre (as :func:`block_truth` assigns them).
    A block with an empty list is one no drive of that day can find changed."""
    from blockloc.maps.store import open_map

    store = open_map(mp)
    changes = _day_changes(P, S, session)
    out: dict = {b: [] for b in store.ids}
    tree, ids = _keyframe_tree(store)
    pts = {b: store.load(b)[0][:, :3].astype(float) for b in store.ids}
    pad = 0.25
    for c in changes:
        x0, x1, y0, y1, z0, z1 = c.box_map()
        if c.action in ("removed", "moved"):
            for b, p in pts.items():
                if ((p[:, 0] > x0 - pad) & (p[:, 0] < x1 + pad) & (p[:, 1] > y0 - pad) & (p[:, 1] < y1 + pad)
                        & (p[:, 2] > z0 - pad) & (p[:, 2] < z1 + pad)).any():
                    out[b].append(f"{c.kind} ({c.action})")
        if c.action in ("added", "moved"):
            centre = [(x0 + x1) / 2, (y0 + y1) / 2, (z0 + z1) / 2]
            out[str(ids[tree.query(centre)[1]])].append(f"{c.kind} ({c.action})")
    return out


def _metrics(run_dir: Path) -> dict:
    m = json.loads((run_dir / "metrics.json").read_text())
    return {k: m.get(k) for k in ("ate_trans_rmse_m", "ate_rot_rmse_deg", "failures", "rejected", "frames",
                                  "relocalizations")}


def segment_errors(P: str, S: int, session: str, run_dir: Path, parts: int = 10) -> list[float]:
    """RMS position error (m; against the session's truth, not aligned, as the run's ATE) of each
    of ``parts`` equal stretches (by frame) of the run in ``run_dir``: where along the route a map
    helps or hurts."""
    from blockloc.app.catalog import open_sequence
    from blockloc.trajectory_io import read_tum

    est = read_tum(run_dir / "poses.tum")
    gt = open_sequence(f"sim:{P}/{session}@{S}").ground_truth().interpolate(est.stamps)
    e = np.linalg.norm(est.poses[:, :3, 3] - gt[:, :3, 3], axis=1)
    return [float(np.sqrt(np.mean(c ** 2))) for c in np.array_split(e, parts) if len(c)]


def mapping_error_along(P: str, S: int, session: str, mapping: str, frames: int = 0) -> float:
    """RMS position error (m) of the ``mapping`` drive's mapping poses (the simulator's offline-SLAM
    error a map built from it inherits), taken at the mapping pose nearest each ``session`` truth
    pose (its first ``frames`` seconds x 10 when given): how good a map is where the session drives."""
    from scipy.spatial import cKDTree

    from blockloc.app.catalog import open_sequence

    route = open_sequence(f"sim:{P}/{session}@{S}").ground_truth()
    pos = route.poses[:, :3, 3]
    if frames:
        pos = pos[route.stamps <= route.stamps[0] + frames / 10.0]
    q = open_sequence(f"sim:{P}/{mapping}@{S}")
    mp = q.mapping_poses()
    truth = q.ground_truth().interpolate(mp.stamps)
    err = np.linalg.norm(mp.poses[:, :3, 3] - truth[:, :3, 3], axis=1)
    return float(np.sqrt(np.mean(err[cKDTree(truth[:, :3, 3]).query(pos[::10])[1]] ** 2)))


def same_error_poses(P: str, S: int, out: Path) -> Path:
    """A TUM file of ``map_m12``'s mapping poses carrying the mapping day's offline-SLAM error
    instead of its own: the two drives follow the same route on the same clock (their truths agree
    pose for pose; checked here), so the month-0 mapping poses, stamped on the 12-month day, are
    ``map_m12``'s truth with the stale map's error. A map built from them (``map build --poses``)
    differs from the stale map only by what changed in the world: the fresh reference with the
    mapping error held equal."""
    from blockloc.app.catalog import open_sequence
    from blockloc.geometry import Trajectory
    from blockloc.trajectory_io import write_tum

    m0, m12 = open_sequence(f"sim:{P}/map@{S}"), open_sequence(f"sim:{P}/map_m12@{S}")
    g0, g12 = m0.ground_truth(), m12.ground_truth()
    if len(g0.stamps) != len(g12.stamps) or not np.allclose(g0.poses, g12.poses, atol=1e-9):
        raise SystemExit(f"sim:{P}/map@{S} and map_m12 do not drive the same route on the same clock")
    mp = m0.mapping_poses()
    return write_tum(out, Trajectory(mp.stamps - g0.stamps[0] + g12.stamps[0], mp.poses))


def _update_group(text: str) -> str:
    """``--update-from``'s value: sessions joined by '+' (the runs of one ``map update``)."""
    parts = [t for t in text.split("+") if t]
    bad = [t for t in parts if t not in ("loc_m3", "map_m12")]
    if not parts or bad:
        raise argparse.ArgumentTypeError(f"expected loc_m3, map_m12 or loc_m3+map_m12, got {text!r}")
    return "+".join(dict.fromkeys(parts))


def _group_tag(group: str) -> str:
    """The name suffix of an update group's map and run (the default's, loc_m3, has none: the names
    kept in --work stay those of earlier runs)."""
    return "" if group == "loc_m3" else "_" + group.replace("+", "_")


def where_worse(P: str, S: int, mp: Path, upd: Path, run_dir: Path, parts: int = 10,
                reach_m: float = 40.0) -> list[dict]:
    """Where along loc_m12 (the ``parts`` stretches of :func:`segment_errors`, by frame of the run
    ``run_dir``) the update
    touched the map: per stretch, the stale map's blocks loc_m12 drives in (the block of the
    keyframe nearest each true pose) with what the update in ``upd`` did to each (``changed``:
    rebuilt; ``held back``: changes detected, not applied; ``-``: nothing detected), and the
    simulator's true changes (``changes()`` of loc_m12) within ``reach_m`` (the sensor's range) of
    the stretch. A stretch where the updated map trails the fresh one with no true change in reach
    owes it to the map's own mapping error, not to the update."""
    from blockloc.app.catalog import open_sequence
    from blockloc.maps.store import open_map
    from blockloc.sim.changes import open_session

    store = open_map(mp)
    tree, ids = _keyframe_tree(store)
    rec = json.loads((upd / "manifest.json").read_text()).get("lifelong") or {}
    changed = set(rec.get("changed_blocks") or [])
    held = {h["block"] for h in rec.get("held_back") or [] if "block" in h and h["block"] not in changed}
    seq = open_session(P, "loc_m12", S)
    boxes = np.array([c.box_map() for c in seq.changes()], float).reshape(-1, 6)
    lo, hi = boxes[:, [0, 2, 4]], boxes[:, [1, 3, 5]]
    from blockloc.trajectory_io import read_tum

    stamps = read_tum(run_dir / "poses.tum").stamps  # cut by frame as segment_errors cuts the runs
    truth = open_sequence(f"sim:{P}/loc_m12@{S}").ground_truth().interpolate(stamps)
    out = []
    for pos in np.array_split(truth[:, :3, 3], parts):
        blocks, n = np.unique(ids[tree.query(pos)[1]], return_counts=True)
        # distance from each pose to each change's box (0 inside)
        d = np.linalg.norm(np.maximum(np.maximum(lo[None] - pos[:, None], pos[:, None] - hi[None]), 0), axis=2) \
            if len(boxes) else np.zeros((len(pos), 0))
        near = np.flatnonzero((d <= reach_m).any(0)) if len(boxes) else []
        out.append({"blocks": {str(b): ("changed" if b in changed else "held back" if b in held else "-")
                               for b in blocks[np.argsort(-n)]},
                    "changes_in_reach": len(near),
                    "change_kinds": sorted({seq.changes()[i].kind for i in near})})
    return out


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def update_cost(mp: Path, upd: Path, fresh: Path | None, wall: float | None, cpu: float | None) -> dict:
    """Hash check of the unchanged blocks, sizes, time per changed block."""
    old = json.loads((mp / "manifest.json").read_text())
    new = json.loads((upd / "manifest.json").read_text())
    rec = new.get("lifelong") or {}
    changed = set(rec.get("changed_blocks") or [])
    files_old = {e["id"]: e["file"] for e in old["entries"]}
    same, differ = 0, []
    for e in new["entries"]:
        if e["id"] in changed:
            continue
        if e["id"] in files_old and _sha(upd / e["file"]) == _sha(mp / files_old[e["id"]]):
            same += 1
        else:
            differ.append(e["id"])
    size = lambda man: sum(int(e["bytes"]) for e in man["entries"])  # noqa: E731
    out = {"changed_blocks": sorted(changed), "unchanged_identical": same, "unchanged_differ": differ,
           "bytes_stale": size(old), "bytes_updated": size(new), "held_back": len(rec.get("held_back") or [])}
    if fresh is not None and (fresh / "manifest.json").is_file():
        out["bytes_fresh"] = size(json.loads((fresh / "manifest.json").read_text()))
    if wall is not None and changed:
        out["wall_per_block_s"], out["cpu_per_block_s"] = wall / len(changed), cpu / len(changed)
    out["update_wall_s"], out["update_cpu_s"] = wall, cpu
    return out


def dynamic_hook(work: Path, preset: str, seed: int) -> list[str]:
    """``--dynamic``: the dynamic-points comparison with DUFOMap in the same run (``python -m
    bench.dynamic``: the 12-month mapping day of this bench's preset and seed, exported in the
    DynamicMap Benchmark's layout, scored for the raw map, ours and DUFOMap); its page's lines."""
    from bench import dynamic

    page = dynamic.main(["--preset", preset, "--seed", str(seed), "--work", str(work / "dynamic"),
                         "--out", str(work / "dynamic.md")])
    return Path(page).read_text().splitlines()


def detect_while_tracking(work: Path, mp: Path, P: str, S: int, frames: int, stride: int, log: list,
                          key: str) -> dict:
    """``track --detect-changes`` on the first ``frames`` frames of loc_m12 in the stale map: the
    detection's cost (changes.json: per frame as the tracking loop feeds it, p50 / p99 / max, and
    the classification at the end) beside the tracking's (metrics.json; the process's CPU)."""
    from blockloc.cache import fingerprint

    # key: the detector's and the map's (cache_keys), and the code feeding it while tracking
    key = fingerprint("blockloc.app.runs", "blockloc.commands.track", params=(key,))
    out = work / f"run_loc_m12_detect_f{frames}_s{stride}-{key}"
    cmd = ["blockloc", "track", "--seq", f"sim:{P}/loc_m12@{S}", "--map", str(mp), "--init", "gt", "--no-record",
           "--max-frames", str(frames), "--detect-changes", "--changes-stride", str(stride), "--out", str(out)]
    _once(cmd, out / "changes.json", log)
    doc = json.loads((out / "changes.json").read_text())
    m = json.loads((out / "metrics.json").read_text())
    c = dict(doc["cost"])
    c.update(frames=frames, stride=stride, scans_used=doc["scans_used"], scans_rejected=doc["scans_rejected"],
             update_ms_median=m.get("update_ms_median"), update_ms_p99=m.get("update_ms_p99"),
             process_wall_s=log[-1][2], process_cpu_s=log[-1][3])
    return c


#: The modules whose code makes a map of ``blockloc map build`` (the simulator's sessions, the
#: loaders, the builder and its mounting estimate): a change to any of them is a new map.
BUILDER_MODULES = ("blockloc.sim", "blockloc.datasets", "blockloc.maps.block_maps", "blockloc.maps.build_plan",
                   "blockloc.maps.build_tasks", "blockloc.maps.mapping", "blockloc.maps.mounting",
                   "blockloc.maps.store", "blockloc.maps.pcd", "blockloc.registration", "blockloc.voxels",
                   "blockloc.geometry", "blockloc.config")
#: ... and those of ``blockloc map update`` (detection and rebuild), on top of the builder's.
UPDATE_MODULES = ("blockloc.maps.changes", "blockloc.app.lifelong", "blockloc.maps.dynamic_removal")


def cache_keys(P: str, S: int, stride: int) -> dict:
    """The keys the kept maps and runs are filed under in --work, so a map (and every run on it)
    made by an older builder is never reused: ``builder`` over BUILDER_MODULES' code and the map
    settings ``map build`` reads for the preset (the default config, e.g. ``calibrate_mounting``);
    ``update`` over UPDATE_MODULES' code, the builder key and the detection stride."""
    from blockloc.app.catalog import config_for_sequence
    from blockloc.cache import fingerprint

    builder = fingerprint(*BUILDER_MODULES, params=(P, S, repr(config_for_sequence(f"sim:{P}/map@{S}").map)))
    return {"builder": builder, "update": fingerprint(*UPDATE_MODULES, params=(builder, stride))}


def _f(v, nd=2) -> str:
    return "-" if v is None or (isinstance(v, float) and not np.isfinite(v)) else f"{v:.{nd}f}"


def main(argv: list[str] | None = None) -> Path:
    ap = argparse.ArgumentParser(prog="python -m bench.lifelong")
    ap.add_argument("--preset", default="tiny")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--sessions", default="loc_m3,loc_m12", help="sessions to detect on (comma separated)")
    ap.add_argument("--update-from", action="append", type=_update_group,
                    help="loc/cost: the session(s) whose stale-map runs update the map, '+' joining runs of one "
                         "update (loc_m3, map_m12: another drive of the 12-month day, which carries the changes "
                         "loc_m12 meets, loc_m3+map_m12: both runs in one `map update`); repeat for several "
                         "updated maps (default: loc_m3)")
    ap.add_argument("--frames", type=int, default=0, help="track only the first N frames of each session (0: all)")
    ap.add_argument("--stride", type=int, default=2, help="detection uses every stride-th trusted frame")
    ap.add_argument("--parts", default=",".join(PARTS), help=f"comma separated: {', '.join(PARTS)}")
    ap.add_argument("--detect-frames", type=int, default=200,
                    help="track: frames tracked with --detect-changes (loc_m12 on the stale map)")
    ap.add_argument("--dynamic", action="store_true", help="also the DUFOMap comparison (bench/_dynamic.py)")
    ap.add_argument("--map", type=Path, help="with --run: the stale map of the run (nothing is built)")
    ap.add_argument("--run", type=Path, help="detect only: score this tracking run (on --map) of the one session "
                    "in --sessions; nothing is built or tracked (the campus: a run of thousands of frames)")
    ap.add_argument("--work", type=Path, default=Path("/tmp/blockloc-bench-lifelong"))
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args(argv)
    args.update_from = list(dict.fromkeys(args.update_from or ["loc_m3"]))
    if args.run is not None and (args.map is None or args.parts != "detect" or "," in args.sessions):
        ap.error("--run needs --map, one session in --sessions and --parts detect")
    from bench.__main__ import machine

    P, S, parts = args.preset, args.seed, set(args.parts.split(","))
    sessions = [s for s in args.sessions.split(",") if s]
    work = args.work / (f"{P}_{S}" + (f"_f{args.frames}" if args.frames else ""))
    work.mkdir(parents=True, exist_ok=True)
    lim = ["--max-frames", str(args.frames)] if args.frames else []
    log: list = []
    load0, t_all = os.getloadavg()[0], time.perf_counter()
    keys = cache_keys(P, S, args.stride)
    bk, uk = keys["builder"], keys["update"]  # every kept map and run is filed under its maker's key
    mp = work / f"map-{bk}" if args.map is None else args.map
    if args.run is None:
        _once(["blockloc", "map", "build", "--seq", f"sim:{P}/map@{S}", "--kind", "block", "--out", str(mp)],
              mp / "manifest.json", log)

    def track(session: str, map_dir: Path, name: str) -> Path:
        out = work / name
        _once(["blockloc", "track", "--seq", f"sim:{P}/{session}@{S}", "--map", str(map_dir), "--init", "gt",
               "--no-record", "--out", str(out), *lim], out / "metrics.json", log)
        return out

    groups = args.update_from
    srcs = {s for g in groups for s in g.split("+")}
    need = (set(sessions) if "detect" in parts else set()) | (srcs | {"loc_m12"} if parts & {"loc", "cost"} else set())
    need |= {"loc"} if "unchanged" in parts else set()
    if args.run is None:
        runs = {s: track(s, mp, f"run_{s}_stale-{bk}") for s in ("loc", "loc_m3", "loc_m12", "map_m12")
                if s in need}
    else:  # given: scored as it is
        runs = {sessions[0]: args.run}
    from blockloc.maps.changes.detect import Thresholds

    result: dict = {"preset": P, "seed": S, "frames": args.frames, "stride": args.stride, "load1_start": load0,
                    "keys": keys,
                    "min_block_m3": Thresholds().min_block_m3}

    def write() -> None:  # after every part: a long run stopped half-way keeps what it measured
        result["load1_end"], result["wall_s"] = os.getloadavg()[0], time.perf_counter() - t_all
        (work / f"bench_{args.out.stem}.json").write_text(json.dumps(result, indent=1, default=str))
        args.out.parent.mkdir(parents=True, exist_ok=True)
        tmp = args.out.with_suffix(".md.tmp")
        tmp.write_text("\n".join(render(result, args, log, machine(), dyn)) + "\n")
        tmp.replace(args.out)

    dyn: list[str] = []
    if "detect" in parts:
        result["detect"] = []
        for s in sessions:
            result["detect"].append(score_detection(P, S, s, mp, runs[s], args.stride))
            write()
    if "unchanged" in parts and args.run is None:
        result["unchanged"] = unchanged_day(P, S, mp, runs["loc"], args.stride)
        result["changes_per_block"] = {s: changes_per_block(P, S, s, mp) for s in ("loc", *sessions)}
        write()
    upds: dict = {}  # update group -> (its map, wall, cpu)
    fresh, fresh_same = work / f"map_fresh-{bk}", work / f"map_fresh_same_error-{bk}"
    if parts & {"loc", "cost"}:
        for g in groups:
            upd, wall, cpu = work / f"map_upd{_group_tag(g)}-{uk}", None, None
            cmd = ["blockloc", "map", "update", str(mp)]
            for s in g.split("+"):
                cmd += ["--run", str(runs[s])]
            cmd += ["--out", str(upd), "--stride", str(args.stride)]
            if (upd / "manifest.json").exists():
                log.append((cmd, True, None, None))
            else:
                wall, cpu = _run(cmd)
                log.append((cmd, False, wall, cpu))
            upds[g] = (upd, wall, cpu)
        if "cost" in parts:
            result["costs"] = {g: update_cost(mp, u, None, w, c) for g, (u, w, c) in upds.items()}
            write()
        _once(["blockloc", "map", "build", "--seq", f"sim:{P}/map_m12@{S}", "--kind", "block", "--out", str(fresh)],
              fresh / "manifest.json", log)
        if "loc" in parts:  # the fresh map again, with the stale map's mapping error (same_error_poses)
            tum = same_error_poses(P, S, work / f"map_m12_poses_with_map_error-{bk}.tum")
            _once(["blockloc", "map", "build", "--seq", f"sim:{P}/map_m12@{S}", "--poses", str(tum), "--kind",
                   "block", "--out", str(fresh_same)], fresh_same / "manifest.json", log)
        if "cost" in parts:
            result["costs"] = {g: update_cost(mp, u, fresh, w, c) for g, (u, w, c) in upds.items()}
            write()
    if "loc" in parts:
        result["loc"] = {}
        # the stale map on the mapping month's own loc drive (nothing changed): what the map gives
        # without any change, so its mapping error is told apart from the year's changes
        rows = (("stale", "loc_m12", mp, bk),
                *((f"updated{_group_tag(g)}", "loc_m12", upds[g][0], uk) for g in groups),
                ("fresh", "loc_m12", fresh, bk),
                ("fresh_same_error, the stale map's mapping error", "loc_m12", fresh_same, bk),
                ("stale, month 0 (loc: no change)", "loc", mp, bk))
        for name, session, m, key in rows:
            run = track(session, m, f"run_{session}_{name.split(',')[0]}-{key}")
            result["loc"][name] = {**_metrics(run), "segments": segment_errors(P, S, session, run)}
            write()
        stale_run = work / f"run_loc_m12_stale-{bk}"
        result["where"] = {g: where_worse(P, S, mp, upds[g][0], stale_run) for g in groups}
        write()
        result["mapping_error"] = {m: mapping_error_along(P, S, "loc_m12", m, args.frames) for m in ("map", "map_m12")}
        write()
    if "track" in parts:
        result["track"] = detect_while_tracking(work, mp, P, S, args.detect_frames, args.stride, log, uk)
        write()
    if args.dynamic:
        dyn = dynamic_hook(work, P, S)
    write()
    print((args.out).read_text())
    return args.out


def _where_lines(r: dict) -> list[str]:
    """The per-tenth table of each updated map against the fair fresh map (:func:`where_worse`)."""
    loc = r["loc"]
    fair = (loc.get("fresh_same_error, the stale map's mapping error") or {}).get("segments")
    fresh, stale = (loc.get("fresh") or {}).get("segments"), (loc.get("stale") or {}).get("segments")
    L = []
    for g, where in r["where"].items():
        seg = (loc.get(f"updated{_group_tag(g)}") or {}).get("segments")
        if not seg or not fair or len(seg) != len(where):
            continue
        L += ["", f"#### Where the map updated from {g} trails the fresh maps (loc_m12 by tenths)", "",
              "RMS position error of each tenth of the run (m); blocks: the stale map's blocks of the keyframes "
              "nearest the true poses, most frames first, with what the update did (changed / held back / -); "
              "true changes: the simulator's changes of the 12-month day within 40 m of the stretch.", "",
              "| tenth | stale | updated | fresh | fresh, stale map's error | updated - fair fresh | blocks | "
              "true changes in reach |", "|---|---|---|---|---|---|---|---|"]
        for k, w in enumerate(where):
            blocks = ", ".join(f"{b} ({s})" for b, s in w["blocks"].items())
            L.append(f"| {k + 1} | {_f(stale[k], 3) if stale else '-'} | {seg[k]:.3f} | "
                     f"{_f(fresh[k], 3) if fresh else '-'} | {fair[k]:.3f} | {seg[k] - fair[k]:+.3f} | {blocks} | "
                     f"{w['changes_in_reach']} ({', '.join(w['change_kinds']) or '-'}) |")
    return L


def _unchanged_lines(r: dict) -> list[str]:
    """The unchanged part: month 0's drive through the detector, and the change list per block."""
    u = r["unchanged"]
    fr, fa = u["false_removed_where"], u["false_added_where"]
    L = ["", "### Block precision on month 0's `loc` drive (no structure changed, parked cars and bins rearranged)", "",
         f"`blockloc map changes --map MAP --run RUN_loc --stride {r['stride']}` (its recipe, through the API) on "
         "the stale-map run of `loc`, another drive of the mapping day. Its only true changes are the parked cars "
         "and bins the simulator rearranges on every day; a detected voxel is explained when it lies in one's box "
         "(grown a voxel); a confirmed block is falsely confirmed unless its explained voxels alone hold a "
         f"26-connected cluster of {u['min_block_m3']:g} m^3 (the detector's rule); 'unexplained alone' counts the "
         "blocks whose unexplained voxels alone hold one (a false alarm a true change beside it hides).", "",
         "| session | scans used (gated) | blocks examined (without a true change) | confirmed | falsely confirmed "
         "| unexplained alone would confirm | removed voxels: explained (unexplained: vegetation, ground, other) "
         "| added voxels: explained (unexplained: ...) | detection wall / CPU |", "|---|---|---|---|---|---|---|---|---|",
         f"| loc | {u['scans_used']} ({u['scans_rejected']}) | {u['examined']} ({len(u['without_true_change'])}) | "
         f"{len(u['confirmed'])} | {len(u['false_confirmed'])}"
         + (f" ({', '.join(u['false_confirmed'])})" if u["false_confirmed"] else "")
         + f" | {len(u['false_alone'])}" + (f" ({', '.join(u['false_alone'])})" if u["false_alone"] else "")
         + f" | {u['removed_voxels']}: {u['removed_explained']} ({fr['vegetation']}, {fr['ground']}, {fr['other']}) "
         f"| {u['added_voxels']}: {u['added_explained']} ({fa['vegetation']}, {fa['ground']}, {fa['other']}) | "
         f"{u['wall_s']:.0f} / {u['cpu_s']:.0f} s (load {u['load1']:.1f}) |", "",
         "| block | true changes (parked) | detected voxels (explained) | largest cluster m^3: detected / explained "
         "/ unexplained | confirmed | false |", "|---|---|---|---|---|---|"]
    for b in u["blocks"]:
        L.append(f"| {b['block']} | {len(b['true_changes'])} | {b['detected_voxels']} ({b['explained_voxels']}) | "
                 f"{_f(b.get('largest_change_m3'), 2)} / {b['explained_largest_m3']:.2f} / "
                 f"{b['unexplained_largest_m3']:.2f} | {b['confirmed']} | {b['false']} |")
    cpb = r.get("changes_per_block") or {}
    if cpb:
        L += ["", "The simulator's changes each block of the map holds (removed: the box holds the block's map "
              "points; added: the block of the keyframe nearest the box); a block with none is one a drive of that "
              "day can find unchanged:", "", "| session | block | changes |", "|---|---|---|"]
        for s, per in cpb.items():
            for b, kinds in per.items():
                counts = {k: kinds.count(k) for k in dict.fromkeys(kinds)}
                L.append(f"| {s} | {b} | {len(kinds)}: " + (", ".join(f"{n} {k}" for k, n in counts.items()) or "none")
                         + " |")
    return L


def render(r: dict, args, log: list, machine: str, dyn: list[str]) -> list[str]:
    sessions = (f" --sessions {args.sessions}" if {"detect", "unchanged"} & set(args.parts.split(",")) else "")
    ups = getattr(args, "update_from", None) or ["loc_m3"]
    cmd = (f"python -m bench.lifelong --preset {r['preset']} --seed {r['seed']}{sessions} "
           f"--stride {r['stride']} --parts {args.parts}" + (f" --frames {r['frames']}" if r["frames"] else "")
           + (f" --detect-frames {args.detect_frames}" if "track" in args.parts.split(",") else "")
           + "".join(f" --update-from {g}" for g in ups if ups != ["loc_m3"])
           + (" --dynamic" if args.dynamic else "")
           + (f" --map {args.map} --run {args.run}" if getattr(args, "run", None) is not None else ""))
    L = ["## Lifelong maps: change detection, tracking months later, update cost", "",
         f"Command: `{cmd}`, run {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())} on {machine}; "
         f"one run, seed {r['seed']}; 1-min load average {r['load1_start']:.1f} at the start, "
         f"{r['load1_end']:.1f} at the end ({r['wall_s'] / 60:.0f} min wall in all; shared machine: wall times are "
         "not speed figures). Steps as a user types them:", ""]
    if getattr(args, "run", None) is not None:
        L.append(f"- the map `{args.map}` and the run `{args.run}` given (not built or tracked here); the detection is "
                 f"`blockloc map changes --map {args.map} --run {args.run} --stride {r['stride']}`'s, through the API")
    for c, reused, wall, cpu in log:
        L.append(f"- `{' '.join(c)}`" + (" (kept from an earlier run)" if reused else f": {wall:.0f} s wall, {cpu:.0f} s CPU"))
    if "detect" in r:
        L += ["", "### Detection against the truth", "",
              "Voxels of 0.5 m; right within one voxel (bench/lifelong.py's docstring has the truth).", "",
              "| session | scans used (gated) | removed P / R / F1 (det, truth) | added P / R / F1 (det, truth) "
              "| blocks P / R (tp, fp, fn of examined) | unchanged blocks examined (falsely confirmed) "
              "| detection CPU per scan (frames' casting left out) |", "|---|---|---|---|---|---|---|"]
        for d in r["detect"]:
            rm, ad, bc = d["removed"], d["added"], d["block_counts"]
            L.append(f"| {d['session']} | {d['scans_used']} ({d['scans_rejected']}) | {_f(rm['precision'])} / "
                     f"{_f(rm['recall'])} / {_f(rm['f1'])} ({rm['detected']}, {rm['truth']}) | {_f(ad['precision'])} / "
                     f"{_f(ad['recall'])} / {_f(ad['f1'])} ({ad['detected']}, {ad['truth']}) | "
                     f"{_f(d['block_precision'])} / {_f(d['block_recall'])} ({bc['tp']}, {bc['fp']}, {bc['fn']} of "
                     f"{bc['examined']}) | {bc.get('unchanged', '-')} ({bc['fp']}) | "
                     f"{d['cpu_per_scan_s']:.2f} s (load {d['load1']:.1f}) |")
        if any("emptied" in d for d in r["detect"]):
            L += ["", "The same detection against the removed truth less the voxels today's static or changed returns "
                  "(true poses) still fill in half of the scans that see them (a fence the removed car stood against, "
                  "the end of the car parked in its place: the box of the removed object, grown 0.25 m, takes them in):", "",
                  "| session | removed truth voxels still filled | removed P / R / F1 (det, truth) "
                  "| blocks P / R (tp, fp, fn of examined) | missed blocks |", "|---|---|---|---|---|"]
            for d in r["detect"]:
                e = d.get("emptied")
                if e:
                    rm, bc = e["removed"], e["block_counts"]
                    L.append(f"| {d['session']} | {e['removed_truth_still_filled']} | {_f(rm['precision'])} / "
                             f"{_f(rm['recall'])} / {_f(rm['f1'])} ({rm['detected']}, {rm['truth']}) | "
                             f"{_f(e['block_precision'])} / {_f(e['block_recall'])} ({bc['tp']}, {bc['fp']}, {bc['fn']} "
                             f"of {bc['examined']}) | {', '.join(e['missed']) or '-'} |")
        L += ["", "Where the false detections lie (vegetation volume / within 0.5 m of the terrain / elsewhere):", "",
              "| session | false removed: vegetation, ground, other | false added: vegetation, ground, other |",
              "|---|---|---|"]
        for d in r["detect"]:
            fr, fa = d.get("false_removed_where") or {}, d.get("false_added_where") or {}
            L.append(f"| {d['session']} | {fr.get('vegetation', '-')}, {fr.get('ground', '-')}, {fr.get('other', '-')} | "
                     f"{fa.get('vegetation', '-')}, {fa.get('ground', '-')}, {fa.get('other', '-')} |")
        L += ["", "Per block (truth voxels: observed removed + added truth voxels the block owns; changed when "
              "their largest 26-connected cluster has 8 voxels, 1 m^3; confirmed when the detected one spans "
              f"min_block_m3 = {r.get('min_block_m3', '-')} m^3):", "",
              "| session | block | truth voxels (largest cluster) | changed | detected removed | detected added "
              "| largest detected cluster m^3 | confirmed |",
              "|---|---|---|---|---|---|---|---|"]
        for d in r["detect"]:
            for b in d["blocks"]:
                if b["truth_voxels"] or b["removed_voxels"] or b["added_voxels"]:
                    L.append(f"| {d['session']} | {b['block']} | {b['truth_voxels']} ({b.get('truth_largest_voxels', '-')}) "
                             f"| {b['changed']} | {b['removed_voxels']} | {b['added_voxels']} | "
                             f"{_f(b.get('largest_change_m3'), 1)} | {b['confirmed']} |")
    if "unchanged" in r:
        L += _unchanged_lines(r)
    if "loc" in r:
        L += ["", "### Tracking loc_m12 (12 months later) on each map", "",
              "Worst tenth: the route cut in ten stretches by frame, the largest RMS position error of a "
              "stretch minus the stale map's on the same stretch (above 0: worse than the stale map there).", "",
              "| map | ATE translation RMSE (m) | rotation RMSE (deg) | failures | rejected scans | frames "
              "| worst tenth vs stale (m) |",
              "|---|---|---|---|---|---|---|"]
        base = (r["loc"].get("stale") or {}).get("segments")
        for name, m in r["loc"].items():
            seg = m.get("segments")
            worst = (max(a - b for a, b in zip(seg, base)) if seg and base and len(seg) == len(base)
                     and name != "stale" and "month 0" not in name else None)
            L.append(f"| {name} | {_f(m['ate_trans_rmse_m'], 3)} | {_f(m['ate_rot_rmse_deg'], 2)} | {m['failures']} | "
                     f"{m['rejected']} | {m['frames']} | {'-' if worst is None else f'{worst:+.3f}'} |")
        if r.get("mapping_error"):
            me = r["mapping_error"]
            L += ["", f"The maps' own pose error where loc_m12 drives (the simulator's offline-SLAM error of the "
                  f"mapping drive, RMS at the mapping pose nearest each loc_m12 pose): stale and updated "
                  f"(`map`) {me['map']:.3f} m, fresh (`map_m12`) {me['map_m12']:.3f} m."]
    if r.get("where") and r.get("loc"):
        L += _where_lines(r)
    costs = r.get("costs") or ({"loc_m3": r["cost"]} if "cost" in r else {})
    if costs:
        L += ["", "### Update cost", ""]
    for g, c in costs.items():
        L += [f"Updated from {g}: changed blocks {len(c['changed_blocks'])} ({', '.join(c['changed_blocks']) or '-'}); "
              f"held back: {c['held_back']}. Unchanged blocks byte-identical (sha256 of the files): "
              f"{c['unchanged_identical']} of {c['unchanged_identical'] + len(c['unchanged_differ'])}"
              + (f" (differ: {', '.join(c['unchanged_differ'])})" if c["unchanged_differ"] else "") + ". "
              f"Size: stale {c['bytes_stale'] / 1e6:.2f} MB, updated {c['bytes_updated'] / 1e6:.2f} MB"
              + (f", fresh {c['bytes_fresh'] / 1e6:.2f} MB (updated / fresh = {c['bytes_updated'] / c['bytes_fresh']:.2f})"
                 if c.get("bytes_fresh") else "") + "."
              + (f" Update (the whole command, detection included): {c['update_wall_s']:.0f} s wall, "
                 f"{c['update_cpu_s']:.0f} s CPU; per changed block {c['wall_per_block_s']:.1f} s wall, "
                 f"{c['cpu_per_block_s']:.1f} s CPU." if c.get("wall_per_block_s") is not None else ""), ""]
    if "track" in r:
        t = r["track"]
        L += ["", "### Change detection in `track --detect-changes`", "",
              f"loc_m12 on the stale map, first {t['frames']} frames, every {t['stride']}-th trusted frame used "
              f"({t['scans_used']} scans used, {t['scans_rejected']} gated)."]
        if "per_frame_cpu_ms" not in t:  # a run of the detector after the last frame (before 2026-12-06 13:00)
            L += ["The detection ran after the last frame; its cost amortized per frame tracked.", "",
                  "| what | wall | CPU |", "|---|---|---|",
                  f"| detection per frame tracked | {t['wall_ms_per_frame_tracked']:.0f} ms | "
                  f"{t['cpu_ms_per_frame_tracked']:.0f} ms |"]
        else:
            pf, ps = t["per_frame_cpu_ms"], t["per_scan_cpu_ms"]
            wf, ws = t["per_frame_wall_ms"], t["per_scan_wall_ms"]
            L += ["The detector is fed each frame as the tracking loop emits it (in the same thread; a used frame "
                  "is processed when the next trusted frame brings the pose after it). CPU: the detector's thread "
                  "(`time.thread_time`); per frame tracked: every frame's call, per scan used: the calls that "
                  f"processed a scan; the classification runs once at the end. 1-min load average {t['load_1min']} "
                  "at its end. Budget: the 100 ms scan period, with the tracking's own time in it.", "",
                  "| what | p50 | p99 | max | wall p50 / p99 |", "|---|---|---|---|---|",
                  f"| detection CPU per frame tracked | {pf['p50']:.1f} ms | {pf['p99']:.1f} ms | {pf['max']:.0f} ms | "
                  f"{wf['p50']:.1f} / {wf['p99']:.1f} ms |",
                  f"| detection CPU per scan used | {ps['p50']:.1f} ms | {ps['p99']:.1f} ms | {ps['max']:.0f} ms | "
                  f"{ws['p50']:.1f} / {ws['p99']:.1f} ms |",
                  *([f"| ... per scan used, no block joining | {t['per_scan_no_join_cpu_ms']['p50']:.1f} ms | "
                     f"{t['per_scan_no_join_cpu_ms']['p99']:.1f} ms | {t['per_scan_no_join_cpu_ms']['max']:.0f} ms | - |",
                     f"| ... the {t['join_frames']} frames blocks joined on | {t['join_cpu_ms']['p50']:.1f} ms | "
                     f"{t['join_cpu_ms']['p99']:.1f} ms | {t['join_cpu_ms']['max']:.0f} ms | - |"]
                    if "join_cpu_ms" in t else []),
                  f"| tracking update per scan (wall) | {_f(t['update_ms_median'], 1)} ms | "
                  f"{_f(t['update_ms_p99'], 1)} ms | - | - |", "",
                  "| what | wall | CPU |", "|---|---|---|",
                  f"| detection, whole (frames and the end) | {t['wall_s']:.1f} s | {t['cpu_s']:.1f} s |",
                  f"| the classification at the end | {t['final_wall_s']:.2f} s | {t['final_cpu_s']:.2f} s |",
                  *([f"| the kernels loaded before the first frame (startup) | {t['startup_wall_s']:.2f} s | "
                     f"{t['startup_cpu_s']:.2f} s |"] if t.get("startup_cpu_s") is not None else []),
                  f"| detection per frame tracked, the end included (mean) | {t['wall_ms_per_frame_tracked']:.1f} ms | "
                  f"{t['cpu_ms_per_frame_tracked']:.1f} ms |"]
        if t.get("process_cpu_s") is not None:
            L.append(f"| the whole command (tracking + detection + writing) | {t['process_wall_s']:.0f} s | "
                     f"{t['process_cpu_s']:.0f} s |")
        if "blocks_loaded" in t:
            L += ["", f"Blocks loaded by the detector: {t['blocks_loaded']} of the map's {t['blocks_in_map']}."]
    if dyn:
        L += ["", "### Dynamic points", "", *dyn]
    return L


if __name__ == "__main__":
    main(sys.argv[1:])
