"""Block maps (Feng et al., ICRA 2024, Algorithm 1): stitch mapping keyframes into blocks.

A block collects keyframes until a keyframe lies farther than S (``block_size_m``, 3D distance)
from the block's FIRST keyframe; that closing keyframe is kept in the closed block and also starts
the next one, so adjacent blocks share a scan (spatial continuity). A closed block is voxel-
downsampled and its centroid looked up in a KD-tree over the centroids of the blocks so far
(3D distance d to the nearest):

- d >= 0.5 S: a new block;
- 0.1 S < d < 0.5 S: merged into the nearest block, whose centroid is renewed;
- d <= 0.1 S: skipped (the route repeats an existing block).

Unlike the released code (YixFeng/Block_Map_from_Groundtruth) the closing keyframe is not dropped,
the second block is checked against the first like every other, and the distance is 3D (the
released code sums x, y and the homogeneous 1 of the pose). The last, partial block is never
dropped (the released code keeps it only above a size heuristic): if its keyframes stay within
0.5 S of its first one it is appended to the block it continues (event 'tail'), otherwise it goes
through the rule above.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable

import numpy as np

from blockloc.errors import MapError
from blockloc.maps.mapping import Keyframe
from blockloc.voxels import voxel_downsample

log = logging.getLogger(__name__)

#: A candidate block's keyframes are summed by voxel in runs of this many (counted from the
#: candidate's first keyframe) and the runs' sums added in order: the in-memory builder and the
#: build plan (one task per run, :mod:`blockloc.maps.build_plan`) cut the same runs, so they add
#: the same numbers in the same order and write the same bytes. A fixed number, never derived
#: from the number of workers; memory follows one run's raw points and the block's area.
KEYFRAMES_PER_RUN = 8


@dataclass
class Block:
    """A finished block: points (N, 3) float32 map frame (voxel-filtered), intensity (N,) float32,
    centroid (3,) float64 = mean of the points, and the frame indices of its keyframes."""

    points: np.ndarray
    intensity: np.ndarray | None
    centroid: np.ndarray
    keyframes: list[int] = field(default_factory=list)


@dataclass
class BlockEvent:
    """What happened to a closed candidate block: 'new', 'merge', 'skip' or 'tail' (the last,
    short partial block appended to the block it continues).

    block: the block it became / merged into / was skipped for (nearest); distance_m: distance of
    its centroid to the nearest existing centroid (inf for the first block)."""

    action: str
    block: int
    distance_m: float
    keyframes: list[int]


# --------------------------------------------------------------------------- the parts of Algorithm 1
# Algorithm 1 splits into three parts that the in-memory builder below and the distributed build
# plan (blockloc.maps.build_plan) share, so both give the same blocks:
# - CandidateSegmenter: which keyframes form each candidate block (positions only);
# - VoxelAccumulator / merge_block_points: a candidate's points and a merge (points only);
# - BlockLedger: new / merge / skip / tail from centroids only.


#: Runs' voxel-sum records a :class:`VoxelAccumulator` holds before adding them up (192 MB).
PENDING_RECORDS = 4_000_000


class VoxelAccumulator:
    """The points of one candidate block as its keyframes arrive (map frame, metres).

    Keyframes are summed by voxel (``voxel_size_m``; <= 0: none) in runs of
    ``keyframes_per_run`` (:func:`keyframe_run_sums`), and each run's sums are added to the
    block's (:meth:`add_run`, the same records a build-plan task computes elsewhere).
    :meth:`result` gives the voxel centroids: the mean of every point of the voxel, whatever the
    runs. The bytes depend only on the keyframes, their order and the run length.
    """

    def __init__(self, voxel_size_m: float, keyframes_per_run: int = KEYFRAMES_PER_RUN):
        self.voxel_size_m = float(voxel_size_m)
        self.keyframes_per_run = int(keyframes_per_run)
        if self.keyframes_per_run < 1:
            raise MapError(f"keyframes_per_run {keyframes_per_run!r}: expected an integer >= 1")
        self._run: list[tuple[np.ndarray, np.ndarray | None]] = []
        self._sums: np.ndarray | None = None
        self._pending: list[np.ndarray] = []  # runs' records not added to _sums yet
        self._pending_len = 0
        self._intensity = True  # every keyframe so far had intensity

    def add(self, points: np.ndarray, intensity: np.ndarray | None = None) -> None:
        """One keyframe's points (N, 3) map frame and intensity (N,) or None."""
        self._run.append((points, intensity))
        if len(self._run) >= self.keyframes_per_run:
            self._close_run()

    def add_run(self, records: np.ndarray, has_intensity: bool) -> None:
        """A run's voxel sums (:data:`~blockloc.maps.grid_tiles.VOXEL_SUM` records of
        :func:`keyframe_run_sums`), added after the runs before it."""
        self._intensity = self._intensity and bool(has_intensity)
        self._pending.append(records)
        self._pending_len += len(records)
        if self._pending_len >= PENDING_RECORDS:
            self._merge()

    def _merge(self) -> None:
        """The pending runs added to the sums in one merge. Adding them one merge at a time gives
        the same bytes (each voxel's sums are added in the same order, from 0), but every merge
        re-sorts the whole block so far, so a candidate of R runs cost R passes over the block
        (12 synthetic runs of 300k points: 3.3-6.7 s of CPU one at a time, 0.5-1.9 s in one)."""
        from blockloc.maps.grid_tiles import merge_voxel_sums

        parts = ([] if self._sums is None else [self._sums]) + self._pending
        self._pending, self._pending_len = [], 0
        if parts:
            self._sums = parts[0] if len(parts) == 1 else merge_voxel_sums(parts, self.voxel_size_m)

    def result(self) -> tuple[np.ndarray, np.ndarray | None]:
        """Voxel centroids (M, 3) float32, ascending voxel-key order, and mean intensity (M,)
        float32 (None when a keyframe had none)."""
        self._close_run()
        self._merge()
        rec = self._sums
        if rec is None or len(rec) == 0:
            return np.zeros((0, 3), np.float32), None
        n = rec["count"].astype(np.float64)
        pts = (rec["sum"][:, :3] / n[:, None]).astype(np.float32)
        inten = (rec["sum"][:, 3] / n).astype(np.float32) if self._intensity else None
        return pts, inten

    def _close_run(self) -> None:
        if self._run:
            rec, has_intensity = keyframe_run_sums(self._run, self.voxel_size_m)
            self._run = []
            self.add_run(rec, has_intensity)


