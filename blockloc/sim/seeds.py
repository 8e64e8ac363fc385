"""The simulator's seeding: every random draw comes from a generator seeded by
``SeedSequence([seed, stable_hash(name), stream])``, so a world, a session's day or a frame is a
pure function of (preset, seed, session, index), the same in every process."""

from __future__ import annotations

import zlib


def stable_hash(text: str) -> int:
    """A process-independent 32-bit hash of ``text`` (Python's hash() is salted)."""
    return zlib.crc32(text.encode("utf-8"))
