"""The place index: what a scan would see at sample places of the map, for no-hint relocalization.

Descriptor (Scan Context's polar layout, Kim and Kim 2018). In the levelled frame (z up, see
``projection``), map structure in a *static* height band above the local ground (default 2-4 m:
above pedestrians, cars, bins and fences, whose trails and parked copies fill accumulated maps but
change between sessions; walls, trunks, poles and crowns stay) is a 2D occupancy raster at 0.5 m.
Around a place, the raster is binned into rings (``ring_width_m``) and azimuth sectors
(``num_sectors``) between ``min_range_m`` and ``max_range_m``: one bit per bin, set when an occupied
cell covers it. A place stores two such bit sets: of the raster itself, and of the raster grown by
``tolerance_m`` (a disk), which is where a scan taken up to that far from the place can see
structure. A scan gives the same bits from its own band cells (the same tables), plus *free* bits:
bins it saw through, in front of its first hit in each sector, shrunk by the tolerance.

Matching (every place, every column shift s = a yaw). A log-likelihood ratio per observed scan bit,
of "taken at this place, turned by s" against "taken anywhere": an occupied scan bit falls on the
place's grown bits with probability ``coverage`` here and with the place's density (per ring)
elsewhere; a free scan bit falls on the place's own bits with probability ``see_through`` here
and with its density elsewhere. So dense places, which explain any scan by chance, are discounted,
and places with structure where the scan saw through are penalised. No rotation-invariant key
prefilters the places: the match is asymmetric (a scan sees part of what the map holds), which a
KD-tree over keys cannot express, and bit counting over every place and shift is fast (numba).
The best shift is the yaw estimate (sub-sector by a parabola through the maximum).

Open places. Where the static band holds fewer than ``min_bits`` bits (open stretches: lawns,
squares, a street between thinned trees), a place is described in ``open_band_m`` instead (default
0.5-4 m: fences, hedges, bushes, posts and the little that stands higher), the same bits and the
same matching; a scan's cells in that band are matched against these places, its static-band cells
against the others, and both rank in one list (the score is per observed bit either way). Such a
band holds what changes between sessions (parked cars), which the matching model's ``coverage``
absorbs and verification, unchanged, still judges.

Places. Along the mapping keyframes (block maps record them per entry) every
``keyframe_spacing_m``, and on a ``spacing_m`` grid over the drivable area: cells whose ground was
seen, with no structure within ``clearance_m``, with at least ``min_bits`` bits, and, when the map
has keyframes, within ``max_offset_m`` of one with a clear line of sight to it (the localization
route may leave the mapping route; a place behind a wall was never seen).

Stored as the map store extra ``place_index.npz`` (``MapStore.load_extra`` checks its sha256):
:func:`write_place_index` builds and adds it to a local store (after ``map build``, or for
``blockloc map index MAP``); :func:`load_place_index` reads it, or builds and caches one for a map
without.
"""

from __future__ import annotations

import io
import json
import logging
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from blockloc.errors import GlobalInitError, MapError
from blockloc.fileio import load_arrays
from blockloc.global_init.place_descriptors import (  # noqa: F401  (pack, unpack, scan_descriptor: re-exported)
    PlaceIndexParams,
    ScanCells,
    _disk,
    _tables,
    best_shift,
    descriptors_on_raster,
    match_scores,
    pack,
    scan_cells,
    scan_descriptor,
    unpack,
)

log = logging.getLogger(__name__)

PLACE_INDEX_NAME = "place_index.npz"
FORMAT = "blockloc-place-index"
FORMAT_VERSION = 3  # 2: the "vertical" projection of the band; 3: open places (``band``)
READS_VERSIONS = (2, 3)  # a version-2 index loads as one without open places
TILE_M = 256.0  # the index is built tile by tile: memory bounded by the tile, not the map
@dataclass
class PlaceCandidate:
    """A place that looks like the scan.

    x, y: the place in the map frame (m). yaw: the body's yaw in the map frame there (rad), from the
    best column shift (NaN from :meth:`PlaceIndex.query_cells`, which knows no body tilt). score:
    log-likelihood ratio per observed scan bit (higher is better; > 0: more likely here than
    anywhere). xy_L: (2,) the place in the levelled frame; theta: the levelled scan's rotation into
    the levelled frame (rad; what branch and bound searches). index: row in the index.
    """

    x: float
    y: float
    yaw: float
    score: float
    xy_L: np.ndarray
    theta: float
    index: int


