"""Map update: rebuild only the blocks with confirmed changes, as a new version of the store.

From one or more runs' :class:`~.pipeline.ChangeResult` (each from that run's trusted, gated
scans only):

1. **Strong evidence.** A removed or added voxel is applied when two runs or more found it, or one
   run saw it over ``strong_scans`` scans or more (removed: scans that saw through it; added:
   scans that hit it). Everything weaker is held back and reported.
2. **Coherent changes.** Of the strong voxels, removed and added together, only those in a
   26-connected cluster of ``min_change_m3`` or more are applied (a wall, a building, a parked car:
   one changed object; 3 m³ by default, stricter than the 1 m³ by which the detector confirms a
   block, its ``min_block_m3``: an update writes the map, a report only points at it);
   voxels scattered over a block (a grazing ray, a mixed pixel, a pose a few centimetres off
   carving a facade's edge) are held back and reported, so they never carve the map.
3. **Confirmed blocks.** A block is rebuilt when its applied voxels number ``min_block_voxels``
   or more; other blocks with detected changes are held back (reported with their counts).
   **Grown.** A weak voxel (too little evidence alone) joined by 26-connection to an applied
   change is applied with it (hysteresis, as an edge detector grows strong edges through weak
   ones): the far corners of a removed wall, seen through by fewer scans than its middle, are the
   same object; weak voxels touching no applied change stay held back.
4. **Rebuild.** A confirmed block keeps its points outside the applied removed voxels and gains
   the runs' points inside the applied added voxels it owns (the nearest keyframe's block),
   voxel-filtered at the store's ``voxel_size_m``. It also gains what the change **revealed**:
   the runs' new points (off the map) within ``reveal_m`` of an applied change that are
   persistent (their ``voxel_m / 2`` cell hit by ``reveal_hits`` scan points or more, the runs
   together) and outside dynamic voxels: the ground and facades a removed building hid from the
   mapping day, which the detector cannot call "added" (the mapping day never had them in
   sight) yet a map built fresh holds. Dynamic voxels are never added.
5. **Write.** The new block files get new names (``<id>.v<N>.pcd``); every other entry is copied
   from the parent manifest as it is (the same file, the same bytes). The place index is rebuilt
   by the ``place_index`` function the caller passes (the application layer builds it from the
   config: ``blockloc.app.lifelong``; global init's per-entry rasters are cached by content: only
   the changed blocks' are computed again). Then the version is committed (:mod:`.versions`).
"""

from __future__ import annotations

import hashlib
import json
import logging
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from blockloc.errors import MapError
from blockloc.maps.changes.detect import unique_keys, unpack_keys, voxel_keys

log = logging.getLogger(__name__)


@dataclass
class UpdatePlan:
    """What an update applies. removed / added: sorted voxel keys applied; voxel_m: their edge;
    blocks: block id -> counts of the confirmed blocks; held_back: dicts of what was not applied."""

    voxel_m: float
    removed: np.ndarray
    added: np.ndarray
    blocks: dict = field(default_factory=dict)
    held_back: list = field(default_factory=list)
    added_owner: dict = field(default_factory=dict)  # added voxel key -> block id that gains it
    #: revealed points (module docstring, step 4): their reach from an applied change (m; 0: none)
    #: and the fewest scan points per ``voxel_m / 2`` cell
    reveal_m: float = 0.0
    reveal_hits: int = 3
    grown: int = 0  # weak voxels applied with the change they touch


def _strong(keys_per_run: list[np.ndarray], scans_per_run: list[np.ndarray], strong_scans: int, min_runs: int):
    if not keys_per_run:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    allk = np.concatenate(keys_per_run)
    alls = np.concatenate(scans_per_run)
    keys, inv = np.unique(allk, return_inverse=True)
    runs = np.bincount(inv, minlength=len(keys))
    best = np.zeros(len(keys), np.int64)
    np.maximum.at(best, inv, alls)
    return keys[(runs >= min_runs) | (best >= strong_scans)], keys[(runs < min_runs) & (best < strong_scans)]


def coherent(removed: np.ndarray, added: np.ndarray, voxel_m: float, min_change_m3: float):
    """Split strong voxels (sorted keys, edge ``voxel_m``) into those in a 26-connected cluster
    (removed and added together) of ``min_change_m3`` or more and the scattered rest:
    (removed kept, added kept, removed scattered, added scattered)."""
    from blockloc.maps.changes.detect import cluster_sizes

    both = np.union1d(removed, added)
    if not len(both) or min_change_m3 <= 0:
        return removed, added, removed[:0], added[:0]
    big = both[cluster_sizes(both) * voxel_m ** 3 >= min_change_m3 - 1e-9]
    rm_in, ad_in = np.isin(removed, big), np.isin(added, big)
    return removed[rm_in], added[ad_in], removed[~rm_in], added[~ad_in]


