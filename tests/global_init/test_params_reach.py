"""Every field of the ``global_init`` config section reaches the code that uses it.

The section is global initialization's own dataclass (``GlobalInitParams``; the localizer's
``InitParams`` extends it). A field renamed on one side only would stop being read: a recording
``InitParams`` notes every field the localizer reads over a hinted search (verified) and a
no-hint search that nothing verifies (every place stage, then the regions' fallback). The few
fields read only on branches a small synthetic map does not take, or by the caller of
``localize``, are named below and must at least be read somewhere in ``blockloc/``."""

from __future__ import annotations

import ast
import dataclasses
from pathlib import Path

from blockloc.config import Config, GlobalInitConfig, RegistrationConfig
from blockloc.geometry import xyzrpy_to_T
from blockloc.global_init.params import GlobalInitParams, InitParams
from blockloc.global_init.relocalize import GlobalLocalizer

from .synthetic import GRAVITY_Z_DOWN, Z_DOWN, gravity_body, scan_from, world_up

SECTION = {f.name for f in dataclasses.fields(GlobalInitParams)}
# read by the caller that hands the hinted window to localize (session, ``blockloc init``)
BY_THE_CALLER = {"window_m", "yaw_window_deg"}
# read only when a plausible rival of a verified best shows up (none in this map), or when a search
# ends with a best whose coverage could not be judged and whose fit is not strong (the clear best:
# ``test_climb.py``)
RARE = {"ambiguity_z", "unjudged_clear_best", "unjudged_end_min_fitness", "unjudged_end_min_structure_fitness", "unjudged_end_margin"}


class Recording(InitParams):
    def __getattribute__(self, name):
        if name in SECTION:
            READ.add(name)
        return object.__getattribute__(self, name)


READ: set = set()


def _params(**changes) -> Recording:
    base = InitParams.from_config(Config().global_init, RegistrationConfig())
    return Recording(**{**{f.name: getattr(base, f.name) for f in dataclasses.fields(InitParams)}, **changes})


def test_the_global_init_section_is_the_localizers_dataclass():
    assert GlobalInitConfig is GlobalInitParams and issubclass(InitParams, GlobalInitParams)
    gi = Config().global_init
    p = InitParams.from_config(gi, RegistrationConfig(num_threads=3))
    assert all(getattr(p, name) == getattr(gi, name) for name in SECTION) and p.num_threads == p.refine_workers == 3


def test_every_global_init_field_reaches_the_localizer():
    READ.clear()
    m = world_up(seed=3) @ Z_DOWN.T
    T_true = xyzrpy_to_T(6.0, 4.0, -(1.9 + 0.02 * 6.0), 0.03, -0.02, 2.4)
    scan, g = scan_from(m, T_true), gravity_body(T_true)
    res = GlobalLocalizer.for_points(m, GRAVITY_Z_DOWN, _params()).localize(scan, g, hint_xy=(10.0, 0.0))
    assert res.verified
    # No-hint, nothing can verify: every place stage, then the regions' fallback.
    params = _params(min_fitness=0.999, place_candidates=(2, 4), place_all_yaw_candidates=2,
                     reloc_window_m=60.0, max_regions=1, max_search_s=0.0)
    res = GlobalLocalizer.for_points(m, GRAVITY_Z_DOWN, params).localize(scan, g)
    assert not res.verified and res.stats["regions_searched"] == 1
    assert SECTION - READ - BY_THE_CALLER - RARE == set()

    # What the runs above do not read is read by the code all the same (by attribute name).
    attrs = set()
    for path in Path("blockloc").rglob("*.py"):
        if path.name in ("params.py", "config.py"):
            continue
        attrs |= {n.attr for n in ast.walk(ast.parse(path.read_text())) if isinstance(n, ast.Attribute)}
    assert (BY_THE_CALLER | RARE) - READ <= attrs
