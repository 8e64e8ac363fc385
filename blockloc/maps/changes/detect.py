"""Change detection: per-voxel occupancy evidence from many scans against a prior map.

Pure core on numpy arrays (no files, no config). Frame: the map's, metres.

Every voxel (edge ``voxel_m``) keeps two counts over the scans of a run: ``n_hit`` (scans with an
endpoint in it) and ``n_free`` (scans whose rays pass through it without ending in it or next to
it). Its log-odds of being occupied is ``L = n_hit * l_occ + n_free * l_free``: one update per
voxel per scan, so a single scan never decides (a voxel needs ``min_scans`` scans of evidence
and ``|L|`` past a threshold). Free space is marked only by the part of each ray more than
``ray_margin_m`` short of its endpoint, and never next to one of that scan's hits: a slightly wrong
pose, a grazing ray over the ground or a mixed pixel does not carve the map (the same idea as
DUFOMap's localization-error dilation). Inside the map's voxels both tests are made on fine cells
(``voxel_m / 2.5``): a ray counts through a map voxel only where it crosses one of the voxel's
occupied fine cells, more than one fine cell from the scan's hits (a ray 0.3 m above the ground
passes through the ground's 0.5 m voxel without passing through the ground, and a parked car's
lowest metre, a voxel from the ground hits, stays open to evidence); off the map, a voxel next
to (26 neighbours) a hit of the scan is spared.

Rays that end on the ground stop marking free space further short of their endpoint, the more
so the flatter they run (:func:`ray_margins`): over its last metres a grazing ray runs a few
centimetres above the ground and would carve it.

Classes:

- **removed**: a map voxel rays now pass through (``L <= -removed_logodds``, ``n_free >=
  min_scans``);
- **added**: a voxel holding, in ``min_scans`` scans or more, **new** points (more than one fine
  cell from every map point) in fine cells the mapping day had in clear sight (a straight line
  from one of the nearest mapping keyframes, or from the nearest in one of eight directions,
  crosses no map cell: :func:`seen_by_keyframes`), with ``n_new * l_occ + n_free * l_free >= added_logodds``: structure where the mapping
  day saw free space, not merely a place it never saw; decided on points, not whole voxels, so
  the part of a new object in the ground's voxel counts;
- **dynamic**: a voxel off the map (and its neighbours) with new points in some scans and seen
  free in others, the free evidence outweighing: a pedestrian, a passing car (also ground a
  removed object had hidden, crossed just above it: dynamic voxels are only reported).

Rays are walked by sampling every ``voxel_m / 2`` (numpy, a chunk of rays at a time): that can
skip a voxel's corner, which only costs evidence, never adds it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from blockloc.geometry import tangent_basis

#: voxel key packing: 21 bits per axis (signed, +- 2^20 voxels: +-524 km at 0.5 m)
_BITS = 21
_OFF = 1 << (_BITS - 1)
_MASK = (1 << _BITS) - 1


def pack_keys(ijk: np.ndarray) -> np.ndarray:
    """(N, 3) int voxel indices -> (N,) int64 keys (order-preserving per axis is not promised)."""
    ijk = np.asarray(ijk, dtype=np.int64) + _OFF
    return (ijk[:, 0] << (2 * _BITS)) | (ijk[:, 1] << _BITS) | ijk[:, 2]


def unpack_keys(keys: np.ndarray) -> np.ndarray:
    """(N,) int64 keys -> (N, 3) int64 voxel indices."""
    keys = np.asarray(keys, dtype=np.int64)
    return np.stack([(keys >> (2 * _BITS)) & _MASK, (keys >> _BITS) & _MASK, keys & _MASK], axis=1) - _OFF


def voxel_keys(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """(N,) int64 keys of the voxels of (N, 3) points (metres)."""
    pts = np.asarray(points)
    if pts.dtype != np.float32:  # float32 is read as it is: widened exactly, as astype(float64) does
        pts = np.asarray(pts, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] < 3:
        return pack_keys(np.floor(np.asarray(pts, np.float64)[:, :3] / voxel_m).astype(np.int64))
    from blockloc.maps._raycast_kernels import point_keys

    out = np.empty(len(pts), np.int64)  # compiled: one pass, no (N, 3) temporaries
    point_keys(np.ascontiguousarray(pts), float(voxel_m), out)
    return out


_NEIGHBOURS = np.array([(a, b, c) for a in (-1, 0, 1) for b in (-1, 0, 1) for c in (-1, 0, 1)], dtype=np.int64)


def unique_keys(keys: np.ndarray) -> np.ndarray:
    """Sorted unique int64 ``keys`` (any shape, flattened): ``np.unique(keys)``, by a sort. numpy
    2.4's plain ``np.unique`` hashes first: ~40x slower on 400k voxel keys, and the detector calls
    it on every scan's keys."""
    keys = np.sort(np.asarray(keys, np.int64).ravel())
    return keys[np.r_[True, keys[1:] != keys[:-1]]] if len(keys) else keys


def dilate_keys(keys: np.ndarray) -> np.ndarray:
    """Sorted unique keys of ``keys`` and their 26 neighbours. One axis at a time, each a linear
    merge of the sorted keys shifted by -1, 0, +1 along it (a shift of one voxel is a shift of the
    packed key by the axis' unit while the index stays inside its 21 bits): sorting 27 copies
    took ~24 ms a scan on the small world."""
    from blockloc.maps._raycast_kernels import merge_shifted

    out = unique_keys(keys)
    for unit in (1, 1 << _BITS, 1 << (2 * _BITS)):
        out = merge_shifted(out, np.int64(unit))
    return out


