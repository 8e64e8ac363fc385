"""The hinted search (``GlobalLocalizer.localize`` with a position hint).

A hint is a constraint on the no-hint search, not another search: the map's place index, cut to
the places inside the hint's window (a square of ``window_m`` around the hint, levelled frame) and,
with a yaw hint, to the yaw window, ranks them; the no-hint place stages (``no_hint``) search small
windows around the best of them, and every leaf refined lies inside the hint's window. The same
refinement and verification follow. Plain branch and bound over the whole window
(``_search_region``) runs only where the place stages cannot answer: the window holds no indexed
place, the map has no index (``use_place_index`` false), the places gave nothing verified and
nothing ambiguous (a pose between places the index does not describe well), or (``search_on_doubt``)
their candidates verified but left the result ambiguous, or verified a best whose static-band
coverage was not judged and whose fit is not strong (``search_on_unjudged``, as without a hint).

Why: branch and bound over a 40 x 40 m window at every yaw scores ~1.5M nodes a scan at full
HDL-32E density (3.2 s median on the small world, docs/bench/global_init.md), while the index
picks the right place and its yaw among a few dozen in the window in milliseconds.

:class:`HintedSearch` is a base of :class:`blockloc.global_init.relocalize.GlobalLocalizer`; it
uses the localizer's ``params``, ``place_index``, ``_relocalize_places``, ``_search_region``,
``_decide`` and ``_decide_unless_doubted``, and sets ``_leaf_box``, which ``_refine`` honours.
"""

from __future__ import annotations

import time

import numpy as np

from blockloc.global_init.projection import ScanProjection
from blockloc.global_init.verify import InitResult

# stats keys that add up over the place stages and the branch and bound
_SUMMED = ("bnb_time_s", "refine_time_s", "nodes_visited", "pyramid_time_s")


class HintedSearch:
    """The hinted search of a localizer (module docstring)."""

    _leaf_box: tuple[np.ndarray, np.ndarray] | None = None

    def _localize_hinted(self, scan: ScanProjection, scan_ndt: np.ndarray, cells, center: np.ndarray,
                         window_m: float, theta_c: float, yaw_win: float, t0: float,
                         points_body: np.ndarray | None = None) -> InitResult:
        """Search the window of side ``window_m`` (m) around ``center`` (2,) (levelled frame, m) at
        rotations ``theta_c`` +- ``yaw_win`` / 2 (rad). ``t0``: ``time.perf_counter()`` at the start
        of the search (the result's ``time_s`` counts from it)."""
        p = self.params
        half = 0.5 * window_m
        stats: dict = {"hint_window_m": window_m}
        rows = np.zeros(0, np.int64)
        if p.use_place_index:
            index = self.place_index  # loaded by the caller, outside the search's time
            stats["index_load_s"] = self._index_load_s
            xy = index.xy_L.astype(np.float64)
            rows = np.flatnonzero(np.all(np.abs(xy - center) <= half, axis=1))
        stats["places_in_window"] = int(len(rows))
        cands = []
        dense = None  # the scan's every point, once the search went on
        if len(rows):
            self._leaf_box = (center - half, center + half)
            try:
                cands, stats = self._relocalize_places(scan, scan_ndt, cells, index.subset(rows), theta_c, yaw_win,
                                                       stats, candidates=p.hint_place_candidates)
            finally:
                self._leaf_box = None
            stats["hint_search"] = "places"
            res = self._decide(list(cands), stats, 0.0, scan_ndt, final=False)
            if res.verified or res.ambiguous:
                # A verified best whose static-band coverage was not judged stands only on a strong
                # fit, as without a hint (defaults' map, --rng 13, hinted frame 25176 with 8 m place
                # windows: a place 23 m off, fitness 0.77, coverage not judged, stood; the window's
                # branch and bound finds the truth, fitness 0.92).
                out, stands = self._decide_unless_doubted(cands, stats, t0, scan_ndt, scan, cells, p.search_on_doubt,
                                                          doubt_unjudged=p.search_on_unjudged)
                if stands:
                    return out
                # Ambiguous among the places (campus, nominal-mounting map, frames 14583 and 20179:
                # verified candidates along a street): the places are not all the window holds, so
                # its branch and bound goes on and the decision judges everything found, with every
                # test as before (as the no-hint search goes on, ``_search_on``).
                cands = list(out.candidates)
                stats["searched_on"] = True
                dense = self._dense_points(points_body)
        more, st = self._search_region(scan, scan_ndt, center, window_m, theta_c, yaw_win, cells=cells)
        stats.update({k: v + stats.get(k, 0) if k in _SUMMED else v for k, v in st.items()})
        stats["hint_search"] = "places, then branch and bound" if len(rows) else "branch and bound"
        stats["regions_searched"] = 1
        return self._decide(cands + more, stats, time.perf_counter() - t0, scan_ndt, scan=scan, cells=cells,
                            dense_points=dense)

    def _in_leaf_box(self, x: float, y: float) -> bool:
        """Whether a 2D leaf (levelled frame, m) may be refined: inside the hint's window, if any."""
        box = self._leaf_box
        return box is None or bool(box[0][0] <= x <= box[1][0] and box[0][1] <= y <= box[1][1])