def grow(removed: np.ndarray, added: np.ndarray, rm_weak: np.ndarray, ad_weak: np.ndarray):
    """Weak voxels (sorted keys) 26-connected, through weak ones, to an applied one (``removed`` /
    ``added``, sorted keys): (removed grown, added grown, removed weak left, added weak left)."""
    from blockloc.maps.changes.detect import cluster_labels

    applied = np.union1d(removed, added)
    if not len(applied) or not (len(rm_weak) or len(ad_weak)):
        return removed, added, rm_weak, ad_weak
    both = np.union1d(applied, np.union1d(rm_weak, ad_weak))
    label = cluster_labels(both)
    keep = np.isin(label, label[np.searchsorted(both, applied)])
    joined = both[keep]
    rj, aj = np.isin(rm_weak, joined), np.isin(ad_weak, joined)
    return (np.union1d(removed, rm_weak[rj]), np.union1d(added, ad_weak[aj]), rm_weak[~rj], ad_weak[~aj])


def plan_update(results: list, *, strong_scans: int = 15, min_runs: int = 2, min_block_voxels: int = 8,
                min_change_m3: float = 3.0, grow_weak: bool = True, reveal_m: float = 10.0,
                reveal_hits: int = 3) -> UpdatePlan:
    """Decide what to apply from runs' ChangeResults (module docstring, steps 1-3). min_change_m3:
    the smallest coherent change applied (m^3; 0: every strong voxel). grow_weak: apply the weak
    voxels joined to an applied change. reveal_m, reveal_hits: the revealed points' reach (m; 0:
    none) and persistence (step 4)."""
    from scipy.spatial import cKDTree

    if not results:
        raise MapError("map update: no run to update from")
    voxel_m = results[0].voxels.voxel_m
    if any(r.voxels.voxel_m != voxel_m for r in results):
        raise MapError("map update: the runs' change voxels differ in size")
    rm, rm_weak = _strong([r.voxels.removed for r in results], [r.voxels.removed_free for r in results],
                          strong_scans, min_runs)
    ad, ad_weak = _strong([r.voxels.added for r in results], [r.voxels.added_hits for r in results],
                          strong_scans, min_runs)
    rm, ad, rm_lone, ad_lone = coherent(rm, ad, voxel_m, min_change_m3)
    grown = 0
    if grow_weak:
        n0 = len(rm) + len(ad)
        rm, ad, rm_weak, ad_weak = grow(rm, ad, rm_weak, ad_weak)
        grown = len(rm) + len(ad) - n0
    block_keys, block_kf = {}, {}
    for r in results:
        block_keys.update(r.block_keys)
        block_kf.update(r.block_keyframes)
    ids = list(block_keys)
    kf = [np.asarray(block_kf[b], float).reshape(-1, 3) for b in ids]
    owner = np.concatenate([[b] * len(k) for b, k in zip(ids, kf)]).astype(object) if ids else np.zeros(0, object)
    kf = np.concatenate(kf) if kf else np.zeros((0, 3))

    def owners(keys):
        if not len(keys) or not len(kf):
            return np.zeros(len(keys), object)
        return owner[cKDTree(kf).query((unpack_keys(keys) + 0.5) * voxel_m)[1]]

    ad_owner, adw_owner, adl_owner = owners(ad), owners(ad_weak), owners(ad_lone)
    plan = UpdatePlan(voxel_m, np.zeros(0, np.int64), np.zeros(0, np.int64), reveal_m=float(reveal_m),
                      reveal_hits=int(reveal_hits), grown=int(grown))
    applied_rm, applied_ad = [], []
    for b in ids:
        r_in = rm[np.isin(rm, block_keys[b])]
        a_in = ad[ad_owner == b]
        weak = int(np.isin(rm_weak, block_keys[b]).sum() + (adw_owner == b).sum())
        lone = int(np.isin(rm_lone, block_keys[b]).sum() + (adl_owner == b).sum())
        n = len(r_in) + len(a_in)
        if n >= min_block_voxels:
            plan.blocks[b] = {"removed_voxels": len(r_in), "added_voxels": len(a_in), "held_back_voxels": weak,
                              "scattered_voxels": lone}
            applied_rm.append(r_in)
            applied_ad.append(a_in)
        elif n or weak or lone:
            plan.held_back.append({"block": b, "removed_voxels": len(r_in), "added_voxels": len(a_in),
                                   "weak_voxels": weak, "scattered_voxels": lone,
                                   "reason": f"{n} strong changed voxels < {min_block_voxels}"
                                   + (f"; {weak} voxels with too little evidence" if weak else "")
                                   + (f"; {lone} strong voxels in no change of {min_change_m3:g} m^3" if lone else "")})
        if weak and n >= min_block_voxels:
            plan.held_back.append({"block": b, "weak_voxels": weak,
                                   "reason": f"{weak} voxels seen by one run in fewer than {strong_scans} scans"})
        if lone and n >= min_block_voxels:
            plan.held_back.append({"block": b, "scattered_voxels": lone,
                                   "reason": f"{lone} strong voxels in no coherent change of {min_change_m3:g} m^3 "
                                             "or more"})
    plan.removed = unique_keys(np.concatenate(applied_rm)) if applied_rm else plan.removed
    plan.added = unique_keys(np.concatenate(applied_ad)) if applied_ad else plan.added
    plan.added_owner = dict(zip(ad.tolist(), ad_owner.tolist()))
    return plan


