"""The no-hint search's stages (``GlobalLocalizer.localize`` without a position hint).

The map's place index ranks the places that look like the scan, with a yaw guess each; one branch
and bound runs over small windows around the best ``place_candidates[0]`` of them (yaw within
``place_yaw_window_deg`` of the guess), then, while nothing is verified, around more of them
(``place_candidates[1]``; later stages also refine the best leaves by 2D score beyond the first
places), then around the first ``place_all_yaw_candidates`` of them at every yaw, then around the
rest of ``place_candidates``; only then
(``whole_map_fallback``) are square regions tiling the map searched in the order of a cheap score
(the best coarse bound of a subsampled scan over coarse angles) until one gives a verified match
or ``max_search_s`` has passed.

:class:`NoHintSearch` is a base of :class:`blockloc.global_init.relocalize.GlobalLocalizer`; it
uses the localizer's ``params``, ``map``, ``_search_region``, ``_refine`` and ``_decide``.
"""

from __future__ import annotations

import math
import time

import numpy as np

from blockloc.errors import GlobalInitError
from blockloc.global_init.bnb import Candidate2D, Window, make_angles, required_cells, rotated_cells, search_windows
from blockloc.global_init.projection import ScanProjection
from blockloc.global_init.verify import InitCandidate
from blockloc.jit import NEVER, Deadline

GROUP_M = 400.0  # windows of the no-hint search share one pyramid crop per square of this side