def in_sorted(keys: np.ndarray, table: np.ndarray) -> np.ndarray:
    """(N,) bool: keys found in the sorted unique ``table`` (a binary search: ``np.isin`` sorts the
    table again on every call)."""
    if not len(table):
        return np.zeros(len(keys), bool)
    j = np.minimum(np.searchsorted(table, keys), len(table) - 1)
    return table[j] == keys


_in_sorted = in_sorted


def near_sorted(keys: np.ndarray, table: np.ndarray) -> np.ndarray:
    """(N,) bool: the cell of each key or one of its 26 neighbours is in the sorted unique
    ``table`` (the same cell size): within one cell of what the table holds."""
    from blockloc.maps._raycast_kernels import near_any

    keys = np.ascontiguousarray(keys, dtype=np.int64).ravel()
    out = np.zeros(len(keys), bool)
    if not len(keys) or not len(table):
        return out
    near_any(keys, np.ascontiguousarray(table, np.int64), out)  # compiled: no (N, 27) keys made
    return out


def ray_free_keys(origin: np.ndarray, endpoints: np.ndarray, voxel_m: float, margin_m,
                  chunk: int = 4096, fine: tuple | None = None, hit_fine: np.ndarray | None = None,
                  only: np.ndarray | None = None) -> np.ndarray:
    """Sorted unique keys of the voxels the rays ``origin`` -> each endpoint pass through, up to
    ``margin_m`` (a number or (N,) per ray) short of the endpoint. origin: (3,); endpoints:
    (N, 3); metres, one frame.

    fine: (map_keys, fine_m, fine_keys) or None. With it, a ray counts through a map voxel (its
    key in the sorted ``map_keys``) only where it crosses one of the voxel's occupied fine cells
    (edge ``fine_m``, sorted ``fine_keys``): a ray over the ground a few centimetres below it in
    the same voxel did not pass through what the map holds there.

    The compiled :func:`blockloc.maps.raycast.free_voxels` gives the same voxels (the same
    samples and float operations) in a twentieth of the time; the sorting below runs only where
    its grid would be too big (a stray far endpoint)."""
    from blockloc.maps.raycast import free_voxels, unit_rays

    ijk = free_voxels(origin, endpoints, voxel_m, margin_m, fine=fine, hit_fine=hit_fine)
    if ijk is not None:
        keys = np.sort(pack_keys(ijk))
        return keys[_in_sorted(keys, only)] if only is not None else keys
    origin, d, u, usable = unit_rays(origin, endpoints, margin_m)
    if not len(d):
        return np.zeros(0, dtype=np.int64)
    step = voxel_m / 2.0
    out = []
    for s in range(0, len(u), chunk):
        uu, ll = u[s:s + chunk], usable[s:s + chunk]
        n = int(np.ceil(ll.max() / step))
        t = (np.arange(n) + 0.5) * step
        ok = t[None, :] < ll[:, None]  # (R, n)
        pts = origin + uu[:, None, :] * t[None, :, None]
        pts = pts[ok]
        keys = voxel_keys(pts, voxel_m)
        if fine is not None:
            map_keys, fine_m, fine_keys = fine
            on_map = _in_sorted(keys, map_keys)
            idx = np.flatnonzero(on_map)
            fk = voxel_keys(pts[idx], fine_m)
            through = _in_sorted(fk, fine_keys)
            if hit_fine is not None and through.any():
                t_idx = np.flatnonzero(through)
                through[t_idx[near_sorted(fk[t_idx], hit_fine)]] = False
            keep = ~on_map
            keep[idx[through]] = True
            keys = keys[keep]
        if only is not None:
            keys = keys[_in_sorted(keys, only)]
        out.append(unique_keys(keys))
    return unique_keys(np.concatenate(out))


def without_lowest(fine_keys: np.ndarray, up: np.ndarray) -> np.ndarray:
    """The sorted fine keys less the lowest occupied cell of each vertical column (``up``: (3,)
    unit vector against gravity, along a map axis): the ground's surface, which rays may not
    carve. Far from the sensor a scan's ground hits lie metres apart and a ray running low over
    the ground between them, or over a slope rising ahead of it, would otherwise thin the ground
    out of the map; a removed object's cells above the ground stay open to evidence."""
    fine_keys = np.asarray(fine_keys, np.int64)
    up = np.asarray(up, float).reshape(3)
    axis = int(np.argmax(np.abs(up)))
    if not len(fine_keys) or abs(up[axis]) < 0.9:  # gravity not along an axis: nothing spared
        return fine_keys
    if _sorted_columns(fine_keys, axis):
        # the sorted keys hold each column's cells together, bottom first or last: no sort
        keep = np.ones(len(fine_keys), bool)
        keep[_column_lowest(fine_keys, up[axis] > 0)[0]] = False
        return fine_keys[keep]
    ijk = unpack_keys(fine_keys)
    h = ijk[:, axis] * np.sign(up[axis])  # height in cells
    other = [a for a in range(3) if a != axis]
    col = pack_keys(np.c_[ijk[:, other], np.zeros(len(ijk), np.int64)])
    order = np.lexsort((h, col))
    first = np.ones(len(order), bool)
    first[1:] = col[order][1:] != col[order][:-1]
    keep = np.ones(len(fine_keys), bool)
    keep[order[first]] = False
    return fine_keys[keep]


def _sorted_columns(keys: np.ndarray, axis: int) -> bool:
    """The sorted unique packed ``keys`` list each vertical column's cells together in height
    order: the vertical ``axis`` is the packing's last (fastest) one."""
    return axis == 2 and len(keys) > 0 and bool((keys[1:] > keys[:-1]).all())