def new_points_by_block(plan: UpdatePlan, results: list) -> dict:
    """block id -> ((M, 3) float64 map-frame points, (M,) float32 intensity) each confirmed block of
    ``plan`` gains from the runs' new points (``offmap_points``): those in the applied added
    voxels, and the revealed ones (module docstring, step 4), each given to the block of its
    nearest keyframe (``plan.added_owner`` for added voxels)."""
    from scipy.spatial import cKDTree

    from blockloc.maps.changes.detect import in_sorted

    out = {b: (np.zeros((0, 3)), np.zeros(0, np.float32)) for b in plan.blocks}
    have = [r for r in results if len(r.offmap_points)]
    if not plan.blocks or not have:
        return out
    pts = np.concatenate([np.asarray(r.offmap_points, np.float64) for r in have])
    inten = np.concatenate([np.asarray(r.offmap_intensity, np.float32) for r in have])
    k = voxel_keys(pts, plan.voxel_m)
    added = np.asarray(plan.added, np.int64)
    owner = np.full(len(pts), None, dtype=object)
    sel = in_sorted(k, added) if len(added) else np.zeros(len(pts), bool)
    owner[sel] = [plan.added_owner.get(int(x)) for x in k[sel]]
    applied = np.union1d(plan.removed, added)
    if plan.reveal_m > 0 and len(applied):
        dynamic = unique_keys(np.concatenate([np.asarray(r.voxels.dynamic, np.int64) for r in results]))
        cand = ~sel & ~in_sorted(k, dynamic) & ~in_sorted(k, np.asarray(plan.removed, np.int64))
        # persistent: the cell hit by reveal_hits scan points or more (the detector thins each scan
        # to about a point per voxel_m / 2 cell, so about as many scans); a walker's cells are hit
        # once or twice
        cell = voxel_keys(pts, plan.voxel_m / 2)
        cells, inv, n = np.unique(cell, return_inverse=True, return_counts=True)
        cand &= n[inv] >= plan.reveal_hits
        centres = (unpack_keys(applied) + 0.5) * plan.voxel_m
        j = np.flatnonzero(cand)
        near = np.isfinite(cKDTree(centres).query(pts[j], distance_upper_bound=plan.reveal_m)[0])
        j = j[near]
        ids, kf = [], []
        for r in results:
            for b, f in r.block_keyframes.items():
                f = np.asarray(f, float).reshape(-1, 3)
                ids += [b] * len(f)
                kf.append(f)
        if len(j) and ids:
            owner[j] = np.asarray(ids, object)[cKDTree(np.concatenate(kf)).query(pts[j])[1]]
    for b in plan.blocks:
        m = owner == b
        if m.any():
            out[b] = (pts[m], inten[m])
            plan.blocks[b]["new_points"] = int(m.sum())
    return out


def rebuild_block(points: np.ndarray, intensity: np.ndarray | None, removed: np.ndarray,
                  new_points: np.ndarray, new_intensity: np.ndarray, voxel_m: float,
                  store_voxel_m: float) -> tuple[np.ndarray, np.ndarray, int]:
    """A block's new (points (N, 3) float64, intensity (N,) float32) and how many of its old points
    it kept: its points outside the ``removed`` voxels (sorted keys at ``voxel_m``) plus
    ``new_points`` (M, 3) filtered at ``store_voxel_m`` (centroids, mean intensity)."""
    from blockloc.voxels import voxel_downsample

    pts = np.asarray(points, np.float64)[:, :3]
    inten = np.zeros(len(pts), np.float32) if intensity is None else np.asarray(intensity, np.float32)
    keep = ~np.isin(voxel_keys(pts, voxel_m), removed) if len(removed) else np.ones(len(pts), bool)
    pts, inten = pts[keep], inten[keep]
    kept = len(pts)
    if len(new_points):
        add, add_i = voxel_downsample(np.asarray(new_points, np.float64), store_voxel_m,
                                      np.asarray(new_intensity, np.float32))
        pts = np.concatenate([pts, add])
        inten = np.concatenate([inten, np.asarray(add_i, np.float32)])
    return pts, inten, kept


