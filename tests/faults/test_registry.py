"""The case registry that docs/robustness.md is generated from lists every test of the suite."""

from __future__ import annotations

import inspect


def test_every_fault_test_is_a_registered_case():
    from .report import load_registry

    entries = load_registry()
    names = {n.split("[")[0] for n, _ in entries}
    import sys

    package = __name__.rsplit(".", 1)[0]
    tests = {name for mod, m in list(sys.modules.items()) if mod.startswith(f"{package}.test_")
             for name, fn in inspect.getmembers(m, inspect.isfunction)
             if name.startswith("test_") and fn.__module__ == mod}
    tests.discard("test_every_fault_test_is_a_registered_case")
    assert tests - names == set()
    assert len(entries) >= 30 and len({n for n, _ in entries}) == len(entries)
