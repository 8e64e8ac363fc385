"""The fault cases, as data: what is injected, which finding of issues 16 and 40 it covers and what the
test asserts. ``docs/robustness.md`` is generated from this registry and a run of the suite
(``python -m tests.faults.report``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

#: The findings of issues 16 (1-7) and 40 (8-12), by number.
FINDINGS = {
    1: "silent deletion (replace only what blockloc made)",
    2: "one fault ends the run and discards it",
    3: "Ctrl-C / SIGTERM report success",
    4: "argument errors, --help, the README's options",
    5: "the simulator's ROS bags (another helper)",
    6: "smaller: binary CSV, gaps, config ranges, names, modes, plot, progress",
    7: "tests without the shared data",
    8: "issue 40: --overwrite deleted a user's files (ownership proven by a marker's content)",
    9: "issue 40: output folders checked before any work (writable, free space, not in use)",
    10: "issue 40: disk full, folder removed, permissions changed mid-run",
    11: "issue 40: inputs (no IMU file, a bad keyframe in a map build, PCD counts and headers)",
    12: "issue 40: the `latest` link (its signal messages: finding 3)",
}


@dataclass(frozen=True)
class Case:
    """One fault: ``id`` (the pytest id), the ``finding`` it covers, ``what`` is injected and
    what the test ``expect``s. For command-table cases: ``args`` of ``blockloc``, the exit
    ``code`` and a ``needle`` the one-line message must contain (the option or file named)."""

    id: str
    finding: int
    what: str
    expect: str
    args: tuple[str, ...] = ()
    code: int = 2
    needle: str | None = None
    files: dict = field(default_factory=dict, compare=False, hash=False)


#: (test function name, Case) of every registered case, in registration order.
REGISTRY: list[tuple[str, Case]] = []


def case(finding: int, what: str, expect: str) -> Callable:
    """Register a test function as one case (its name is its id)."""

    def mark(fn):
        _register(fn.__name__, Case(fn.__name__.removeprefix("test_"), finding, what, expect))
        return fn

    return mark


def table(test_name: str, cases: list[Case]) -> list[Case]:
    """Register a parametrized table (``test_name[case.id]`` each); returns ``cases``."""
    ids = [c.id for c in cases]
    assert len(set(ids)) == len(ids), f"duplicate case ids in {test_name}"
    for c in cases:
        _register(f"{test_name}[{c.id}]", c)
    return cases


def _register(name: str, c: Case) -> None:
    # a module imported a second time under another name registers nothing twice
    if all(n != name for n, _ in REGISTRY):
        REGISTRY.append((name, c))