def keyframe_run_sums(clouds, voxel_size_m: float) -> tuple[np.ndarray, bool]:
    """A run of keyframes summed by voxel: ``clouds`` [(points (N, 3) map frame, metres,
    intensity (N,) or None)] in order. Points are rounded to float32 (what a block stores) before
    they are binned and summed in float64; non-finite points are dropped. Returns (records
    (M,) :data:`~blockloc.maps.grid_tiles.VOXEL_SUM`, ascending key order (input order when
    ``voxel_size_m <= 0``), whether every keyframe had intensity)."""
    from blockloc.maps.grid_tiles import voxel_sums

    has_intensity = all(i is not None for _, i in clouds)
    pts = [np.asarray(p, np.float32).reshape(-1, 3) for p, _ in clouds]
    inten = [np.zeros(len(p), np.float32) if i is None else np.asarray(i, np.float32).reshape(-1)
             for p, (_, i) in zip(pts, clouds)]
    pts = np.concatenate(pts).astype(np.float64) if pts else np.zeros((0, 3))
    inten = np.concatenate(inten).astype(np.float64) if inten else np.zeros(0)
    finite = np.isfinite(pts).all(axis=1)
    if not finite.all():
        pts, inten = pts[finite], inten[finite]
    return voxel_sums(pts, inten, voxel_size_m), has_intensity


def merge_block_points(points: np.ndarray, intensity: np.ndarray | None, more: np.ndarray,
                       more_intensity: np.ndarray | None, voxel_size_m: float
                       ) -> tuple[np.ndarray, np.ndarray | None]:
    """A block merged with a candidate: the voxel filter of both clouds together (float32 points
    (N, 3), map frame; intensity None unless both have it)."""
    inten = None if (intensity is None or more_intensity is None) else np.concatenate(
        [intensity, more_intensity])
    merged, inten = voxel_downsample(np.concatenate([points, more]), voxel_size_m, inten)
    return merged.astype(np.float32), inten


def block_centroid(points: np.ndarray) -> np.ndarray:
    """(3,) float64 mean of a block's float32 points (what the KD-tree and the manifest hold)."""
    return np.asarray(points).astype(np.float64).mean(axis=0)