class NoHintSearch:
    """The place stages and the regions' fallback of a localizer."""

    def _relocalize_places(self, scan: ScanProjection, scan_ndt: np.ndarray, cells, index, theta_c: float,
                           yaw_win: float, stats: dict, deadline: Deadline = NEVER,
                           candidates: tuple[int, ...] | None = None, flip_open: bool = False,
                           first_stage: int = 0, done: list[Candidate2D] | None = None):
        """No-hint search through the place index, widening stage by stage (module docstring) while
        ``deadline`` has not passed (``jit.Deadline``); ``candidates``: the stages' place counts
        (default ``place_candidates``); ``flip_open``: an open place's window is searched at its yaw
        guess reversed too (every yaw allowed). ``first_stage``: resume a search that stopped
        after that many stages (the candidates it returned are not returned again); ``done``: the
        2D leaves refined so far (a list the search extends: pass the same one to resume)."""
        p = self.params
        candidates = p.place_candidates if candidates is None else candidates
        yaw_guess = math.radians(p.place_yaw_window_deg)
        # A stage tries every yaw around the first few places (a yaw guess off by more than the
        # window: a weak or symmetric match; small world seed 2, frame 847: the true place ranked
        # first with its yaw guess 40 deg off, never searched at its yaw before the budget ran out).
        # Every yaw costs ~20 guessed windows each, hence only the first few places. It comes third,
        # after the second stage's more places at their guesses: a true place ranked lower is far
        # more common than a yaw guess that far off (campus, ten draws of 100 frames: 24 searches
        # ended at the second guessed stage, none at every yaw, which cost them 0.1-0.5 s each).
        stages = [(k, yaw_guess) for k in candidates]
        if p.place_all_yaw_candidates > 0:
            stages.insert(min(2, len(stages)), (p.place_all_yaw_candidates, min(yaw_win, 2 * math.pi)))
        if first_stage >= len(stages):
            return [], dict(stats, place_stage=first_stage)  # every stage was searched
        t = time.perf_counter()
        theta_window = (theta_c, yaw_win) if yaw_win < 2 * math.pi else None
        places = index.query_cells(cells, max(candidates), theta_window=theta_window)
        stats.update(place_query_s=time.perf_counter() - t, places=len(index), place_stage=0)
        if not places:
            return [], stats
        out: list[InitCandidate] = []
        done = [] if done is None else done
        k_done = max([k for k, yaw in stages[:first_stage] if yaw == yaw_guess], default=0)
        for i, (k, yaw) in enumerate(stages):
            if i < first_stage:
                continue
            if yaw >= min(yaw_win, 2 * math.pi) and yaw_guess >= min(yaw_win, 2 * math.pi) and i > 0:
                break  # the guesses' windows already covered every allowed yaw
            if i > 0 and deadline.passed():
                stats["timed_out"] = True
                break
            # The places not searched yet (a later yaw-only stage: its places again, at every yaw).
            first = k_done if yaw == yaw_guess else 0
            windows = [Window(c.xy_L, p.place_window_m, c.theta if yaw < 2 * math.pi else theta_c, yaw)
                       for c in places[first:k]]
            if flip_open and yaw < 2 * math.pi and yaw_win >= 2 * math.pi:
                # An open place's yaw guess may be the reverse one: its low band along an open street
                # looks alike both ways (campus, estimated-mounting map, frame 27961: the three true
                # places' guesses 180 deg off). Its window reversed follows it.
                both = []
                for c, w in zip(places[first:k], windows):
                    both.append(w)
                    if index.band[c.index] == 1:
                        both.append(Window(w.center, w.size_m, w.theta + math.pi, w.yaw_window))
                windows = both
            k_done = max(k_done, k) if yaw == yaw_guess else k_done
            if not windows:
                continue
            t = time.perf_counter()
            # A later stage also refines the best 2D leaves beyond its first places: where the scan's
            # static band is thin, the index ranks the true place low (campus frame 27961: 38th of
            # 64, its leaf the 4th best of 48 by 2D score).
            # After the first stage, ``place_later_top_k`` leaves each way: an open place's window
            # comes twice (``flip_open``), and a thin static band ranks the true place low (campus,
            # defaults' map, --rng 13, frames 16591 and 24995: the true places 13th and 34th, their
            # leaves 0.92 / 0.95 by 2D score, never refined with 6; a wrong place verified instead,
            # ambiguous). The first stage, which ends most searches, refines as before.
            top_k = p.place_top_k if i == 0 else max(p.place_top_k, p.place_later_top_k)
            c2d, st = self._search_windows(scan, windows, by_score=top_k if i > 0 else 0, top_k=top_k)
            stats["bnb_time_s"] = stats.get("bnb_time_s", 0.0) + time.perf_counter() - t
            stats["nodes_visited"] = stats.get("nodes_visited", 0) + st.nodes_visited
            t = time.perf_counter()
            out.extend(self._refine(c2d, scan, scan_ndt, cells, skip=done, ordered=p.place_leaves_per_window > 0))
            stats["refine_time_s"] = stats.get("refine_time_s", 0.0) + time.perf_counter() - t
            stats["place_stage"] = i + 1
            stats["windows"] = len(windows)
            stats["regions_searched"] = st.regions  # the GROUP_M squares holding windows
            res = self._decide(list(out), {}, 0.0, scan_ndt, final=False)
            if res.verified or res.ambiguous:
                break  # found; or two places fit (the caller may search on: ``_search_on``)
        return out, stats

    def _search_windows(self, scan: ScanProjection, windows: list[Window], by_score: int = 0,
                        top_k: int | None = None):
        """Branch and bound over the windows, one pyramid per group of nearby windows: the leaves
        to refine, at most ``top_k`` (default ``place_top_k``; best places first, with
        ``place_leaves_per_window``) and then the ``by_score`` best of the others by 2D score."""
        from blockloc.global_init.bnb import SearchStats

        p = self.params
        top_k = p.place_top_k if top_k is None else top_k
        r = p.resolution_m
        top = min(p.pyramid_levels - 1, p.place_top_level)
        reach = float(np.hypot(*scan.xy.T).max()) + (1 << top) * r + 2 * r
        # Windows (best place first) in groups spanning at most GROUP_M: one pyramid crop each,
        # however large the map.
        groups: list[tuple[np.ndarray, np.ndarray, list[Window]]] = []
        for w in windows:
            c = np.asarray(w.center, float)
            for g in groups:
                lo, hi = np.minimum(g[0], c), np.maximum(g[1], c)
                if np.all(hi - lo <= GROUP_M):
                    g[0][:], g[1][:] = lo, hi
                    g[2].append(w)
                    break
            else:
                groups.append((c.copy(), c.copy(), [w]))
        cands: list[Candidate2D] = []
        total = SearchStats(0, 0.0, 0, 0, 0.0, 0.0)
        best = 0.0
        rank = {id(w): i for i, w in enumerate(windows)}
        for _, _, ws in groups:
            c = np.array([w.center for w in ws])
            half = 0.5 * max(w.size_m for w in ws) + reach
            lo = np.floor((c.min(axis=0) - half) / r).astype(np.int64) - 2
            hi = np.floor((c.max(axis=0) + half) / r).astype(np.int64) + 3
            try:
                pyr = self.map.pyramid(lo, hi, top + 1)  # the levels above the roots' are never read
            except GlobalInitError:
                continue
            # Leaves below ambiguity_score_ratio x the best matter neither as the answer nor as its
            # runner-up (_refine would not refine them): prune them, across groups too.
            # (search_windows: per window, min_leaf_score is the best leaf itself; else the floor.)
            floor = best if p.place_leaves_per_window > 0 else p.ambiguity_score_ratio * best
            c2d, st = search_windows(pyr, scan.xy, ws, top_k, p.use_s0, p.s0_ratio, p.min_score, p.nms_m,
                                     p.nms_deg, max_range=scan.max_range, keep_ratio=p.ambiguity_score_ratio,
                                     min_leaf_score=floor, top_level=p.place_top_level,
                                     per_window_k=p.place_leaves_per_window)
            for c in c2d:
                c.window = rank[id(ws[c.window])] if c.window >= 0 else -1
            cands.extend(c2d)
            best = max([best] + [c.score for c in c2d])
            total = SearchStats(st.num_angles, st.angle_step_rad, total.num_roots + st.num_roots,
                                total.nodes_visited + st.nodes_visited, max(total.s0, st.s0),
                                total.time_s + st.time_s)
        total.regions = len(groups)
        cands = [c for c in cands if c.score >= p.ambiguity_score_ratio * best]
        if p.place_leaves_per_window > 0:
            # Best places first (the index's ranking sees free space, which the 2D score does not),
            # each window's leaves by score: a saturated window cannot take every refinement.
            cands.sort(key=lambda c: (c.window, -c.score))
        else:
            cands.sort(key=lambda c: -c.score)
        rest = sorted(cands[top_k:], key=lambda c: -c.score)[:by_score]
        return cands[:top_k] + rest, total

    def _relocalize(self, scan: ScanProjection, scan_ndt: np.ndarray, theta_c: float, yaw_win: float, cells=None,
                    deadline: Deadline = NEVER):
        """The regions' search (module docstring), region by region while before ``deadline``."""
        p = self.params
        w = p.reloc_window_m
        centers = self.map.region_centers(w)
        if len(centers) == 0:
            raise GlobalInitError("the map has no blocks/tiles to relocalize in")
        t = time.perf_counter()
        cheap = np.full(len(centers), -np.inf)
        for i, c in enumerate(centers):
            if deadline.passed():
                break  # the regions scored so far come first
            cheap[i] = self._cheap_score(scan, c, w)
        order = np.argsort(-cheap, kind="stable")
        if p.max_regions > 0:
            order = order[: p.max_regions]
        t_cheap = time.perf_counter() - t
        all_cands: list[InitCandidate] = []
        stats: dict = {"regions": len(centers), "cheap_time_s": t_cheap, "regions_searched": 0}
        for k, i in enumerate(order):
            if deadline.passed():
                stats["timed_out"] = True
                break
            # Regions overlap by the scan's reach, so a pose near a border is inside some window.
            cands, st = self._search_region(scan, scan_ndt, centers[i], w + 2.0 * p.resolution_m, theta_c, yaw_win,
                                            cells=cells)
            stats["regions_searched"] = k + 1
            for key in ("bnb_time_s", "refine_time_s", "nodes_visited"):
                stats[key] = stats.get(key, 0) + st[key]
            all_cands.extend(cands)
            if any(c.verified for c in cands):
                stats["found_in_rank"] = k + 1
                break
        return all_cands, stats

    def _cheap_score(self, scan: ScanProjection, center: np.ndarray, window_m: float) -> float:
        """Orders regions (prunes none): the best level-3 bound (4 m windows at 0.5 m cells) of a
        200-cell subsample over 128 angles and a 2^3-cell translation stride. The top level alone
        saturates over a 100 m region; this is still ~16M lookups per region."""
        from blockloc.global_init import _kernels as K

        p = self.params
        sub = scan.xy[:: max(1, len(scan.xy) // 200)]
        lo, hi = required_cells(sub, center, window_m, p.resolution_m)
        try:
            pyr = self.map.pyramid(lo, hi)
        except GlobalInitError:
            return 0.0
        angles, _ = make_angles(0.0, 2 * math.pi, 2 * math.pi / 128)
        cx, cy = rotated_cells(sub, angles, p.resolution_m)
        dx = (cx - pyr.origin[0]).astype(np.int32)
        dy = (cy - pyr.origin[1]).astype(np.int32)
        level = min(pyr.num_levels - 1, 3)
        r = p.resolution_m
        half = int(math.ceil(0.5 * window_m / r))
        c0 = np.floor(center / r).astype(np.int64)
        g = np.arange(-half, half + 1, 1 << level)
        gx, gy = np.meshgrid(c0[0] + g, c0[1] + g, indexing="ij")
        A = len(angles)
        n = gx.size
        ra = np.repeat(np.arange(A), n).astype(np.int64)
        rtx = np.tile(gx.ravel(), A).astype(np.int64)
        rty = np.tile(gy.ravel(), A).astype(np.int64)
        b = K.root_scores(pyr.levels, level, dx, dy, *K.scan_offsets(dx, dy, pyr.levels.shape[2]), ra, rtx, rty)
        return float(b.max()) / (255.0 * len(sub))
