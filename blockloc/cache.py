"""Where generated data is cached, and keys that change when the code or parameters that made it do.

The demo, the tests and the benchmarks reuse a simulated world and its maps across runs. A cache
entry is keyed by a fingerprint of the source of the modules that produced it plus their
parameters, so a change to the simulator or the map builder never serves stale data.
"""

from __future__ import annotations

import hashlib
import importlib.util
import os
from pathlib import Path


def cache_root() -> Path:
    """``$BLOCKLOC_CACHE`` or ``~/.cache/blockloc``."""
    root = os.environ.get("BLOCKLOC_CACHE")
    return Path(root).expanduser() if root else Path.home() / ".cache" / "blockloc"


def _module_files(name: str) -> list[Path]:
    spec = importlib.util.find_spec(name)
    if spec is None or spec.origin is None:
        raise ImportError(f"no module named {name!r}")
    if spec.submodule_search_locations:
        return sorted(p for d in spec.submodule_search_locations for p in Path(d).rglob("*.py"))
    return [Path(spec.origin)]


def fingerprint(*modules: str, params: object = None) -> str:
    """10 hex digits over the source files of ``modules`` (packages: all their .py files) and
    ``repr(params)``. The same code and parameters give the same key on every machine."""
    h = hashlib.sha256()
    for name in modules:
        for path in _module_files(name):
            h.update(path.name.encode())
            h.update(path.read_bytes())
    h.update(repr(params).encode())
    return h.hexdigest()[:10]