def _column_lowest(keys: np.ndarray, up_positive: bool) -> tuple[np.ndarray, np.ndarray]:
    """(indices of each column's lowest cell, indices of each column's first key) in the sorted
    keys of :func:`_sorted_columns` (a column: the same first two indices); the lowest is the
    column's first cell when up is along +z, its last when along -z."""
    col = keys >> _BITS
    first = np.flatnonzero(np.r_[True, col[1:] != col[:-1]])
    return (first if up_positive else np.r_[first[1:] - 1, len(keys) - 1]), first


def ground_band(fine_keys: np.ndarray, up: np.ndarray, band_cells: int) -> np.ndarray:
    """The sorted fine keys at most ``band_cells`` cells above the lowest occupied cell of their
    vertical column (``up``: (3,) unit vector against gravity, along a map axis): the ground's
    surface with its noise (a laser's angle error puts a stray cell below the surface, and the
    surface itself one or two cells higher). Empty when gravity is not along an axis."""
    fine_keys = np.asarray(fine_keys, np.int64)
    up = np.asarray(up, float).reshape(3)
    axis = int(np.argmax(np.abs(up)))
    if not len(fine_keys) or abs(up[axis]) < 0.9:
        return np.zeros(0, np.int64)
    if _sorted_columns(fine_keys, axis):
        # the sorted keys hold each column's cells together, in height order: its lowest is the
        # run's first (up along +axis) or last cell, no unique over the columns needed
        h = ((fine_keys & _MASK) - _OFF) * int(np.sign(up[axis]))
        lowest, first = _column_lowest(fine_keys, up[axis] > 0)
        low = np.repeat(h[lowest], np.diff(np.r_[first, len(fine_keys)]))
        return fine_keys[h - low <= band_cells]
    ijk = unpack_keys(fine_keys)
    h = ijk[:, axis] * int(np.sign(up[axis]))
    other = [a for a in range(3) if a != axis]
    col, inv = np.unique(pack_keys(np.c_[ijk[:, other], np.zeros(len(ijk), np.int64)]), return_inverse=True)
    low = np.full(len(col), np.iinfo(np.int64).max)
    np.minimum.at(low, inv, h)
    return fine_keys[h - low[inv] <= band_cells]


def ray_margins(origin: np.ndarray, points: np.ndarray, up: np.ndarray, margin_m: float,
                ground_drop_m: float = 0.7, ground_tol_m: float = 0.3) -> np.ndarray:
    """(N,) how far short of its endpoint each ray stops marking free space, metres.

    A ray that ends on the ground (its endpoint ``ground_drop_m`` or more below the sensor) runs
    just above the ground over its last metres: at an elevation e it is within ``ground_tol_m``
    of the ground for ``ground_tol_m / sin|e|`` metres, and would carve the ground voxels it
    grazes. Those rays stop that far short (at least ``margin_m``); other rays ``margin_m``.
    """
    v = np.asarray(points, np.float64)[:, :3] - np.asarray(origin, np.float64).reshape(3)
    h = v @ np.asarray(up, np.float64)
    r = np.maximum(np.linalg.norm(v, axis=1), 1e-9)
    grazing = ground_tol_m / np.maximum(np.abs(h) / r, 0.03)
    return np.where(h < -ground_drop_m, np.maximum(margin_m, grazing), margin_m)