# ----------------------------------------------------------------------------- the index


@dataclass
class PlaceIndex:
    """Places and their descriptors. xy_L: (P, 2) float32 places in the levelled frame (m), on
    lattice corners; source: (P,) uint8 (0 keyframe, 1 grid); bits, grown: (P, rings, W) uint64
    polar occupancy of the raster and of the raster grown by the tolerance; gravity_map: (3,) the
    map's gravity the levelled frame comes from; stats: build figures; band: (P,) uint8, 0 the
    static band, 1 ``open_band_m`` (an open place; None: all static)."""

    params: PlaceIndexParams
    gravity_map: np.ndarray
    xy_L: np.ndarray
    source: np.ndarray
    bits: np.ndarray
    grown: np.ndarray
    stats: dict = field(default_factory=dict)
    band: np.ndarray | None = None

    def __post_init__(self):
        from blockloc.global_init.projection import R_level_from_gravity

        self.R_L_map = R_level_from_gravity(self.gravity_map)
        self._densities = None
        self._llr_weights = None
        if self.band is None:
            self.band = np.zeros(len(self.xy_L), np.uint8)

    def __len__(self) -> int:
        return len(self.xy_L)

    def densities(self) -> tuple[np.ndarray, np.ndarray]:
        """(P, rings) float32 share of set bits per ring of ``grown`` and of ``bits``."""
        if self._densities is None:
            from blockloc.global_init import _kernels as K

            S = self.params.num_sectors
            self._densities = (K.popcounts(self.grown).astype(np.float32) / S,
                               K.popcounts(self.bits).astype(np.float32) / S)
        return self._densities

    def llr_weights(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(occ_hit, occ_miss, free_hit, free_miss), each (P, rings) float32: the log-likelihood
        ratio's weights of every place (:func:`match_scores`), computed once (they depend on the
        index alone, not on the scan)."""
        if self._llr_weights is None:
            from blockloc.global_init.place_descriptors import llr_weights

            dens_grown, dens_raw = self.densities()
            self._llr_weights = (llr_weights(self.params.coverage, dens_grown)
                                 + llr_weights(self.params.see_through, dens_raw))
        return self._llr_weights

    def subset(self, rows: np.ndarray) -> "PlaceIndex":
        """The places ``rows`` ((K,) indices or (P,) mask) alone, same parameters. A place's match
        scores are its own (its bits and densities), so they equal those in the whole index."""
        sub = PlaceIndex(self.params, self.gravity_map, self.xy_L[rows], self.source[rows], self.bits[rows],
                         self.grown[rows], dict(self.stats), self.band[rows])
        if self._densities is not None:
            sub._densities = (self._densities[0][rows], self._densities[1][rows])
        if self._llr_weights is not None:  # elementwise of the densities: the rows' own
            sub._llr_weights = tuple(w[rows] for w in self._llr_weights)
        return sub

    # -- serialization -------------------------------------------------------------------

    def to_bytes(self) -> bytes:
        """A compressed .npz (no pickles): arrays plus a JSON header of the parameters.

        The same index gives the same bytes (a serial and a Dask build of a map are compared byte
        for byte): zip entries carry a fixed date and the header leaves out the build time."""
        import zipfile

        stats = {k: v for k, v in self.stats.items() if k != "build_s"}
        meta = {"format": FORMAT, "version": FORMAT_VERSION, "params": asdict(self.params),
                "gravity_map": [float(v) for v in self.gravity_map], "stats": stats}
        arrays = {"meta": np.frombuffer(json.dumps(meta, sort_keys=True).encode(), np.uint8),
                  "xy_L": self.xy_L.astype(np.float32), "source": self.source.astype(np.uint8),
                  "bits": np.ascontiguousarray(self.bits, np.uint64).view(np.uint8),
                  "grown": np.ascontiguousarray(self.grown, np.uint64).view(np.uint8),
                  "band": self.band.astype(np.uint8)}
        buf = io.BytesIO()
        with zipfile.ZipFile(buf, "w") as zf:
            for name, arr in arrays.items():
                member = io.BytesIO()
                np.lib.format.write_array(member, np.ascontiguousarray(arr), allow_pickle=False)
                info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
                info.compress_type = zipfile.ZIP_DEFLATED
                info.external_attr = 0o600 << 16
                zf.writestr(info, member.getvalue())
        return buf.getvalue()

    @classmethod
    def from_bytes(cls, data: bytes, where: str = PLACE_INDEX_NAME) -> "PlaceIndex":
        """Parse :meth:`to_bytes` output; MapError naming ``where`` when it is not one."""
        try:
            z = load_arrays(io.BytesIO(data))
            meta = json.loads(bytes(z["meta"]).decode())
            xy, src, raw, grown = z["xy_L"], z["source"], z["bits"], z["grown"]
            band = z.get("band")
        except (OSError, ValueError, KeyError, UnicodeDecodeError, EOFError) as exc:
            raise MapError(f"{where}: not a place index ({exc})") from None
        if not isinstance(meta, dict) or meta.get("format") != FORMAT:
            got = meta.get("format") if isinstance(meta, dict) else None
            raise MapError(f"{where}: not a place index (format {got!r})")
        version = meta.get("version")
        if version not in READS_VERSIONS:
            raise MapError(f"{where}: place index version {version!r}, this blockloc reads "
                           f"{', '.join(map(str, READS_VERSIONS))}; rebuild it with 'blockloc map index'")
        if version == 3 and band is None:
            raise MapError(f"{where}: place index version 3 without its 'band' array; "
                           "rebuild it with 'blockloc map index'")
        if version < 3:
            log.info("%s: place index version %s has no open places (open stretches are not indexed); "
                     "'blockloc map index' rebuilds it", where, version)
        try:
            p = dict(meta["params"])
            p["band_m"] = tuple(p["band_m"])
            # version 2 knew no open band; a version-3 header says its own
            p["open_band_m"] = tuple(p["open_band_m"]) if p.get("open_band_m") is not None else None
            params = PlaceIndexParams(**p)
            gravity = np.asarray(meta["gravity_map"], float).reshape(3)
        except (KeyError, TypeError, ValueError, GlobalInitError) as exc:
            raise MapError(f"{where}: bad place index header ({exc})") from None
        P, NR, W = len(xy), params.num_rings, params.words
        if xy.shape != (P, 2) or src.shape != (P,) or raw.dtype != np.uint8 or grown.dtype != np.uint8 \
                or raw.shape != (P, NR, 8 * W) or grown.shape != raw.shape \
                or (band is not None and band.shape != (P,)):
            raise MapError(f"{where}: place index arrays disagree (xy {xy.shape}, source {src.shape}, "
                           f"bits {raw.shape}, grown {grown.shape}, band {None if band is None else band.shape}; "
                           f"{NR} rings of {params.num_sectors} sectors)")

        def words(a):
            return np.ascontiguousarray(a).view(np.uint64).reshape(P, NR, W)

        return cls(params, gravity, xy.astype(np.float32), src.astype(np.uint8), words(raw), words(grown),
                   meta.get("stats", {}), None if band is None else band.astype(np.uint8))

    # -- queries ---------------------------------------------------------------------------

    def query(self, points_body: np.ndarray, gravity_body: np.ndarray, k: int = 10) -> list[PlaceCandidate]:
        """The ``k`` places (at least ``nms_m`` apart) that look most like a scan, best first.

        points_body: (N, 3) body frame, metres; gravity_body: (3,) gravity in the body frame.
        """
        sc = self.scan_cells(points_body, gravity_body)
        cands = self.query_cells(sc, k)
        for c in cands:
            c.yaw = self.yaw_map(c.theta, sc.R_tilt)
        return cands

    def scan_cells(self, points_body: np.ndarray, gravity_body: np.ndarray) -> "ScanCells":
        """:func:`scan_cells` with this index's parameters."""
        return scan_cells(points_body, gravity_body, self.params)

    def yaw_map(self, theta: float, R_tilt: np.ndarray) -> float:
        """Map-frame yaw (rad) of a body whose levelled scan turns by ``theta`` into the levelled frame."""
        c, s = math.cos(theta), math.sin(theta)
        R = self.R_L_map.T @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ R_tilt
        return float(math.atan2(R[1, 0], R[0, 0]))

    def scores(self, cells: "ScanCells", static=None) -> np.ndarray:
        """(P, S) :func:`match_scores` of a scan's cells at every place and shift: the static
        band's cells against the static places, the open band's against the open places (module
        docstring); ``static``: the static band's :func:`scan_descriptor` when made already."""
        p = self.params
        if static is None:
            static = scan_descriptor(cells.band, p, cells.obstacles, cells.free_from_m)
        open_rows = np.flatnonzero(self.band == 1)
        if len(open_rows) == 0 or cells.open_band is None:
            score = match_scores(static, self)
            if len(open_rows):
                score[open_rows] = -1e6  # a scan without open-band cells cannot match them (ranked last)
            return score
        score = np.empty((len(self), p.num_sectors), np.float32)
        rows = np.flatnonzero(self.band != 1)
        score[rows] = match_scores(static, self, rows)
        score[open_rows] = match_scores(scan_descriptor(cells.open_band, p, cells.obstacles, cells.free_from_m),
                                        self, open_rows)
        return score

    def thin_static(self, cells: "ScanCells", static=None) -> bool:
        """Whether a scan's static band holds fewer than ``min_bits`` bits (what makes a place open)
        while the index holds open places: its static and open scores are then ranked side by side
        (:meth:`query_cells`), neither trusted over the other. ``static``: as in :meth:`scores`."""
        if cells.open_band is None or not np.any(self.band == 1) or not np.any(self.band == 0):
            return False
        p = self.params
        if static is None:
            static = scan_descriptor(cells.band, p, cells.obstacles, cells.free_from_m)
        occupied = static.counts(p.num_sectors)[0]
        return bool(occupied.sum() < p.min_bits)

    def query_cells(self, cells: "ScanCells", k: int = 10, nms_m: float = 4.0,
                    theta_window: tuple[float, float] | None = None) -> list[PlaceCandidate]:
        """Top ``k`` places for a scan's cells (:meth:`scan_cells`), at least ``nms_m`` apart, best
        first; ``theta_window`` (centre, width) rad restricts the yaw."""
        if len(self) == 0 or k <= 0:
            return []
        p = self.params
        S = p.num_sectors
        static = scan_descriptor(cells.band, p, cells.obstacles, cells.free_from_m)  # made once, used twice
        score = self.scores(cells, static)
        allowed = None
        if theta_window is not None and theta_window[1] < 2 * math.pi:
            ang = np.arange(S) * 2 * math.pi / S - theta_window[0]
            allowed = np.abs((ang + math.pi) % (2 * math.pi) - math.pi) <= 0.5 * theta_window[1] + math.pi / S
        best, shift = best_shift(score, allowed)
        order = np.argsort(-best, kind="stable")
        if self.thin_static(cells, static):
            # A handful of static bits scores high per bit at sparse static places by chance (campus:
            # 20 bits, 1.2 per bit, the true open place at rank 8342), yet 12 bits found the true
            # static place first on another frame: the two rankings alternate.
            order = _alternate(order[self.band[order] == 0], order[self.band[order] == 1])
        from blockloc.global_init import _kernels as K

        # the best places at least nms_m apart, best first
        kept = K.greedy_nms(self.xy_L.astype(np.float64), order.astype(np.int64), float(nms_m), int(k))
        out: list[PlaceCandidate] = []
        for o in kept:
            xy = self.xy_L[o].astype(np.float64)
            m = self.R_L_map.T @ np.r_[xy, 0.0]
            out.append(PlaceCandidate(float(m[0]), float(m[1]), float("nan"), float(best[o]), xy,
                                      float(shift[o] * 2 * math.pi / S), int(o)))
        return out