def apply_update(map_root: str | Path, plan: UpdatePlan, results: list, *, runs: list[str],
                 out: str | Path | None = None, place_index: Callable[[object], bytes] | None = None) -> dict:
    """Write the plan as a new version of the local store ``map_root`` (or of a copy at ``out``,
    which must not exist). place_index: when blocks changed and the store has a place index,
    called with the new version's :class:`~blockloc.maps.store.MapStore` (staged, not yet
    current) and returning the new index file's bytes (None: the index is left out of the new
    version, with a warning). Returns the version record (with ``version`` and ``path``)."""
    from blockloc.maps.changes import versions
    from blockloc.maps.pcd import encode_pcd
    from blockloc.maps.store import MANIFEST_NAME, entry_stats, open_map

    root = Path(map_root)
    store = open_map(root)
    if store.files.is_remote or store.legacy or store.kind != "block":
        raise MapError(f"{map_root}: map update needs a local block map store with a manifest")
    target = root
    tmp = None
    if out is not None:
        out = Path(out)
        if out.exists():
            raise MapError(f"--out {out}: already exists (choose a new directory)")
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.updating-", dir=out.parent))
        for p in root.iterdir():  # the same bytes: unchanged blocks stay byte-identical
            if p.is_file():
                shutil.copy2(p, tmp / p.name)
            elif p.is_dir() and p.name == versions.VERSIONS_DIR:
                shutil.copytree(p, tmp / p.name)
        target = tmp
    try:
        versions.ensure_history(target)
        number = versions.next_version(target)
        doc = json.loads((target / MANIFEST_NAME).read_text())
        store_voxel = float(store.params.get("voxel_size_m", 0.2))
        by_block_new = new_points_by_block(plan, results)
        changed = []
        for e in doc["entries"]:
            b = e["id"]
            if b not in plan.blocks:
                continue
            pts, inten = store.load(b)
            P, I = by_block_new[b]
            new_pts, new_int, kept = rebuild_block(pts, inten, plan.removed, P, I, plan.voxel_m, store_voxel)
            data = encode_pcd(new_pts, new_int)
            file = f"{b}.v{number}.pcd"
            (target / file).write_bytes(data)
            lo, hi, mean = entry_stats(new_pts)
            e.update({"file": file, "bounds_min": [float(v) for v in lo], "bounds_max": [float(v) for v in hi],
                      "centroid": [float(v) for v in mean], "num_points": int(len(new_pts)),
                      "bytes": len(data), "sha256": hashlib.sha256(data).hexdigest()})
            # points added: in the added voxels and those seen behind what was removed (step 4), so
            # a block can gain points with no voxel added
            plan.blocks[b].update({"points_before": int(len(pts)), "points_after": int(len(new_pts)),
                                   "points_removed": int(len(pts) - kept), "points_added": int(len(new_pts) - kept)})
            changed.append(b)
        extras = doc.get("extras") or {}
        if changed and "place_index.npz" in extras:
            if place_index is None:
                extras.pop("place_index.npz")
                log.warning("map update: no place index builder given, the new version has no place index")
            else:
                from blockloc.maps.files import open_map_files
                from blockloc.maps.store import MapEntry, MapStore

                # the new version's store, before it is current
                staged = MapStore(open_map_files(target), doc["kind"], str(doc.get("frame", "map")),
                                  doc.get("parameters") or {},
                                  [MapEntry.from_dict(d, str(target)) for d in doc["entries"]])
                data = place_index(staged)
                name = f"place_index.v{number}.npz"
                (target / name).write_bytes(data)
                extras["place_index.npz"] = {"file": name, "bytes": len(data),
                                             "sha256": hashlib.sha256(data).hexdigest()}
        if extras:
            doc["extras"] = extras
        record = {"runs": list(runs), "changed_blocks": changed,
                  "blocks": {b: plan.blocks[b] for b in changed}, "held_back": plan.held_back,
                  "grown_voxels": int(plan.grown), "reveal_m": float(plan.reveal_m),
                  "note": "update" if changed else "update (no confirmed change)"}
        number = versions.commit_version(target, doc, record)
        if tmp is not None:
            tmp.rename(out)
            target = out
        return {"version": number, "path": str(target), **record}
    except BaseException:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
        raise