@dataclass
class Evidence:
    """Per-voxel scan counts (see the module docstring), merged a batch of scans at a time.

    keys: sorted (V,) int64; n_hit, n_free: (V,) int32. ``scans``: scans added; ``rejected``:
    scans a consistency gate dropped (see :meth:`add_scan`). With ``fine`` (the map's voxels and
    fine cells, :func:`ray_free_keys`), each scan's **new** points (none of the map's fine cells
    within one fine cell: 0.2-0.4 m off every map point at the default sizes) are kept as fine
    keys per scan for :meth:`new_counts`; without it every point is new.
    """

    voxel_m: float
    margin_m: float = 1.0
    fine: tuple | None = None  # (map_keys, fine_m, fine_keys): see :func:`ray_free_keys`
    #: sorted fine keys rays may count through (None: all of ``fine``'s; :func:`without_lowest`)
    carvable: np.ndarray | None = None
    #: sorted fine keys of the ground's surface (:func:`ground_band`), or None (not known)
    ground: np.ndarray | None = None
    #: (3,) unit vector against gravity in the map frame, or None (not known): the first
    #: :meth:`add_scan` given one sets it (the ground-sheet rule of :func:`classify` needs it)
    up: np.ndarray | None = None
    keys: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    n_hit: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))
    n_free: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))
    scans: int = 0
    rejected: int = 0
    #: per scan: (sorted unique fine keys of its new points, (same length) the voxel of each)
    new_fine: list = field(default_factory=list)
    _pending_hit: list = field(default_factory=list)
    _pending_free: list = field(default_factory=list)

    def add_scan(self, origin: np.ndarray, points_map: np.ndarray, up: np.ndarray | None = None) -> np.ndarray:
        """One scan: sensor origin (3,) and its points (N, 3), both in the map frame; up: (3,)
        unit vector against gravity, or None (no ground-ray margin, see :func:`ray_margins`).
        Returns (N,) bool: the new points (class docstring)."""
        if up is not None and self.up is None:
            self.up = np.asarray(up, np.float64).reshape(3)
        hits = unique_keys(voxel_keys(points_map, self.voxel_m))
        margin = self.margin_m if up is None else ray_margins(origin, points_map, up, self.margin_m)
        if self.fine is not None:
            map_keys, fine_m, fine_keys = self.fine
            pf = voxel_keys(points_map, fine_m)
            new = ~near_sorted(pf, fine_keys)
            hit_fine = unique_keys(pf)
        else:
            map_keys, fine_m = np.zeros(0, np.int64), self.voxel_m / 2.5
            new = np.ones(len(points_map), bool)
            pf = voxel_keys(points_map, fine_m)
            hit_fine = None
        through = self.fine
        if self.fine is not None and self.carvable is not None:
            through = (map_keys, fine_m, self.carvable)
        free = ray_free_keys(origin, points_map, self.voxel_m, margin, fine=through, hit_fine=hit_fine)
        # next to a hit: spared off the map at the voxel level; inside the map's voxels the fine
        # cells near the hits were spared already (ray_free_keys), so the metre above the ground
        # stays open to evidence
        near_hit = np.isin(free, dilate_keys(hits), assume_unique=True) & ~_in_sorted(free, map_keys)
        self._pending_hit.append(hits)
        self._pending_free.append(free[~near_hit])
        cells, first = np.unique(pf[new], return_index=True)
        self.new_fine.append((cells, voxel_keys(points_map[new][first], self.voxel_m)))
        self.scans += 1
        if len(self._pending_hit) >= 32:
            self.flush()
        return new

    def flush(self) -> None:
        """Merge the pending scans into the counts."""
        if not self._pending_hit:
            return
        from blockloc.maps._raycast_kernels import merge_counts

        # each scan's keys come sorted: merged pairwise (linear merges, a tree of them), then into
        # the counts, instead of sorting every pending key again with the counts' keys (~0.3 s a
        # flush on the small world: the p99 of a scan's cost)
        parts = [_counted(h, True) for h in self._pending_hit] + [_counted(f, False) for f in self._pending_free]
        self._pending_hit, self._pending_free = [], []
        while len(parts) > 1:
            parts = [merge_counts(*parts[i], *parts[i + 1]) if i + 1 < len(parts) else parts[i]
                     for i in range(0, len(parts), 2)]
        keys, n_hit, n_free = merge_counts(self.keys, self.n_hit.astype(np.int64), self.n_free.astype(np.int64),
                                           *parts[0])
        self.keys, self.n_hit, self.n_free = keys, n_hit.astype(np.int32), n_free.astype(np.int32)

    def logodds(self, l_occ: float, l_free: float) -> np.ndarray:
        self.flush()
        return self.n_hit * l_occ + self.n_free * l_free

    def fine_m(self) -> float:
        return self.fine[1] if self.fine is not None else self.voxel_m / 2.5

    def new_cells(self) -> np.ndarray:
        """Sorted unique fine keys of every scan's new points."""
        return (unique_keys(np.concatenate([c for c, _ in self.new_fine])) if self.new_fine
                else np.zeros(0, np.int64))

    def new_counts(self, seen_free: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """(n_new, n_new_free): (V,) int64 in key order: scans with a new point in the voxel, and
        scans with a new point in a fine cell of the sorted ``seen_free`` (where the mapping
        day had in sight: :func:`seen_by_keyframes`; None: all)."""
        self.flush()
        n_any = np.zeros(len(self.keys), np.int64)
        n_ok = np.zeros(len(self.keys), np.int64)
        for cells, vk in self.new_fine:
            if not len(cells):
                continue
            a = unique_keys(vk)
            n_any[np.searchsorted(self.keys, a)] += 1
            if seen_free is None:
                n_ok[np.searchsorted(self.keys, a)] += 1
            else:
                ok = _in_sorted(cells, seen_free)
                b = unique_keys(vk[ok])
                n_ok[np.searchsorted(self.keys, b)] += 1
        return n_any, n_ok


def _counted(keys: np.ndarray, hit: bool) -> tuple:
    """(sorted unique keys, n_hit, n_free) of one scan's hit (``hit``) or free keys, each key
    counted as often as it occurs."""
    keys = np.asarray(keys, np.int64).ravel()
    if len(keys) > 1 and not (keys[1:] > keys[:-1]).all():
        keys, n = np.unique(np.sort(keys), return_counts=True)
        n = n.astype(np.int64)
    else:
        n = np.ones(len(keys), np.int64)
    zero = np.zeros(len(keys), np.int64)
    return (keys, n, zero) if hit else (keys, zero, n)


def segments_clear(origins: np.ndarray, targets: np.ndarray, fine_keys: np.ndarray, fine_m: float,
                   margin_m: float, chunk: int = 2048) -> np.ndarray:
    """(N,) bool: the segment from each of ``origins`` (N, 3) to its target (N, 3), up to
    ``margin_m`` short of the target, crosses none of the sorted occupied ``fine_keys`` (cells of
    edge ``fine_m``): the target was in sight from the origin. Sampled every ``fine_m / 2``."""
    origins = np.asarray(origins, np.float64).reshape(-1, 3)
    targets = np.asarray(targets, np.float64).reshape(-1, 3)
    d = targets - origins
    length = np.linalg.norm(d, axis=1)
    usable = length - margin_m
    u = d / np.maximum(length, 1e-9)[:, None]
    step = fine_m / 2.0
    clear = np.ones(len(d), bool)
    for s in range(0, len(d), chunk):
        sl = slice(s, s + chunk)
        top = float(usable[sl].max()) if len(usable[sl]) else 0.0
        if top <= 0:
            continue
        t = (np.arange(int(np.ceil(top / step))) + 0.5) * step
        ray, j = np.nonzero(t[None, :] < usable[sl, None])
        pts = origins[sl][ray] + u[sl][ray] * t[j, None]
        blocked = unique_keys(ray[_in_sorted(voxel_keys(pts, fine_m), fine_keys)])
        clear[s + blocked] = False
    return clear


def seen_by_keyframes(cells: np.ndarray, fine_m: float, keyframes: np.ndarray, fine_keys: np.ndarray,
                      margin_m: float, max_range_m: float = 40.0, k: int = 3, sectors: int = 0,
                      pool: int = 64, up: np.ndarray | None = None, chunk: int = 8192) -> np.ndarray:
    """The sorted fine ``cells`` (edge ``fine_m``) the mapping day could see: in clear sight
    (:func:`segments_clear` through the map's occupied ``fine_keys``) from one of the ``k``
    keyframes (K, 3 sensor positions) nearest to it within ``max_range_m``, or, with
    ``sectors``, from the nearest keyframe of one of ``sectors`` equal azimuth sectors around the
    cell (about ``up``, (3,) unit vector against gravity in the map frame; None: the map's z
    axis), among its ``pool`` nearest keyframes within range. Where the mapping day saw through
    a cell and the map holds nothing there, it saw free space; where the map's structure hid the
    cell, a point there today is merely new to the map, not added.

    Why the sectors: the nearest keyframes are one stretch of one road. When a wall stands
    between that road and the cell, every one of them is hidden, while the drive saw the cell
    from another road (small world seed 2 loc_m3: a site fence 12 m behind a wall from the
    nearest road, seen from the cross road 15-20 m away; docs/bench/lifelong.md, detect7)."""
    from scipy.spatial import cKDTree

    cells = np.asarray(cells, np.int64)
    kf = np.asarray(keyframes, np.float64).reshape(-1, 3)
    if not len(cells) or not len(kf):
        return np.zeros(0, np.int64)
    centres = (unpack_keys(cells) + 0.5) * fine_m
    tree = cKDTree(kf)
    k = min(int(k), len(kf))
    dist, idx = tree.query(centres, k=k)
    dist, idx = dist.reshape(len(cells), k), idx.reshape(len(cells), k)
    seen = np.zeros(len(cells), bool)
    for j in range(k):  # the nearest keyframe first; the next ones only for cells still hidden
        todo = np.flatnonzero(~seen & (dist[:, j] <= max_range_m))
        if len(todo):
            seen[todo] = segments_clear(kf[idx[todo, j]], centres[todo], fine_keys, fine_m, margin_m)
    if sectors > 0:
        e1, e2 = tangent_basis(np.array([0.0, 0.0, 1.0]) if up is None else np.asarray(up, np.float64).reshape(3))
        m = min(int(pool), len(kf))
        hidden = np.flatnonzero(~seen)
        for c0 in range(0, len(hidden), chunk):  # (cells x pool) arrays a chunk of cells at a time
            todo = hidden[c0:c0 + chunk]
            d2, i2 = tree.query(centres[todo], k=m, distance_upper_bound=max_range_m)
            d2, i2 = d2.reshape(len(todo), m), i2.reshape(len(todo), m)
            ok = np.isfinite(d2)  # sorted by distance; past the range: inf, index len(kf)
            i2 = np.where(ok, i2, 0)
            v = kf[i2] - centres[todo][:, None, :]
            az = np.arctan2(v @ e2, v @ e1)
            sector = np.minimum(((az + np.pi) / (2 * np.pi) * sectors).astype(np.int64), sectors - 1)
            for s in range(sectors):  # the nearest keyframe of each sector, for cells still hidden
                inside = ok & (sector == s)
                first = np.argmax(inside, axis=1)
                rows = np.flatnonzero(inside.any(axis=1) & ~seen[todo])
                if len(rows):
                    seen[todo[rows]] = segments_clear(kf[i2[rows, first[rows]]], centres[todo[rows]], fine_keys,
                                                      fine_m, margin_m)
    return cells[seen]


def cluster_labels(keys: np.ndarray) -> np.ndarray:
    """(K,) int label of the 26-connected cluster each of the sorted unique ``keys`` belongs to
    (labels 0..C-1)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    keys = np.asarray(keys, dtype=np.int64)
    if not len(keys):
        return np.zeros(0, np.int64)
    ijk = unpack_keys(keys)
    rows, cols = [], []
    for off in _NEIGHBOURS:
        if not off.any():
            continue
        nb = pack_keys(ijk + off)
        j = np.searchsorted(keys, nb)
        j = np.minimum(j, len(keys) - 1)
        hit = keys[j] == nb
        rows.append(np.flatnonzero(hit))
        cols.append(j[hit])
    r, c = np.concatenate(rows), np.concatenate(cols)
    g = coo_matrix((np.ones(len(r), np.int8), (r, c)), shape=(len(keys), len(keys)))
    return connected_components(g, directed=False)[1].astype(np.int64)


def cluster_sizes(keys: np.ndarray) -> np.ndarray:
    """(K,) size of the 26-connected cluster each of the sorted unique ``keys`` belongs to."""
    label = cluster_labels(keys)
    return np.bincount(label)[label] if len(label) else np.zeros(0, np.int64)


@dataclass(frozen=True)
class Thresholds:
    """Decision thresholds (module docstring). l_occ / l_free: log-odds per scan hit / free."""

    l_occ: float = 0.85
    l_free: float = -0.4
    min_scans: int = 5
    removed_logodds: float = 2.0
    added_logodds: float = 2.0
    min_block_voxels: int = 8  # the bench's truth: a block changed with this many truth voxels
    min_cluster_voxels: int = 8  # removed / added voxels in smaller 26-connected clusters are noise
    #: removed needs the voxel (nearly) empty today: this session's scans hit it in at most this
    #: share of the scans that saw it (rays pass through a tree crown and stop in it by chance),
    #: and no map voxel next to it hit in more (a crown's edge next to its core)
    max_hit_share: float = 0.1
    #: a block is confirmed when one 26-connected cluster of its changed voxels (removed and
    #: added together) spans this volume, m^3 (scattered noise never forms one that large)
    min_block_m3: float = 1.0  # chosen on the small world seed 1, loc_m12 (docs/bench/lifelong.md)
    #: removed needs map structure: a voxel holding at least this many of the map's occupied fine
    #: cells, or one next to such a removed voxel (an object's edge). A voxel with one or two map
    #: points is the mapping day's sensor noise (mixed pixels at depth edges, a laser's angle
    #: error over far ground, a range tail) as often as structure; today's rays cross it.
    min_map_cells: int = 4  # chosen on the small world seed 1, loc_m12
    #: a removed cluster is kept only when at least this share of its voxels hold
    #: ``min_map_cells`` map fine cells: a removed object is a surface the map held densely
    #: (median 6-8 fine cells a voxel on the small world), while the mapping day's mixed pixels
    #: behind crown edges pile up, over a drive, into clouds of voxels holding one to three
    #: cells, a few of them dense enough to pass ``min_map_cells`` and carry their neighbours
    min_solid_share: float = 0.5
    #: a voxel holding the ground's surface (:func:`ground_voxels`) is no see-through neighbour
    #: that spares the voxels next to it (``max_hit_share``'s second rule)
    ground_spares_none: bool = True
    #: a map voxel spares its removed neighbours (``max_hit_share``'s second rule) only when hit
    #: in at least this many scans: one stray return (a mixed pixel, the ground's noise just over
    #: the ground band, a grazing ray) in a voxel seen by five scans kept whole sides of removed
    #: cars (campus loc_m12 block 013; small seed 1 loc_m12: removed recall 0.54 -> 0.86 at
    #: precision 1.00; docs/bench/lifelong.md, detect5)
    solid_min_hits: int = 2  # chosen on campus loc_m12 and small seed 1 loc_m12
    #: ... and holds at least this many of the map's occupied fine cells (0: any map voxel). The
    #: ground a removed car hid on the mapping day holds one or two of the map's cells (the car's
    #: lowest edge) and is hit today: it kept the car's side as a crown's edge (campus loc_m12
    #: block 000; docs/bench/lifelong.md, detect6)
    solid_min_cells: int = 2  # chosen on campus loc_m12
    #: a voxel holding the ground's surface can be removed
    ground_removable: bool = False
    #: the ground's surface: fine cells this many cells above the lowest of their column or less
    ground_band_cells: int = 1  # chosen on the small world seed 1, loc_m12
    #: added needs the new point's cell in sight from one of this many nearest mapping keyframes
    seen_keyframes: int = 3
    #: ... or from the nearest keyframe of one of this many azimuth sectors around the cell (among
    #: its ``seen_pool`` nearest within range; 0: off): the nearest keyframes are one stretch of
    #: one road, all hidden by the same wall where the drive saw the place from another road
    #: (small world seed 2 loc_m3 block 002, a site's fence; docs/bench/lifelong.md, detect7)
    seen_sectors: int = 8  # chosen on small seed 2 loc_m3
    seen_pool: int = 64
    #: a removed cluster lying as a sheet over the ground (:func:`ground_sheets`: at most this many
    #: voxels per occupied vertical column on average, 0: rule off) ...
    sheet_voxels_per_column: float = 1.2  # with sheet_height_m: the largest pair leaving campus loc_m12's blocks as they were
    #: ... with its voxels' median height above the map's local ground at most this, m, is not
    #: removed structure: it is the mapping day's mixed pixels between the ground and a crown or a
    #: trunk standing behind it (the range drawn part of the way to the nearer return), piled up
    #: over the drive's passes into a layer 0.1-1 m over the ground that today's rays cross.
    #: Removed structure stands up: a wall, a car's sides, a hedge fill two or more voxels a column
    #: (seed 2's sheets: 1.0-1.14 voxels a column, median 0.1-0.3 m; a removed car on the campus
    #: loc_m12 run can look as flat: 1.25 / 1.0 m lost one of its changed blocks)
    sheet_height_m: float = 0.5


@dataclass
class VoxelChanges:
    """Classified voxels: sorted int64 keys of each class (module docstring), voxel edge m."""

    voxel_m: float
    removed: np.ndarray
    added: np.ndarray
    dynamic: np.ndarray
    logodds: dict  # class -> (K,) float log-odds of its voxels, in key order
    added_hits: np.ndarray  # (len(added),) scans that hit each added voxel
    removed_free: np.ndarray  # (len(removed),) scans that saw through each removed voxel


def ground_voxels(voxel_m: float, fine_m: float, ground_fine: np.ndarray) -> np.ndarray:
    """Sorted keys (edge ``voxel_m``) of the voxels holding one of the ground's fine cells
    (``ground_fine``: sorted keys of edge ``fine_m``, :func:`ground_band`)."""
    return unique_keys(voxel_keys((unpack_keys(ground_fine) + 0.5) * fine_m, voxel_m))


def map_cells_per_voxel(keys: np.ndarray, voxel_m: float, fine_m: float, fine_keys: np.ndarray) -> np.ndarray:
    """(K,) how many of the sorted fine keys (edge ``fine_m``: the map's occupied fine cells) lie
    in each voxel of ``keys`` (edge ``voxel_m``)."""
    if not len(fine_keys) or not len(keys):
        return np.zeros(len(keys), np.int64)
    owner = voxel_keys((unpack_keys(fine_keys) + 0.5) * fine_m, voxel_m)
    uk, cnt = np.unique(owner, return_counts=True)
    j = np.minimum(np.searchsorted(uk, keys), len(uk) - 1)
    return np.where(uk[j] == keys, cnt[j], 0)


def ground_sheets(keys: np.ndarray, label: np.ndarray, voxel_m: float, ground_fine: np.ndarray,
                  fine_m: float, up: np.ndarray, max_per_column: float, max_height_m: float) -> np.ndarray:
    """(C,) bool per cluster label (``label``: (K,) labels 0..C-1 of the sorted ``keys``, voxels
    of edge ``voxel_m``): the cluster lies as a sheet over the ground. Its voxels fill at most
    ``max_per_column`` of its vertical columns' voxels on average, and their median height (the
    voxel's bottom) above the map's local ground (the lowest of ``ground_fine``, the ground band's
    fine cells of edge ``fine_m``, in the voxel's column) is at most ``max_height_m``. A voxel over
    no ground cell has no height and counts as high. False for every cluster when gravity is not
    along a map axis. up: (3,) unit vector against gravity."""
    keys = np.asarray(keys, np.int64)
    n_c = int(label.max()) + 1 if len(label) else 0
    up = np.asarray(up, float).reshape(3)
    axis = int(np.argmax(np.abs(up)))
    if not n_c or not len(ground_fine) or abs(up[axis]) < 0.9:
        return np.zeros(n_c, bool)
    sign = int(np.sign(up[axis]))
    other = [a for a in range(3) if a != axis]
    # the local ground: the lowest ground cell (its bottom, metres up) under each voxel column
    g = unpack_keys(ground_fine)
    g_lo = g[:, axis] * sign * fine_m if sign > 0 else (g[:, axis] * sign - 1) * fine_m
    g_col = pack_keys(np.c_[np.floor((g[:, other] + 0.5) * fine_m / voxel_m).astype(np.int64),
                            np.zeros(len(g), np.int64)])
    col_u, inv = np.unique(g_col, return_inverse=True)
    low = np.full(len(col_u), np.inf)
    np.minimum.at(low, inv, g_lo)
    v = unpack_keys(keys)
    v_lo = v[:, axis] * sign * voxel_m if sign > 0 else (v[:, axis] * sign - 1) * voxel_m
    v_col = pack_keys(np.c_[v[:, other], np.zeros(len(v), np.int64)])
    j = np.minimum(np.searchsorted(col_u, v_col), max(len(col_u) - 1, 0))
    height = np.where(col_u[j] == v_col, v_lo - low[j], np.inf)
    out = np.zeros(n_c, bool)
    cols = np.unique(np.c_[label, v_col], axis=0)
    n_cols = np.bincount(cols[:, 0], minlength=n_c)
    per_col = np.bincount(label, minlength=n_c) / np.maximum(n_cols, 1)
    for c in np.flatnonzero(per_col <= max_per_column):
        out[c] = np.median(height[label == c]) <= max_height_m
    return out


def _solid_or_next_to_solid(keys: np.ndarray, removed: np.ndarray, voxel_m: float, fine: tuple,
                            min_cells: int) -> np.ndarray:
    """(K,) bool over ``keys``: a removed voxel holding ``min_cells`` map fine cells or more, or
    26-next to one that does (``removed``: (K,) bool candidates; ``fine``: :class:`Evidence`'s)."""
    out = np.zeros(len(keys), bool)
    cand = np.flatnonzero(removed)
    solid = cand[map_cells_per_voxel(keys[cand], voxel_m, fine[1], fine[2]) >= min_cells]
    out[solid] = True
    rest = np.setdiff1d(cand, solid)
    if len(rest) and len(solid):
        out[rest[near_sorted(keys[rest], keys[solid])]] = True
    return out


def classify(ev: Evidence, map_keys: np.ndarray, map_free_fine: np.ndarray | None, th: Thresholds) -> VoxelChanges:
    """Removed / added / dynamic voxels from the evidence. map_keys: sorted unique keys of the
    map's occupied voxels; map_free_fine: sorted fine keys (``ev.fine_m()``) of the scans' new
    points' cells the mapping day had in sight (:func:`seen_by_keyframes`), or None (any new
    point counts).

    Added is decided on the new points (:class:`Evidence`), not on whole voxels off the map: a
    parked car's lowest half metre shares its voxel with the map's ground (and the next half
    metre is that voxel's neighbour), yet its points are off the ground's fine cells, in cells
    the map's rays crossed."""
    L = ev.logodds(th.l_occ, th.l_free)
    in_map = np.isin(ev.keys, map_keys)
    seen = np.maximum(ev.n_hit + ev.n_free, 1)
    removed = (in_map & (ev.n_free >= th.min_scans) & (L <= -th.removed_logodds)
               & (ev.n_hit <= th.max_hit_share * seen))
    # ... and next to no map voxel this session still hits: the edge of a see-through crown,
    # crossed by few rays, can go unhit in every scan while its core is hit. The ground is no
    # porous object: a voxel holding the ground's surface does not spare its neighbours (else a
    # removed car's lower metre, next to the ground, could never be removed)
    cand = np.flatnonzero(removed)
    if len(cand):
        solid = (in_map & (ev.n_hit + ev.n_free >= th.min_scans) & (ev.n_hit > th.max_hit_share * seen)
                 & (ev.n_hit >= th.solid_min_hits))
        if th.solid_min_cells > 0 and ev.fine is not None and solid.any():
            # ... and holds the map's structure: a voxel the map barely holds (the ground a
            # removed car hid, new today) is no crown's core
            sel = np.flatnonzero(solid)
            solid[sel[map_cells_per_voxel(ev.keys[sel], ev.voxel_m, ev.fine[1], ev.fine[2]) < th.solid_min_cells]] = False
        ground = ground_voxels(ev.voxel_m, ev.fine[1], ev.ground) if ev.fine is not None and ev.ground is not None else None
        if th.ground_spares_none and ground is not None:
            solid &= ~_in_sorted(ev.keys, ground)
        removed[cand[near_sorted(ev.keys[cand], ev.keys[solid])]] = False
        if not th.ground_removable and ground is not None:
            removed &= ~_in_sorted(ev.keys, ground)
    if th.min_map_cells > 1 and ev.fine is not None and removed.any():
        removed &= _solid_or_next_to_solid(ev.keys, removed, ev.voxel_m, ev.fine, th.min_map_cells)
    n_new, n_new_free = ev.new_counts(map_free_fine)
    L_added = n_new_free * th.l_occ + ev.n_free * th.l_free
    added = (n_new_free >= th.min_scans) & (L_added >= th.added_logodds)
    L_new = n_new * th.l_occ + ev.n_free * th.l_free
    # dynamic: off the map's voxels and their neighbours (there, new points seen free again are
    # mostly ground the removed structure had hidden); dynamic voxels are only reported
    near_map = np.isin(ev.keys, dilate_keys(map_keys)) if len(map_keys) else np.zeros(len(ev.keys), bool)
    dynamic = ~near_map & (n_new >= 1) & (ev.n_free >= 2) & (L_new < th.added_logodds) & ~added
    for m in (removed, added):  # scattered voxels are noise (a grazing ray, a mixed pixel)
        sel = np.flatnonzero(m)
        m[sel[cluster_sizes(ev.keys[sel]) < th.min_cluster_voxels]] = False
    if th.min_solid_share > 0 and ev.fine is not None and removed.any():
        # a removed cluster must be mostly map structure, not a cloud of the mapping day's noise
        sel = np.flatnonzero(removed)
        label = cluster_labels(ev.keys[sel])
        solid = map_cells_per_voxel(ev.keys[sel], ev.voxel_m, ev.fine[1], ev.fine[2]) >= th.min_map_cells
        share = np.bincount(label, weights=solid) / np.bincount(label)
        removed[sel[share[label] < th.min_solid_share]] = False
    if (th.sheet_voxels_per_column > 0 and ev.fine is not None and ev.ground is not None
            and ev.up is not None and removed.any()):
        sel = np.flatnonzero(removed)
        label = cluster_labels(ev.keys[sel])
        flat = ground_sheets(ev.keys[sel], label, ev.voxel_m, ev.ground, ev.fine[1], ev.up,
                             th.sheet_voxels_per_column, th.sheet_height_m)
        removed[sel[flat[label]]] = False
    return VoxelChanges(ev.voxel_m, ev.keys[removed], ev.keys[added], ev.keys[dynamic],
                        {"removed": L[removed], "added": L_added[added], "dynamic": L_new[dynamic]},
                        n_new_free[added].astype(np.int64), ev.n_free[removed].astype(np.int64))


def block_report(changes: VoxelChanges, block_keys: dict, block_keyframes: dict,
                 block_points: dict, th: Thresholds) -> list[dict]:
    """Per-block changes (what ``changes.json`` lists).

    block_keys: block id -> sorted unique keys of its occupied voxels. block_keyframes: block id ->
    (K, 3) keyframe positions (added and dynamic voxels go to the block of the nearest keyframe).
    block_points: block id -> (N, 3) its points (removed points are counted from them).
    Each dict: block, removed_voxels, removed_m3, removed_points (map points in them),
    added_voxels, added_m3, added_hits (scan hits in them, summed), dynamic_voxels, confidence (mean occupancy probability of the changed voxels' verdict: 0.5
    unsure, 1 certain), largest_change_m3 (the volume of the largest 26-connected cluster of the
    block's removed and added voxels together), confirmed (``largest_change_m3 >= min_block_m3``:
    one coherent changed object, not a count of scattered voxels that noise over a large block
    reaches).
    """
    from scipy.spatial import cKDTree

    v3 = changes.voxel_m ** 3
    ids = list(block_keys)
    kf, owner = [], []
    for b in ids:
        k = np.asarray(block_keyframes.get(b, np.zeros((0, 3))), float).reshape(-1, 3)
        kf.append(k)
        owner += [b] * len(k)
    kf = np.concatenate(kf) if kf else np.zeros((0, 3))
    owner = np.asarray(owner, dtype=object)

    def nearest_block(keys):
        if not len(keys) or not len(kf):
            return np.zeros(0, dtype=object)
        centres = (unpack_keys(keys) + 0.5) * changes.voxel_m
        return owner[cKDTree(kf).query(centres)[1]]

    add_owner = nearest_block(changes.added)
    dyn_owner = nearest_block(changes.dynamic)
    p_of = lambda L: 1.0 / (1.0 + np.exp(-np.abs(L)))  # noqa: E731
    out = []
    for b in ids:
        rm = np.isin(changes.removed, block_keys[b], assume_unique=True)
        ad = add_owner == b
        dy = dyn_owner == b
        pts = block_points.get(b)
        n_rm_pts = 0
        if pts is not None and rm.any():
            n_rm_pts = int(np.isin(voxel_keys(pts, changes.voxel_m), changes.removed[rm]).sum())
        Ls = np.concatenate([changes.logodds["removed"][rm], changes.logodds["added"][ad]])
        both = unique_keys(np.concatenate([changes.removed[rm], changes.added[ad]]))
        largest_m3 = float(cluster_sizes(both).max() * v3) if len(both) else 0.0
        out.append({"block": b, "removed_voxels": int(rm.sum()), "removed_m3": round(float(rm.sum() * v3), 3),
                    "removed_points": n_rm_pts, "added_voxels": int(ad.sum()),
                    "added_m3": round(float(ad.sum() * v3), 3),
                    "added_hits": int(changes.added_hits[ad].sum()),
                    "dynamic_voxels": int(dy.sum()),
                    "confidence": round(float(p_of(Ls).mean()), 3) if len(Ls) else 0.0,
                    "largest_change_m3": round(largest_m3, 3),
                    "confirmed": largest_m3 >= th.min_block_m3})
    return out