@dataclass
class Candidate:
    """A closed candidate block: its keyframes' keys in order; ``short``: the drive's last,
    partial block, whose keyframes all lie within 0.5 S of its first (a tail candidate)."""

    keys: list[int]
    short: bool = False


class CandidateSegmenter:
    """Cut one drive's keyframes into candidate blocks from their positions alone.

    A candidate closes at the first keyframe farther than S (3D) from its first keyframe; that
    keyframe is also the first of the next candidate. :meth:`finish` returns the last, partial
    candidate unless it holds only that carried keyframe.
    """

    def __init__(self, block_size_m: float):
        self.block_size_m = float(block_size_m)
        self._reset()

    def _reset(self) -> None:
        self._first: np.ndarray | None = None
        self._keys: list[int] = []
        self._positions: list[np.ndarray] = []
        self._carried: int | None = None

    def add(self, key: int, position: np.ndarray) -> Candidate | None:
        """One keyframe (``key``, sensor ``position`` (3,), map frame): the candidate it closes,
        or None."""
        position = np.asarray(position, np.float64).reshape(3)
        if self._first is None:
            self._first = position
        self._keys.append(key)
        self._positions.append(position)
        if np.linalg.norm(position - self._first) <= self.block_size_m:
            return None
        closed = Candidate(self._keys)
        self._first, self._keys, self._positions, self._carried = position, [key], [position], key
        return closed

    def finish(self) -> Candidate | None:
        """The drive's last candidate (None if it holds only the carried keyframe); resets."""
        keys, first, positions = self._keys, self._first, self._positions
        carried_only = len(keys) == 1 and self._carried == keys[0]
        self._reset()
        if not keys or carried_only:
            return None
        span = max(np.linalg.norm(p - first) for p in positions)
        return Candidate(keys, short=bool(span < 0.5 * self.block_size_m))