def _alternate(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a[0], b[0], a[1], b[1], ..., then the rest of the longer one."""
    n = min(len(a), len(b))
    both = np.empty(2 * n, dtype=a.dtype)
    both[0::2], both[1::2] = a[:n], b[:n]
    return np.concatenate([both, a[n:], b[n:]])


# ----------------------------------------------------------------------------- building


def build_place_index(store, gravity_map, params: PlaceIndexParams | None = None, *,
                      cache_dir=None) -> PlaceIndex:
    """The place index of a map store (block or grid; keyframes from block entries when recorded).

    gravity_map: (3,) gravity in the map frame (NCLT and the simulator: (0, 0, +9.81)). The
    per-entry rasters are global init's (built or loaded from its on-disk cache, see ``maps``).
    """
    from blockloc.global_init.maps import StoreMap

    params = params or PlaceIndexParams()
    source = StoreMap(store, gravity_map, params.projection_params, cache_dir)
    kf = [e.keyframes for e in store.entries if e.keyframes is not None and len(e.keyframes)]
    return build_place_index_from_source(source, gravity_map, params,
                                         np.concatenate(kf) if kf else None)


def write_place_index(path, gravity_map, params: PlaceIndexParams | None = None, *, cache_dir=None):
    """Build the place index of the local store at ``path`` and add it to the store (replacing an
    older one; atomic, see ``blockloc.maps.store.add_extra``). For right after ``map build`` and for
    ``blockloc map index MAP``. Returns (the reopened MapStore, the PlaceIndex)."""
    from blockloc.maps.store import add_extra, open_map

    store = open_map(path)
    index = build_place_index(store, gravity_map, params, cache_dir=cache_dir)
    return add_extra(path, PLACE_INDEX_NAME, index.to_bytes()), index


def build_place_index_from_source(source, gravity_map, params: PlaceIndexParams,
                                  keyframes_map: np.ndarray | None = None) -> PlaceIndex:
    """Place index of a global-init map source (``StoreMap`` or ``ArrayMap``): see the module
    docstring. keyframes_map: (K, 3) mapping sensor positions, map frame, metres, or None."""
    from scipy.ndimage import binary_dilation
    from scipy.spatial import cKDTree

    from blockloc.global_init import _kernels as K

    t0 = time.perf_counter()
    p = params
    res = p.resolution_m
    lo_L, hi_L = source.bounds_L()
    R_L_map = source.R_L_map
    kf_xy = None
    if keyframes_map is not None and len(keyframes_map):
        kf_xy = (np.asarray(keyframes_map, float).reshape(-1, 3) @ R_L_map.T)[:, :2]
    # Candidate places: along the keyframes, then the grid (on lattice corners: multiples of res).
    cand, kinds = [], []
    if kf_xy is not None:
        _, first = np.unique(np.floor(kf_xy / p.keyframe_spacing_m).astype(np.int64), axis=0, return_index=True)
        cand.append(kf_xy[np.sort(first)])
        kinds.append(np.zeros(len(first), np.uint8))
    step = max(1, int(round(p.spacing_m / res))) * res
    gx = np.arange(math.ceil(lo_L[0] / step), math.floor(hi_L[0] / step) + 1) * step
    gy = np.arange(math.ceil(lo_L[1] / step), math.floor(hi_L[1] / step) + 1) * step
    grid = np.array(np.meshgrid(gx, gy, indexing="ij")).reshape(2, -1).T
    if kf_xy is not None:
        d, nearest = cKDTree(kf_xy).query(grid, distance_upper_bound=p.max_offset_m)
        grid, nearest = grid[np.isfinite(d)], nearest[np.isfinite(d)]
        if cand:
            dk, _ = cKDTree(cand[0]).query(grid, distance_upper_bound=0.5 * p.spacing_m)
            grid, nearest = grid[~np.isfinite(dk)], nearest[~np.isfinite(dk)]
    cand.append(grid)
    kinds.append(np.ones(len(grid), np.uint8))
    xy = np.concatenate(cand) if cand else np.zeros((0, 2))
    kind = np.concatenate(kinds) if kinds else np.zeros(0, np.uint8)
    corner = np.round(xy / res).astype(np.int64)
    anchor = np.full((len(xy), 2), np.nan)
    if kf_xy is not None:
        anchor[kind == 1] = kf_xy[nearest]
    n_cand = len(xy)

    # Tile by tile: the base raster of the tile plus the profile reach.
    tab = _tables(p)
    margin = tab.radius + 2
    clear_cells = int(math.ceil(p.clearance_m / res))
    keep = np.zeros(len(xy), bool)
    band = np.zeros(len(xy), np.uint8)
    bits = np.zeros((len(xy), p.num_rings, p.words), np.uint64)
    grown = np.zeros_like(bits)
    disk = _disk(p.tolerance_m / res)
    open_source = None if p.open_band_m is None else source.with_params(p.open_projection_params)
    tile = int(TILE_M / res)
    c_lo = np.floor(lo_L / res).astype(np.int64)
    c_hi = np.floor(hi_L / res).astype(np.int64) + 1
    for tx in range(int(c_lo[0]), int(c_hi[0]) + 1, tile):
        for ty in range(int(c_lo[1]), int(c_hi[1]) + 1, tile):
            inside = np.flatnonzero((corner[:, 0] >= tx) & (corner[:, 0] < tx + tile)
                                    & (corner[:, 1] >= ty) & (corner[:, 1] < ty + tile))
            if len(inside) == 0:
                continue
            lo = np.array([tx, ty]) - margin
            hi = np.array([tx, ty]) + tile + margin
            try:
                origin, base = source.base_raster(lo, hi)
            except GlobalInitError:
                continue  # no map entry here
            occ = base == 255
            ci = corner[inside] - origin
            ok = _drivable(occ, ci, clear_cells, source, xy[inside], anchor[inside], origin, res,
                           kind[inside] == 0)
            ci, inside = ci[ok], inside[ok]
            if len(inside) == 0:
                continue
            desc = descriptors_on_raster(occ, ci, p)
            good = K.popcounts(desc).sum(axis=1) >= p.min_bits
            bits[inside[good]] = desc[good]
            grown[inside[good]] = descriptors_on_raster(binary_dilation(occ, disk), ci[good], p)
            keep[inside[good]] = True
            if open_source is not None and not np.all(good):
                _open_places(open_source, lo, hi, ci[~good], inside[~good], xy, p, clear_cells, disk,
                             keep, band, bits, grown)
        for src in (source, open_source):
            if hasattr(src, "release"):
                src.release()  # the pieces stay in the on-disk cache
    index = PlaceIndex(p, np.asarray(gravity_map, float).reshape(3), (corner[keep] * res).astype(np.float32),
                       kind[keep], bits[keep], grown[keep], band=band[keep])
    index.stats = {"build_s": round(time.perf_counter() - t0, 3), "candidates": int(n_cand),
                   "places": int(keep.sum()), "keyframe_places": int(np.sum(kind[keep] == 0)),
                   "grid_places": int(np.sum(kind[keep] == 1)), "open_places": int(np.sum(band[keep] == 1))}
    log.info("place index: %d places (%d along keyframes, %d open) of %d candidates in %.1f s", keep.sum(),
             index.stats["keyframe_places"], index.stats["open_places"], n_cand, index.stats["build_s"])
    return index


def _open_places(open_source, lo, hi, ci, rows, xy, p: PlaceIndexParams, clear_cells: int, disk,
                 keep, band, bits, grown) -> None:
    """Describe the places ``rows`` (raster corners ``ci`` (n, 2) of the tile [lo, hi)) that the
    static band left featureless in ``open_band_m`` instead (module docstring): those with
    ``min_bits`` bits there and no open-band structure within the clearance (not on a fence or in a
    hedge). Fills ``keep``, ``band``, ``bits``, ``grown`` in place."""
    from scipy.ndimage import binary_dilation, maximum_filter

    from blockloc.global_init import _kernels as K

    try:
        origin, base = open_source.base_raster(lo, hi)
    except GlobalInitError:
        return
    occ = base == 255
    ci = ci + (np.asarray(lo, np.int64) - origin)  # the same tile: origin == lo
    near = maximum_filter(occ, size=max(2 * clear_cells, 1), mode="constant", cval=False)
    i = np.clip(ci[:, 0], 0, occ.shape[0] - 1)
    j = np.clip(ci[:, 1], 0, occ.shape[1] - 1)
    clear = ~near[i, j]
    ci, rows = ci[clear], rows[clear]
    if len(rows) == 0:
        return
    desc = descriptors_on_raster(occ, ci, p)
    good = K.popcounts(desc).sum(axis=1) >= p.min_bits
    if not np.any(good):
        return
    bits[rows[good]] = desc[good]
    grown[rows[good]] = descriptors_on_raster(binary_dilation(occ, disk), ci[good], p)
    keep[rows[good]] = True
    band[rows[good]] = 1


def _drivable(occ: np.ndarray, ci: np.ndarray, clear_cells: int, source, xy_L: np.ndarray,
              anchor_L: np.ndarray, origin: np.ndarray, res: float, is_keyframe: np.ndarray) -> np.ndarray:
    """Which places (raster corners ci (P, 2)) are drivable: ground seen, no structure within the
    clearance (unless a keyframe place), and (grid places of maps with keyframes: ``anchor_L``
    finite) a clear 2D line of sight to their keyframe."""
    from scipy.ndimage import maximum_filter

    # An even window covers offsets -c..c-1: the cells within c of corner (i, j), which touches
    # cells i-1..i and j-1..j.
    near = maximum_filter(occ, size=max(2 * clear_cells, 1), mode="constant", cval=False)
    i = np.clip(ci[:, 0], 0, occ.shape[0] - 1)
    j = np.clip(ci[:, 1], 0, occ.shape[1] - 1)
    ok = ~near[i, j] | is_keyframe  # the mapping sensor stood at a keyframe place
    ok &= np.isfinite(source.ground_at(xy_L))
    los = np.isfinite(anchor_L[:, 0]) & ok
    if np.any(los):
        a, b = anchor_L[los], xy_L[los]
        n = int(np.ceil(np.max(np.hypot(*(b - a).T)) / (0.5 * res))) + 1
        u = np.linspace(0.0, 1.0, max(n, 2))[None, :, None]
        pts = a[:, None, :] + u * (b - a)[:, None, :]
        cells = np.floor(pts / res).astype(np.int64) - origin
        inside = np.all((cells >= 0) & (cells < np.array(occ.shape)), axis=2)
        cells = np.clip(cells, 0, np.array(occ.shape) - 1)
        blocked = np.any(occ[cells[..., 0], cells[..., 1]] & inside, axis=1)
        idx = np.flatnonzero(los)
        ok[idx[blocked]] = False
    return ok


def load_place_index(store, gravity_map, params: PlaceIndexParams | None = None, cache_dir=None,
                     build_missing: bool = True) -> PlaceIndex | None:
    """The store's place index: its extra when present, else built once and kept in the on-disk
    cache (a warning suggests ``blockloc map index``); None when ``build_missing`` is False and the
    store has none. MapError when the stored index is corrupt (checksum) or unreadable."""
    from blockloc.global_init.maps import default_cache_dir

    if store.has_extra(PLACE_INDEX_NAME):
        index = PlaceIndex.from_bytes(store.load_extra(PLACE_INDEX_NAME), store.files.url(PLACE_INDEX_NAME))
        g = np.asarray(gravity_map, float)
        if np.linalg.norm(index.gravity_map / np.linalg.norm(index.gravity_map) - g / np.linalg.norm(g)) > 1e-3:
            raise MapError(f"{store.files.url(PLACE_INDEX_NAME)}: built for gravity {index.gravity_map.tolist()}, "
                           f"the sequence says {g.tolist()}; rebuild it with 'blockloc map index'")
        return index
    if not build_missing:
        return None
    import hashlib

    params = params or PlaceIndexParams()
    ident = hashlib.sha256(json.dumps([[e.id, e.sha256 or f"{e.num_points}:{e.bytes}"] for e in store.entries]
                                      + [asdict(params), np.round(np.asarray(gravity_map, float), 6).tolist(),
                                         FORMAT_VERSION]).encode()).hexdigest()[:24]
    root = default_cache_dir() / "global_init" if cache_dir is None else Path(cache_dir)
    path = root / "place_index" / f"{ident}.npz"
    if path.exists():
        try:
            return PlaceIndex.from_bytes(path.read_bytes(), str(path))
        except (OSError, MapError) as exc:
            log.warning("ignoring unreadable cached place index %s (%s)", path, exc)
    log.warning("%s has no place index: building one (store it with 'blockloc map index %s')", store.path,
                store.path)
    index = build_place_index(store, gravity_map, params, cache_dir=cache_dir)
    try:
        from blockloc.fileio import atomic_write_bytes

        atomic_write_bytes(path, index.to_bytes())
    except OSError as exc:  # a read-only cache only costs time
        log.warning("cannot cache the place index at %s (%s)", path, exc)
    return index


def index_for_source(source, params: PlaceIndexParams | None = None) -> PlaceIndex:
    """The place index of a global-init map source: a ``StoreMap``'s stored (or cached) index, or
    one built in memory for an ``ArrayMap``."""
    params = params or PlaceIndexParams()
    store = getattr(source, "store", None)
    if store is not None:
        return load_place_index(store, source.gravity_map, params, cache_dir=source.cache_dir)
    return build_place_index_from_source(source.with_params(params.projection_params), source.gravity_map,
                                         params, source.keyframes_map)
