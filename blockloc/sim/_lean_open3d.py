"""open3d imported for the simulator's workers without its plotly viewer.

``import open3d`` imports ``open3d.visualization.draw_plotly``, which imports dash, plotly and
IPython: ~1.3 s of a 2.6 s import (``python -X importtime -c "import open3d"``, load ~15), paid
by the workers' fork server before any worker starts (``blockloc.sim.parallel.PRELOAD``). The
workers only cast rays. Importing this module first puts a stand-in for ``draw_plotly`` in
``sys.modules``; its functions import the real module when first called, so nothing of open3d
is missing, only imported later.

Nothing here is loaded by the CLI or by a process that imported open3d already (then it does
nothing).
"""

from __future__ import annotations

import importlib
import sys
import types

_NAME = "open3d.visualization.draw_plotly"
#: What ``open3d.visualization`` takes from ``draw_plotly`` (open3d 0.17-0.20).
_NAMES = ("get_plotly_fig", "draw_plotly", "draw_plotly_server")


def _real(attr: str):
    """The real ``draw_plotly.<attr>`` (imported now, in place of the stand-in)."""
    mod = sys.modules.get(_NAME)
    if getattr(mod, "_blockloc_stand_in", False):
        del sys.modules[_NAME]
        real = importlib.import_module(_NAME)
        # importing the submodule bound ``open3d.visualization.draw_plotly`` to it; open3d's own
        # import then binds the names to its functions, as here
        pkg = sys.modules["open3d.visualization"]
        for name in _NAMES:
            setattr(pkg, name, getattr(real, name))
    return getattr(importlib.import_module(_NAME), attr)


def _forward(attr: str):
    def call(*args, **kwargs):
        return _real(attr)(*args, **kwargs)

    call.__name__ = call.__qualname__ = attr
    call.__doc__ = f"open3d.visualization.{attr}, imported on first call (blockloc.sim._lean_open3d)."
    return call


def install() -> bool:
    """Put the stand-in in place unless open3d (or its viewer) is imported already; True if put."""
    if "open3d" in sys.modules or _NAME in sys.modules:
        return False
    stand_in = types.ModuleType(_NAME, "stand-in: see blockloc.sim._lean_open3d")
    stand_in._blockloc_stand_in = True
    for attr in _NAMES:
        setattr(stand_in, attr, _forward(attr))
    sys.modules[_NAME] = stand_in
    return True


install()
from blockloc.open3d_loader import open3d  # noqa: E402  (after the stand-in: that is the point)

open3d()