class BlockLedger:
    """Algorithm 1's decisions on closed candidates, from centroids alone (module docstring).

    Holds each block's centroid (3,) float64 and keyframe keys, the keys each block already
    covered (skips) and the events. A block whose merge is still being computed elsewhere is
    *held*: its centroid is unknown but lies in a box (the union of the bounds of the block and
    the candidate merged into it: a voxel centroid lies in the hull of its points); a decision
    waits for a held block (``resolve``) only when that box is as close as the nearest known
    centroid, so the decision is the same as if every centroid were known.
    """

    def __init__(self, block_size_m: float):
        if not block_size_m > 0:
            raise MapError(f"block size {block_size_m!r} m: expected a positive number")
        self.block_size_m = float(block_size_m)
        self.centroids: list[np.ndarray] = []
        self.keys: list[list[int]] = []
        self.skipped_into: dict[int, list[int]] = {}
        self.events: list[BlockEvent] = []
        self.held: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self._last_target: int | None = None  # block the previous candidate went to

    def start_drive(self) -> None:
        """A new drive starts: its first short candidate continues no block of an earlier one."""
        self._last_target = None

    def decide(self, keys: list[int], centroid: np.ndarray, short: bool = False,
               resolve=None) -> BlockEvent:
        """The event of a candidate with ``keys`` and voxel-filtered centroid (3,); records it.

        For 'merge' and 'tail' the caller computes the merged block and calls :meth:`renew`
        (or :meth:`hold` until it is known). ``resolve(blocks)``: called with held blocks whose
        centroids this decision needs; it must :meth:`renew` them.
        """
        centroid = np.asarray(centroid, np.float64).reshape(3)
        keys = list(keys)
        S = self.block_size_m
        if not self.centroids:
            return self._new(keys, centroid, np.inf)
        if short and self._last_target is not None:
            j = self._last_target
            self._wait([j], resolve)
            return self._merge(j, keys, float(np.linalg.norm(centroid - self.centroids[j])), "tail")
        d, j = self._nearest(centroid, resolve)
        if d >= 0.5 * S:
            return self._new(keys, centroid, d)
        if d > 0.1 * S:
            return self._merge(j, keys, d, "merge")
        self._last_target = j
        self.skipped_into.setdefault(j, []).extend(keys)
        ev = BlockEvent("skip", j, d, keys)
        self.events.append(ev)
        log.info("keyframes %s..%s skipped: block %03d already covers them (%.1f m)",
                 keys[0], keys[-1], j, d)
        return ev

    def renew(self, block: int, centroid: np.ndarray) -> None:
        """The centroid (3,) of ``block`` after a merge."""
        self.centroids[block] = np.asarray(centroid, np.float64).reshape(3)
        self.held.pop(block, None)

    def hold(self, block: int, lo: np.ndarray, hi: np.ndarray) -> None:
        """``block``'s merge is being computed; its centroid lies in the box [lo, hi] (3,)."""
        self.held[block] = (np.asarray(lo, np.float64), np.asarray(hi, np.float64))

    def _wait(self, blocks, resolve) -> None:
        blocks = [j for j in blocks if j in self.held]
        if blocks:
            if resolve is None:
                raise MapError(f"blocks {blocks}: merged centroids unknown and no way to wait")
            resolve(blocks)
            if any(j in self.held for j in blocks):
                raise MapError(f"blocks {blocks}: still held after resolving")

    def _nearest(self, centroid: np.ndarray, resolve) -> tuple[float, int]:
        from scipy.spatial import cKDTree

        while True:
            known = [k for k in range(len(self.centroids)) if k not in self.held]
            d, j = np.inf, -1
            if known:
                d, i = cKDTree(np.array([self.centroids[k] for k in known])).query(centroid)
                d, j = float(d), known[int(i)]
            near = [k for k, (lo, hi) in self.held.items()
                    if np.linalg.norm(centroid - np.clip(centroid, lo, hi)) <= d]
            if not near:
                return d, j
            self._wait(near, resolve)

    def _new(self, keys, centroid, d) -> BlockEvent:
        self.centroids.append(centroid)
        self.keys.append(list(keys))
        j = len(self.centroids) - 1
        self._last_target = j
        ev = BlockEvent("new", j, d, keys)
        self.events.append(ev)
        return ev

    def _merge(self, j, keys, d, action) -> BlockEvent:
        have = set(self.keys[j])
        self.keys[j].extend(k for k in keys if k not in have)
        self._last_target = j
        ev = BlockEvent(action, j, d, keys)
        self.events.append(ev)
        log.info("keyframes %s..%s %s into block %03d (centroid %.1f m away)", keys[0], keys[-1],
                 "merged" if action == "merge" else "appended", j, d)
        return ev

    def covered_keys(self, block: int) -> list[int]:
        """Keys of the keyframes ``block`` was built from, then those it covered (skips)."""
        return list(self.keys[block]) + self.skipped_into.get(block, [])

    def event_counts(self) -> dict[str, int]:
        return {a: sum(e.action == a for e in self.events) for a in ("new", "merge", "skip", "tail")}


class BlockMapBuilder:
    """Streaming Algorithm 1 in memory: ``add(keyframe)`` for each keyframe in time order, then
    ``finish()`` (:meth:`end_drive` between drives of a multi-session map).

    block_size_m: S, metres. voxel_size_m: block voxel filter (<= 0: none). The distributed
    build (:mod:`blockloc.maps.build_plan`) runs the same parts as tasks.
    """

    def __init__(self, block_size_m: float = 100.0, voxel_size_m: float = 0.2):
        self._ledger = BlockLedger(block_size_m)
        self.block_size_m = self._ledger.block_size_m
        self.voxel_size_m = float(voxel_size_m)
        self._segmenter = CandidateSegmenter(self.block_size_m)
        self._open = VoxelAccumulator(self.voxel_size_m)
        self.blocks: list[Block] = []
        self.keyframe_positions: list[np.ndarray] = []
        self._position_of: dict[int, np.ndarray] = {}  # keyframe index -> sensor position
        self._finished = False

    @property
    def events(self) -> list[BlockEvent]:
        return self._ledger.events

    @property
    def skipped_into(self) -> dict[int, list[int]]:
        """block -> keyframes it already covered (skipped candidates)."""
        return self._ledger.skipped_into

    def add(self, index: int, position: np.ndarray, points_map: np.ndarray,
            intensity: np.ndarray | None = None) -> None:
        """One keyframe: frame ``index``, sensor ``position`` (3,) and points (N, 3), map frame."""
        if self._finished:
            raise MapError("block map builder already finished")
        position = np.asarray(position, np.float64).reshape(3)
        self.keyframe_positions.append(position)
        self._position_of[index] = position
        self._open.add(points_map, intensity)
        closed = self._segmenter.add(int(index), position)
        if closed is not None:
            self._close(closed)
            self._open.add(points_map, intensity)  # the closing keyframe also opens the next block

    def end_drive(self) -> None:
        """Close the current drive's last candidate; the next keyframes start a new drive."""
        tail = self._segmenter.finish()
        if tail is not None:
            self._close(tail)
        self._open = VoxelAccumulator(self.voxel_size_m)
        self._ledger.start_drive()

    def finish(self) -> list[Block]:
        """Close the last block (if it holds more than the carried-over keyframe); return blocks."""
        if not self._finished:
            self.end_drive()
            self._finished = True
        return self.blocks

    def keyframe_positions_of(self, block: int) -> np.ndarray:
        """(K, 3) sensor positions of the keyframes block ``block`` was built from or already
        covered (skipped ones): where the block's map is good. Map frame, metres."""
        return np.array([self._position_of[k] for k in self._ledger.covered_keys(block)
                         if k in self._position_of], np.float64).reshape(-1, 3)

    def _close(self, candidate: Candidate) -> None:
        pts, inten = self._open.result()
        self._open = VoxelAccumulator(self.voxel_size_m)
        keys = candidate.keys
        if len(pts) == 0:
            log.debug("keyframes %s: no points, no block", keys)
            return
        ev = self._ledger.decide(keys, block_centroid(pts), candidate.short)
        if ev.action == "new":
            self.blocks.append(Block(pts, inten, self._ledger.centroids[ev.block],
                                     self._ledger.keys[ev.block]))
            log.info("block %03d: %d keyframes, %d points", ev.block, len(keys), len(pts))
        elif ev.action in ("merge", "tail"):
            b = self.blocks[ev.block]
            b.points, b.intensity = merge_block_points(b.points, b.intensity, pts, inten,
                                                       self.voxel_size_m)
            b.centroid = block_centroid(b.points)
            self._ledger.renew(ev.block, b.centroid)


def build_block_map(keyframes: Iterable[Keyframe | tuple], *, block_size_m: float = 100.0,
                    voxel_size_m: float = 0.2, out: str | Path | None = None,
                    params: dict | None = None, overwrite: bool = False, frame: str = "map"):
    """Block map from keyframes whose points are already in the map frame.

    keyframes: :class:`~blockloc.maps.mapping.Keyframe` objects, or tuples
    ``(T_map_sensor (4, 4), points_map (N, 3)[, intensity (N,)])`` in time order.
    Returns the :class:`BlockMapBuilder` (blocks, events) when ``out`` is None, else the opened
    :class:`~blockloc.maps.store.MapStore` written atomically to ``out``.
    """
    builder = BlockMapBuilder(block_size_m, voxel_size_m)
    count = 0
    for k, kf in enumerate(keyframes):
        if isinstance(kf, Keyframe):
            builder.add(kf.index, kf.position, kf.points_map, kf.intensity)
        else:
            T, pts, *rest = kf
            builder.add(k, np.asarray(T)[:3, 3], pts, rest[0] if rest else None)
        count += 1
    if count == 0:
        raise MapError("no keyframes to build a block map from (empty session?)")
    builder.finish()
    if out is None:
        return builder
    return write_block_map(builder, out, params=params, overwrite=overwrite, frame=frame)


def write_block_map(builder: BlockMapBuilder, out: str | Path, *, params: dict | None = None,
                    overwrite: bool = False, frame: str = "map"):
    """Write the builder's blocks as a block store (``%03d.pcd`` + CentroidCloud + manifest)."""
    from blockloc.maps.store import MapWriter

    p = {"block_size_m": builder.block_size_m, "voxel_size_m": builder.voxel_size_m,
         "num_keyframes": len(builder.keyframe_positions),
         "events": {a: sum(e.action == a for e in builder.events)
                    for a in ("new", "merge", "skip", "tail")},
         **(params or {})}
    with MapWriter(out, "block", frame=frame, params=p, overwrite=overwrite) as w:
        for i, b in enumerate(builder.blocks):
            w.add(f"{i:03d}", b.points, b.intensity, file=f"{i:03d}.pcd", centroid=b.centroid,
                  keyframes=builder.keyframe_positions_of(i))
        return w.commit()
